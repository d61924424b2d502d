// A CLI's --log-level by name (kept apart from logging.h, which nearly every file includes).
#pragma once

#include <string>

namespace prism {

// SetMinLogLevel by name: "debug", "info", "warning" or "error"; false (the level unchanged) for any
// other name.
bool SetMinLogLevel(const std::string& name);

// The format of every log line: "text" (the default: `TIME LEVEL file:line] message`) or "json" (one
// object per line: time, level, source, and the message's `key=value` fields, or `message` when it has
// none). false (unchanged) for any other name.
bool SetLogFormat(const std::string& name);

// One log line as JSON (what SetLogFormat("json") writes), for tests.
std::string FormatLogJson(const std::string& time, const char* level, const std::string& source,
                          const std::string& message);

}  // namespace prism
