// Misbehaving peers of prism-server, for prism-bench-abuse: each runs in a process of its own until its
// deadline (or SIGTERM) against a real server on this machine.
#pragma once

#include <string>
#include <vector>

namespace prism::abuse {

struct Target {
  std::string zmq_endpoint;       // tcp://127.0.0.1:PORT
  std::string http_host_port;     // 127.0.0.1:PORT ("" = no HTTP listener)
  std::string server_public_key;  // CURVE servers only
  double seconds = 10;            // how long to keep at it
};

struct AbuserInfo {
  std::string name;
  std::string description;
  // What the server must count it in (a /metrics family, labels allowed).
  std::string metric;
  bool needs_curve = false;
  // Not abuse: an ordinary neighbour, for comparison (the bars do not apply).
  bool reference = false;
};

// Every abuser, in the order the benchmark runs them.
const std::vector<AbuserInfo>& Abusers();

// Runs the named abuser; returns the process exit code (2 for an unknown name).
int RunAbuser(const std::string& name, const Target& target);

}  // namespace prism::abuse
