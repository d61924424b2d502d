// JSON text helpers for the command-line tools' summaries.
#pragma once

#include <string>

namespace prism {

// `s` as a JSON string literal: in double quotes, with quotes, backslashes and control characters
// escaped (\n, \r, \t by name, the others as \u00XX). Bytes >= 0x80 pass through (UTF-8 stays UTF-8).
std::string JsonQuote(const std::string& s);

}  // namespace prism
