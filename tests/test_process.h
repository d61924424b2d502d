// Helpers for the cross-module suites that run the real CLIs as separate processes.
#pragma once

#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>

namespace prism::test {

struct ProcessResult {
  int exit_code = -1;
  std::string out;  // stdout and stderr
};

// Runs a shell command, capturing stdout and stderr together.
inline ProcessResult Execute(const std::string& command) {
  ProcessResult r;
  FILE* p = popen((command + " 2>&1").c_str(), "r");
  if (!p) return r;
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof(buf), p)) > 0) r.out.append(buf, n);
  const int status = pclose(p);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

// Path of a binary of this build (PRISM_BINARY_DIR is set by prism_add_test).
// The whole content of a file ("" when it cannot be read).
inline std::string ReadFileText(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

inline std::string Bin(const std::string& name) { return std::string(PRISM_BINARY_DIR) + "/bin/" + name; }

// The number after "key": in a JSON text (NaN when absent).
inline double JsonNumber(const std::string& json, const std::string& key) {
  const std::regex re("\"" + key + "\"\\s*:\\s*([-+0-9.eE]+)");
  std::smatch m;
  if (!std::regex_search(json, m, re)) return std::nan("");
  return std::stod(m[1]);
}

// The string after "key": in a JSON text (no escapes inside; "" when absent).
inline std::string JsonString(const std::string& json, const std::string& key) {
  const std::regex re("\"" + key + "\"\\s*:\\s*\"([^\"]*)\"");
  std::smatch m;
  if (!std::regex_search(json, m, re)) return "";
  return m[1];
}

}  // namespace prism::test
