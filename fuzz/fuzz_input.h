// How the fuzz targets frame one multipart message in a flat input, and how the seed tool writes it:
// a sequence of parts, each a 4-byte little-endian length then that many bytes (a short last part
// takes what is left). At most 8 parts.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace prism::fuzz {

inline std::vector<std::string> SplitParts(const uint8_t* data, size_t size) {
  std::vector<std::string> parts;
  size_t at = 0;
  while (at < size && parts.size() < 8) {
    if (size - at < 4) {
      parts.emplace_back(reinterpret_cast<const char*>(data + at), size - at);
      break;
    }
    size_t n = static_cast<size_t>(data[at]) | static_cast<size_t>(data[at + 1]) << 8 |
               static_cast<size_t>(data[at + 2]) << 16 | static_cast<size_t>(data[at + 3]) << 24;
    at += 4;
    if (n > size - at) n = size - at;
    parts.emplace_back(reinterpret_cast<const char*>(data + at), n);
    at += n;
  }
  return parts;
}

inline std::string JoinParts(const std::vector<std::string>& parts) {
  std::string out;
  for (const std::string& p : parts) {
    const auto n = static_cast<uint32_t>(p.size());
    out += static_cast<char>(n & 0xFF);
    out += static_cast<char>((n >> 8) & 0xFF);
    out += static_cast<char>((n >> 16) & 0xFF);
    out += static_cast<char>((n >> 24) & 0xFF);
    out += p;
  }
  return out;
}

}  // namespace prism::fuzz
