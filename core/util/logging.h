// Minimal structured logging to stderr: `PRISM_LOG(INFO) << "message";`
// Thread-safe: each statement is written with one call.
#pragma once

#include <sstream>
#include <string>

namespace prism {

enum class LogLevel { kDebug = 0, kInfo = 1, kWarning = 2, kError = 3 };

// Messages below this level are dropped. Process-wide, set once by a CLI's main.
void SetMinLogLevel(LogLevel level);
LogLevel MinLogLevel();

namespace internal {
class LogMessage {
 public:
  LogMessage(LogLevel level, const char* file, int line);
  ~LogMessage();
  std::ostream& stream() { return stream_; }

 private:
  LogLevel level_;
  std::string time_, source_;
  std::ostringstream stream_;
};
}  // namespace internal
}  // namespace prism

#define PRISM_LOG_LEVEL_DEBUG ::prism::LogLevel::kDebug
#define PRISM_LOG_LEVEL_INFO ::prism::LogLevel::kInfo
#define PRISM_LOG_LEVEL_WARNING ::prism::LogLevel::kWarning
#define PRISM_LOG_LEVEL_ERROR ::prism::LogLevel::kError
#define PRISM_LOG(level)                                  \
  if (PRISM_LOG_LEVEL_##level < ::prism::MinLogLevel()) { \
  } else ::prism::internal::LogMessage(PRISM_LOG_LEVEL_##level, __FILE__, __LINE__).stream()
