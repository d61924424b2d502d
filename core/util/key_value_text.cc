#include "core/util/key_value_text.h"

#include <sstream>

namespace prism {

std::string TrimWhitespace(const std::string& s) {
  const size_t b = s.find_first_not_of(" \t\r\n"), e = s.find_last_not_of(" \t\r\n");
  return b == std::string::npos ? "" : s.substr(b, e - b + 1);
}

Status ForEachKeyValueLine(const std::string& text, const std::string& source, const std::string& separators,
                           const std::function<Status(const std::string& key, const std::string& value)>& fn) {
  std::istringstream in(text);
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    const size_t hash = line.find('#');
    if (hash != std::string::npos) line.resize(hash);
    line = TrimWhitespace(line);
    if (line.empty()) continue;
    const std::string where = source + ":" + std::to_string(n) + ": ";
    const size_t sep = line.find_first_of(separators);
    if (sep == std::string::npos) return InvalidArgumentError(where + "expected 'key = value', got '" + line + "'");
    if (Status s = fn(TrimWhitespace(line.substr(0, sep)), TrimWhitespace(line.substr(sep + 1))); !s.ok())
      return InvalidArgumentError(where + s.message());
  }
  return Status::Ok();
}

}  // namespace prism
