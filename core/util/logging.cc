#include "core/util/logging.h"

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <ctime>

#include "core/util/log_level.h"

namespace prism {
namespace {
std::atomic<int> g_min_level{static_cast<int>(LogLevel::kInfo)};

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
  char stamp[32];
  std::strftime(stamp, sizeof(stamp), "%Y-%m-%dT%H:%M:%S", &tm);
  const char* base = std::strrchr(file, '/');
  stream_ << stamp << "." << (ms < 100 ? (ms < 10 ? "00" : "0") : "") << ms << "Z " << LevelName(level_) << " "
          << (base ? base + 1 : file) << ":" << line << "] ";
}
LogMessage::~LogMessage() {
  stream_ << "\n";
  const std::string s = stream_.str();
  std::fwrite(s.data(), 1, s.size(), stderr);
}
}  // namespace internal
}  // namespace prism
