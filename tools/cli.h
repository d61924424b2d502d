// Every tool's command line goes through CLI11 the same way. `--help` prints "TOOL: purpose", the usage
// lines, the options with their defaults, then the notes; a bad command line prints
// "TOOL: message (see --help)" on stderr and exits with the tool's usage status.
#pragma once

#include <CLI/CLI.hpp>
#include <string>
#include <utility>
#include <vector>

namespace prism::cli {

// Parse() returns this when the tool should go on.
constexpr int kContinue = -1;

// Gives `app` (named after the tool, e.g. CLI::App app{"", "prism-synth"}) the shared help layout:
// `purpose` (one line), `usage` (the usage lines, without "usage:"), its options with their defaults
// and then `notes` (free text, may be empty). Call it before adding options; subcommands get their own.
void Setup(CLI::App* app, const std::string& purpose, const std::vector<std::string>& usage,
           const std::string& notes = "");

// Parses argv. kContinue when the tool should go on; else its exit status: 0 after --help (the help of
// the subcommand given, if any, on stdout), `usage_exit` after an error (on stderr).
int Parse(CLI::App* app, int argc, char** argv, int usage_exit = 2);

// The values of the options of `app` in command-line order (an option given twice appears twice),
// for options whose effects depend on their order (a config file, then single keys over it).
std::vector<std::pair<const CLI::Option*, std::string>> InCommandLineOrder(const CLI::App& app);

}  // namespace prism::cli
