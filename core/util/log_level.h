// A CLI's --log-level by name (kept apart from logging.h, which nearly every file includes).
#pragma once

#include <string>

namespace prism {

// SetMinLogLevel by name: "debug", "info", "warning" or "error"; false (the level unchanged) for any
// other name.
bool SetMinLogLevel(const std::string& name);

}  // namespace prism
