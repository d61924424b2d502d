// prism-server --bind tcp://127.0.0.1:5555 --data-dir DIR [--config FILE] [--KEY VALUE ...]; prism-server keygen.
// Prints one JSON line on stdout once listening: {"endpoint": "...", "metrics": "..."}.
#include <sys/resource.h>
#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include <csignal>
#include <cstdio>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/slam/slam_config.h"
#include "core/util/log_level.h"
#include "core/util/logging.h"
#include "server/curve.h"
#include "server/server.h"
#include "server/server_options.h"
#include "tools/cli.h"

namespace {

prism::server::Server* g_server = nullptr;

void OnSignal(int) {
  if (g_server) g_server->RequestStop();
}

int Fail(const std::string& m) {
  std::cerr << "prism-server: " << m << "\n";
  return 2;
}

// A CURVE key pair. With `out`, that file (mode 0600) gets both keys and the public key is printed;
// without, both are printed in the key-file format.
int Keygen(const std::string& out) {
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

constexpr char kNotes[] =
    R"(Every option is also a 'key = value' line of the --config file (read first; flags win). The SLAM
options of every session are --slam.KEY VALUE (or slam.KEY = VALUE lines), with the keys of
core/slam/slam_config.h, e.g. --slam.loop_closure false or --slam.tracker.min_gradient 5; they and
--slam-config apply in command-line order.
SIGTERM/SIGINT: stop accepting sessions, finish queued work (shutdown-deadline-ms), persist maps, exit 0.)";

// Parses argv into *options (the config file first, then the flags in command-line order), sets the
// log level and format. cli::kContinue, or the exit status (after keygen too).
int ParseCommandLine(int argc, char** argv, prism::server::ServerOptions* options) {
  using prism::server::ServerOptionKey;
  std::string config, log_level = "info", log_format = "text", keygen_out;
  CLI::App app{"", "prism-server"};
  prism::cli::Setup(
      &app, "serves reconstruction sessions over ZeroMQ (proto/prism/v1/session.proto)",
      {"prism-server --bind ENDPOINT --data-dir DIR [--config FILE] [--KEY VALUE ...] [--slam.KEY VALUE ...]",
       "prism-server keygen [--out FILE]"},
      kNotes);
  app.add_option("--config", config, "'key = value' lines of the options below")->type_name("FILE");
  bool check_only = false;
  app.add_flag("--check", check_only, "read the config file and the flags, report the first problem and exit");
  // One flag per ServerOptions key, with its default; their values are applied below, in order.
  const prism::server::ServerOptions defaults;
  std::map<const CLI::Option*, const ServerOptionKey*> server_key;
  for (const ServerOptionKey& k : prism::server::ServerOptionKeys())
    server_key[app.add_option("--" + k.key, k.help)->type_name(k.value_name)->default_str(k.get(defaults))] = &k;
  app.add_option("--log-level", log_level, "debug|info|warning|error")
      ->type_name("LEVEL")
      ->check(CLI::IsMember({"debug", "info", "warning", "error"}));
  app.add_option("--log-format", log_format,
                 "text|json, one line per event; json: an object with time, level, source\n"
                 "and the event's fields")
      ->type_name("FORMAT")
      ->check(CLI::IsMember({"text", "json"}));
  // --slam.KEY for every SLAM key, not listed one by one in --help; a mistyped key is left over and
  // handed to SetSlamOption below, which names the nearest known one.
  std::map<const CLI::Option*, std::string> slam_key;
  for (const std::string& key : prism::SlamOptionKeys()) slam_key[app.add_option("--slam." + key)->group("")] = key;
  app.allow_extras();
  CLI::App* keygen = app.add_subcommand("keygen", "a CURVE key pair (FILE gets both keys, the public key is printed)");
  prism::cli::Setup(keygen, keygen->get_description(), {"prism-server keygen [--out FILE]"});
  keygen->add_option("--out", keygen_out, "write both keys to FILE (mode 0600) and print the public key")
      ->type_name("FILE");
  if (const int exit = prism::cli::Parse(&app, argc, argv); exit != prism::cli::kContinue) return exit;
  const std::vector<std::string> extra = app.remaining(/*recurse=*/true);
  if (keygen->parsed()) {
    if (!extra.empty()) return Fail("keygen: unknown argument '" + extra.front() + "' (see --help)");
    return Keygen(keygen_out);
  }
  if (!config.empty())
    if (prism::Status s = prism::server::LoadServerConfig(config, options); !s.ok()) return Fail(s.ToString());
  for (const auto& [option, value] : prism::cli::InCommandLineOrder(app)) {
    prism::Status s;
    if (const auto k = server_key.find(option); k != server_key.end()) s = k->second->set(value, options);
    else if (const auto k = slam_key.find(option); k != slam_key.end())
      s = prism::SetSlamOption(k->second, value, &options->pipeline.slam);
    if (!s.ok()) return Fail(s.message() + " (see --help)");
  }
  for (size_t i = 0; i < extra.size(); ++i) {
    if (extra[i].rfind("--slam.", 0) != 0 || i + 1 >= extra.size())
      return Fail("unknown argument or missing value: '" + extra[i] + "' (see --help)");
    if (prism::Status s = prism::SetSlamOption(extra[i].substr(7), extra[i + 1], &options->pipeline.slam); !s.ok())
      return Fail(s.message() + " (see --help)");
    ++i;
  }
  if (check_only) return 0;
  prism::SetMinLogLevel(log_level);
  prism::SetLogFormat(log_format);
  return prism::cli::kContinue;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace prism::server;
  ServerOptions options;
  if (const int exit = ParseCommandLine(argc, argv, &options); exit != prism::cli::kContinue) return exit;
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
  // nlohmann quotes the values (an ipc:// path may hold any character); the layout stays "key": value.
  std::printf("{\"endpoint\": %s, \"metrics\": %s}\n", nlohmann::json((*server)->endpoint()).dump().c_str(),
              nlohmann::json((*server)->metrics_endpoint()).dump().c_str());
  std::fflush(stdout);
  const prism::Status st = (*server)->Run();
  g_server = nullptr;
  if (!st.ok()) return Fail(st.ToString());
  return 0;
}
