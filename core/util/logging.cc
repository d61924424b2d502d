#include "core/util/logging.h"

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <nlohmann/json.hpp>

#include "core/util/log_level.h"

namespace prism {
namespace {
std::atomic<int> g_min_level{static_cast<int>(LogLevel::kInfo)};
std::atomic<bool> g_json{false};

bool IsKeyChar(char c) { return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '.'; }

// Parses `key=value key="quoted \"value\"" ...` (the logs' convention). Returns false when any part of
// the message is not such a pair; a trailing free text after the pairs goes to `rest`.
bool ParseFields(const std::string& m, nlohmann::ordered_json* fields, std::string* rest) {
  size_t i = 0;
  bool any = false;
  while (i < m.size()) {
    while (i < m.size() && m[i] == ' ') ++i;
    if (i == m.size()) break;
    size_t k = i;
    while (k < m.size() && IsKeyChar(m[k])) ++k;
    if (k == i || k >= m.size() || m[k] != '=') {
      if (!any) return false;
      *rest = m.substr(i);
      return true;
    }
    const std::string key = m.substr(i, k - i);
    std::string value;
    size_t j = k + 1;
    bool quoted = false;
    if (j < m.size() && m[j] == '"') {
      quoted = true;
      ++j;
      while (j < m.size() && m[j] != '"') {
        if (m[j] == '\\' && j + 1 < m.size()) ++j;
        value += m[j++];
      }
      if (j < m.size()) ++j;  // the closing quote
    } else {
      while (j < m.size() && m[j] != ' ') value += m[j++];
    }
    char* end = nullptr;
    const double number = std::strtod(value.c_str(), &end);
    const bool is_number = !quoted && !value.empty() && end && *end == '\0' && std::isfinite(number);
    if (is_number && number == std::floor(number) && std::fabs(number) < 9e15)
      (*fields)[key] = static_cast<int64_t>(number);
    else if (is_number) (*fields)[key] = number;
    else if (!quoted && (value == "true" || value == "false")) (*fields)[key] = value == "true";
    else (*fields)[key] = value;
    any = true;
    i = j;
  }
  return any;
}

const char* LevelName(LogLevel level) {
  switch (level) {
    case LogLevel::kDebug:
      return "DEBUG";
    case LogLevel::kInfo:
      return "INFO";
    case LogLevel::kWarning:
      return "WARN";
    case LogLevel::kError:
      return "ERROR";
  }
  return "?";
}
}  // namespace

void SetMinLogLevel(LogLevel level) { g_min_level = static_cast<int>(level); }
LogLevel MinLogLevel() { return static_cast<LogLevel>(g_min_level.load()); }

bool SetLogFormat(const std::string& name) {
  if (name == "text") g_json = false;
  else if (name == "json") g_json = true;
  else return false;
  return true;
}

std::string FormatLogJson(const std::string& time, const char* level, const std::string& source,
                          const std::string& message) {
  nlohmann::ordered_json j;
  j["time"] = time;
  j["level"] = level;
  j["source"] = source;
  nlohmann::ordered_json fields = nlohmann::ordered_json::object();
  std::string rest;
  if (ParseFields(message, &fields, &rest)) {
    for (auto it = fields.begin(); it != fields.end(); ++it)
      if (!j.contains(it.key())) j[it.key()] = it.value();
    if (!rest.empty()) j["message"] = rest;
  } else {
    j["message"] = message;
  }
  return j.dump(-1, ' ', false, nlohmann::ordered_json::error_handler_t::replace);
}

bool SetMinLogLevel(const std::string& name) {
  if (name == "debug") SetMinLogLevel(LogLevel::kDebug);
  else if (name == "info") SetMinLogLevel(LogLevel::kInfo);
  else if (name == "warning") SetMinLogLevel(LogLevel::kWarning);
  else if (name == "error") SetMinLogLevel(LogLevel::kError);
  else return false;
  return true;
}

namespace internal {
LogMessage::LogMessage(LogLevel level, const char* file, int line) : level_(level) {
  const auto now = std::chrono::system_clock::now();
  const std::time_t t = std::chrono::system_clock::to_time_t(now);
  const int ms =
      static_cast<int>(std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char stamp[40];
  const size_t n = std::strftime(stamp, sizeof(stamp), "%Y-%m-%dT%H:%M:%S", &tm);
  std::snprintf(stamp + n, sizeof(stamp) - n, ".%03dZ", ms);
  const char* base = std::strrchr(file, '/');
  time_ = stamp;
  source_ = std::string(base ? base + 1 : file) + ":" + std::to_string(line);
}
LogMessage::~LogMessage() {
  std::string s;
  if (g_json) {
    s = FormatLogJson(time_, LevelName(level_), source_, stream_.str()) + "\n";
  } else {
    s = time_ + " " + LevelName(level_) + " " + source_ + "] " + stream_.str() + "\n";
  }
  std::fwrite(s.data(), 1, s.size(), stderr);
}
}  // namespace internal
}  // namespace prism
