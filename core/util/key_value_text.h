// The "key = value" text of Prism's config files (prism-server's --config, the SLAM options of
// core/slam/slam_config.h): one pair per line, '#' starts a comment, blank lines are skipped, key and
// value are trimmed.
#pragma once

#include <functional>
#include <string>

#include "core/util/status.h"

namespace prism {

// s without leading and trailing spaces, tabs, CR and LF.
std::string TrimWhitespace(const std::string& s);

// Calls fn(key, value) for each pair, in order, splitting each line at its first character from
// `separators`. Stops at the first error: INVALID_ARGUMENT "source:line: ..." for a line without a
// separator or with fn's error message.
Status ForEachKeyValueLine(const std::string& text, const std::string& source, const std::string& separators,
                           const std::function<Status(const std::string& key, const std::string& value)>& fn);

}  // namespace prism
