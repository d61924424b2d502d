// prism-server --bind tcp://127.0.0.1:5555 --data-dir DIR [--config FILE] [--key value ...]
// Prints one JSON line on stdout once listening: {"endpoint": "...", "metrics": "..."}.
#include <sys/resource.h>
#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include <csignal>
#include <cstdio>
#include <iostream>
#include <string>

#include "core/slam/slam_config.h"
#include "core/util/log_level.h"
#include "core/util/logging.h"
#include "server/curve.h"
#include "server/server.h"
#include "server/server_options.h"

namespace {

prism::server::Server* g_server = nullptr;

void OnSignal(int) {
  if (g_server) g_server->RequestStop();
}

int Fail(const std::string& m) {
  std::cerr << "prism-server: " << m << "\n";
  return 2;
}

}  // namespace

// prism-server keygen [--out FILE]: a CURVE key pair. With --out, FILE (mode 0600) gets both keys and
// the public key is printed; without, both are printed in the key-file format.
int Keygen(int argc, char** argv) {
  std::string out;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--out" && i + 1 < argc) out = argv[++i];
    else return Fail("keygen: unknown argument '" + a + "' (usage: prism-server keygen [--out FILE])");
  }
  prism::StatusOr<prism::server::CurveKeyPair> keys = prism::server::GenerateCurveKeyPair();
  if (!keys.ok()) return Fail(keys.status().ToString());
  if (out.empty()) {
    std::cout << "public = " << keys->public_key << "\nsecret = " << keys->secret_key << "\n";
    return 0;
  }
  if (prism::Status s = prism::server::WriteCurveKeyFile(out, *keys); !s.ok()) return Fail(s.ToString());
  std::cout << keys->public_key << "\n";
  return 0;
}

int main(int argc, char** argv) {
  using namespace prism::server;
  if (argc >= 2 && std::string(argv[1]) == "keygen") return Keygen(argc, argv);
  ServerOptions options;
  // The config file first, then flags over it.
  for (int i = 1; i + 1 < argc; ++i)
    if (std::string(argv[i]) == "--config") {
      if (prism::Status s = LoadServerConfig(argv[i + 1], &options); !s.ok()) return Fail(s.ToString());
    }
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h") {
      std::cout << "usage: prism-server --bind ENDPOINT --data-dir DIR [--config FILE] [--KEY VALUE ...]\n"
                   "       prism-server keygen [--out FILE]   (a CURVE key pair; FILE gets both, the public key is "
                   "printed)\n\n"
                   "Serves reconstruction sessions over ZeroMQ (proto/prism/v1/session.proto). Options (flags\n"
                   "or 'key = value' lines in the config file):\n"
                << ServerOptionsHelp()
                << "  log-level debug|info|warning|error\n"
                   "  log-format text|json    one line per event; json: an object with time, level, source and "
                   "the event's fields\n\nSIGTERM/SIGINT: stop accepting sessions, finish queued "
                   "work (shutdown-deadline-ms), persist maps, exit 0.\n";
      return 0;
    }
    if (a.rfind("--", 0) != 0 || i + 1 >= argc)
      return Fail("unknown argument or missing value: '" + a + "' (see --help)");
    const std::string key = a.substr(2), value = argv[++i];
    if (key == "config") continue;
    if (key == "log-level") {
      if (!prism::SetMinLogLevel(value)) return Fail("bad --log-level '" + value + "'");
      continue;
    }
    if (key == "log-format") {
      if (!prism::SetLogFormat(value)) return Fail("bad --log-format '" + value + "' (text or json)");
      continue;
    }
    if (prism::Status s = ApplyServerOption(key, value, &options); !s.ok()) return Fail(s.message() + " (see --help)");
  }
  if (options.data_dir.empty()) return Fail("--data-dir is required (see --help)");
#if defined(__GLIBC__)
  // Frames and chunks of up to max-message-bytes come and go: blocks of 1 MiB and more are mapped and
  // returned to the system when freed (glibc's default threshold rises with each large free, up to
  // 32 MiB, after which such blocks stay in the heap and the RSS with them).
  mallopt(M_MMAP_THRESHOLD, 1 << 20);
  // Few malloc arenas: the sessions' threads come and go, and memory freed in one of many arenas stays
  // with it (the RSS then drifts up after busy periods).
  mallopt(M_ARENA_MAX, 2);
#endif
  // Every HTTP and ZeroMQ peer holds a descriptor: take the hard limit (containers often start at 1024).
  if (rlimit lim{}; getrlimit(RLIMIT_NOFILE, &lim) == 0 && lim.rlim_cur < lim.rlim_max) {
    lim.rlim_cur = lim.rlim_max;
    setrlimit(RLIMIT_NOFILE, &lim);
  }
  prism::StatusOr<std::unique_ptr<Server>> server = Server::Create(options);
  if (!server.ok()) return Fail(server.status().ToString());
  g_server = server->get();
  // What a session's SLAM runs with beyond the defaults (core/slam/slam_config.h keys).
  std::string slam_changed = prism::FormatSlamConfig(options.pipeline.slam, /*only_changed=*/true);
  slam_changed = slam_changed.substr(slam_changed.find('\n') + 1);
  if (!slam_changed.empty()) slam_changed.pop_back();  // the last '\n' (the log adds one)
  if (!slam_changed.empty()) {
    PRISM_LOG(INFO) << "prism-server: SLAM options (others at their defaults):\n" << slam_changed;
  }
  struct sigaction sa {};
  sa.sa_handler = OnSignal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);
  std::signal(SIGPIPE, SIG_IGN);
  std::printf("{\"endpoint\": \"%s\", \"metrics\": \"%s\"}\n", (*server)->endpoint().c_str(),
              (*server)->metrics_endpoint().c_str());
  std::fflush(stdout);
  const prism::Status st = (*server)->Run();
  g_server = nullptr;
  if (!st.ok()) return Fail(st.ToString());
  return 0;
}
