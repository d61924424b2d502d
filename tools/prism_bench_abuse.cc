// prism-bench-abuse: a well-behaved session at 30 frames/s beside each misbehaving peer of a real
// prism-server on this machine (tools/abuse/abusers.h), and what the session, a new session, /healthz,
// the server's memory, metrics and log show. Prints a table (and JSON with --json).
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>
#include <thread>

#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"
#include "prism/client/client.h"
#include "tools/abuse/abusers.h"
#include "tools/client_rig.h"
#include "tools/http_get.h"

extern char** environ;

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;
using nlohmann::json;

double MsSince(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return -1;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size() - 1) + 0.5))];
}

pid_t Spawn(const std::vector<std::string>& args, const std::string& out, const std::string& err) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, err.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  std::vector<char*> argv;
  for (const std::string& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  pid_t pid = 0;
  const int rc = posix_spawn(&pid, args[0].c_str(), &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  return rc == 0 ? pid : -1;
}

void StopProcess(pid_t pid) {
  if (pid <= 0) return;
  kill(pid, SIGTERM);
  int status = 0;
  for (int i = 0; i < 300; ++i) {
    if (waitpid(pid, &status, WNOHANG) == pid) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  kill(pid, SIGKILL);
  waitpid(pid, &status, 0);
}

// A prism-server process: endpoints, log (JSON lines), RSS.
struct Server {
  pid_t pid = -1;
  std::string endpoint, metrics_url, log_path, public_key;

  bool Start(const std::string& bin_dir, const std::string& dir, const std::vector<std::string>& extra) {
    fs::create_directories(dir + "/data");
    log_path = dir + "/server.log";
    std::vector<std::string> args = {bin_dir + "/prism-server",
                                     "--bind",
                                     "tcp://127.0.0.1:*",
                                     "--data-dir",
                                     dir + "/data",
                                     "--metrics",
                                     "127.0.0.1:0",
                                     "--log-format",
                                     "json",
                                     "--idle-timeout-ms",
                                     "3000"};
    args.insert(args.end(), extra.begin(), extra.end());
    pid = Spawn(args, dir + "/server.json", log_path);
    for (int i = 0; i < 200 && endpoint.empty(); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      std::ifstream f(dir + "/server.json");
      std::string line;
      if (std::getline(f, line) && !line.empty()) {
        const json j = json::parse(line, nullptr, false);
        if (j.is_object()) {
          endpoint = j.value("endpoint", "");
          metrics_url = j.value("metrics", "");
        }
      }
    }
    return !endpoint.empty();
  }
  double RssMb() const {
    std::ifstream f("/proc/" + std::to_string(pid) + "/status");
    std::string line;
    while (std::getline(f, line))
      if (line.rfind("VmRSS:", 0) == 0) return std::atof(line.c_str() + 6) / 1024.0;
    return -1;
  }
  std::map<std::string, double> Metrics() const { return prism::FetchMetrics(metrics_url, 2000); }
  size_t LogSize() const {
    std::error_code ec;
    const auto n = fs::file_size(log_path, ec);
    return ec ? 0 : static_cast<size_t>(n);
  }
  std::vector<json> LogSince(size_t offset) const {
    std::ifstream f(log_path);
    f.seekg(static_cast<std::streamoff>(offset));
    std::vector<json> lines;
    std::string line;
    while (std::getline(f, line)) {
      json j = json::parse(line, nullptr, false);
      if (j.is_object()) lines.push_back(std::move(j));
    }
    return lines;
  }
};

struct Sequence {
  prism::client::Rig rig;
  std::vector<cv::Mat> frames;
  std::vector<int64_t> timestamps_ns;
};

Sequence Render(const std::string& preset, int width, int height, int frames) {
  prism::synth::PresetOptions po;
  po.width = width;
  po.height = height;
  po.frames = frames;
  prism::StatusOr<prism::synth::SynthSetup> setup = prism::synth::MakePreset(preset, po);
  if (!setup.ok()) {
    std::cerr << "prism-bench-abuse: " << setup.status() << "\n";
    std::exit(2);
  }
  const prism::Trajectory traj = prism::synth::MakeTrajectory(setup->trajectory);
  Sequence s;
  s.rig = prism::ToClientRig(setup->rig);
  s.frames.resize(frames);
  s.timestamps_ns.resize(frames);
  prism::ThreadPool pool;
  pool.ParallelFor(0, frames, [&](std::ptrdiff_t i) {
    s.frames[i] = prism::synth::RenderFrame(setup->scene, setup->rig, traj[i].world_from_camera, setup->render,
                                            1000003ull + static_cast<uint64_t>(i))
                      .rgb;
    s.timestamps_ns[i] = static_cast<int64_t>(traj[i].timestamp_s * 1e9);
  });
  return s;
}

struct SessionResult {
  bool ok = false;
  std::string error;
  std::vector<double> frame_to_pose_ms;
  size_t tracked = 0;
  uint64_t slowest_frame = 0;  // the frame whose pose took longest
  double slowest_ms = 0;
  double p95() const { return Percentile(frame_to_pose_ms, 0.95); }
};

prism::client::SessionOptions ClientOptions(const Server& server, const std::string& client_pub,
                                            const std::string& client_sec) {
  prism::client::SessionOptions so;
  so.live = true;
  so.codec = prism::client::Codec::kJpeg;
  so.timeout_ms = 10000;
  so.reconnect_timeout_ms = 0;
  so.client_name = "well-behaved";
  so.server_public_key = server.public_key;
  so.client_public_key = client_pub;
  so.client_secret_key = client_sec;
  return so;
}

// The well-behaved session: every frame pushed at `fps`, its pose's arrival timed.
SessionResult RunSession(const Server& server, const Sequence& seq, double fps, const std::string& client_pub,
                         const std::string& client_sec) {
  SessionResult out;
  std::unique_ptr<prism::client::Session> session;
  prism::client::Status s =
      prism::client::Session::Open(server.endpoint, seq.rig, ClientOptions(server, client_pub, client_sec), &session);
  if (!s.ok()) {
    out.error = "open: " + s.ToString();
    return out;
  }
  std::map<uint64_t, Clock::time_point> sent;
  session->SetEventCallback([&](const prism::client::Event& e) {
    if (e.kind != prism::client::Event::Kind::kPose || e.pose.refined) return;
    if (auto it = sent.find(e.pose.frame_sequence_number); it != sent.end()) {
      out.frame_to_pose_ms.push_back(MsSince(it->second));
      if (out.frame_to_pose_ms.back() > out.slowest_ms) {
        out.slowest_ms = out.frame_to_pose_ms.back();
        out.slowest_frame = e.pose.frame_sequence_number;
      }
    }
    if (e.pose.state == prism::client::TrackingState::kTracking) ++out.tracked;
  });
  const auto t0 = Clock::now();
  for (size_t i = 0; i < seq.frames.size(); ++i) {
    // Wait for the frame's time while taking events (callbacks run only inside the session's calls).
    const auto due =
        t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(static_cast<double>(i) / fps));
    prism::client::Event ignored;
    for (auto now = Clock::now(); now < due; now = Clock::now())
      session->Poll(&ignored,
                    std::max(1, static_cast<int>(std::chrono::duration<double, std::milli>(due - now).count())));
    sent[i] = Clock::now();
    const cv::Mat& f = seq.frames[i];
    s = session->PushFrame(seq.timestamps_ns[i], f.data, f.cols, f.rows, static_cast<int>(f.step));
    if (!s.ok()) {
      out.error = "push " + std::to_string(i) + ": " + s.ToString();
      return out;
    }
  }
  prism::client::Summary summary;
  s = session->Close(120000, &summary);
  if (!s.ok()) {
    out.error = "close: " + s.ToString();
    return out;
  }
  out.ok = true;
  return out;
}

// How long a new session takes to open (ms; -1 when it did not within 1 s).
double OpenTimeMs(const Server& server, const Sequence& seq, const std::string& client_pub,
                  const std::string& client_sec) {
  prism::client::SessionOptions so = ClientOptions(server, client_pub, client_sec);
  so.timeout_ms = 1000;
  so.client_name = "new-session";
  std::unique_ptr<prism::client::Session> session;
  const auto t0 = Clock::now();
  const prism::client::Status s = prism::client::Session::Open(server.endpoint, seq.rig, so, &session);
  const double ms = MsSince(t0);
  if (!s.ok()) return -1;
  prism::client::Summary summary;
  (void)session->Close(10000, &summary);
  return ms;
}

// /healthz latency every 200 ms while it runs.
class HealthProbe {
 public:
  explicit HealthProbe(std::string url) : url_(std::move(url)) {
    thread_ = std::thread([this] {
      while (!stop_) {
        const auto t0 = Clock::now();
        const prism::HttpResponse r = prism::FetchHttp(url_ + "/healthz", 2000);
        const double ms = MsSince(t0);
        {
          std::lock_guard<std::mutex> lock(mutex_);
          ms_.push_back(r.status == 200 ? ms : 1e9);
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
      }
    });
  }
  ~HealthProbe() { Stop(); }
  std::vector<double> Stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
    std::lock_guard<std::mutex> lock(mutex_);
    return ms_;
  }

 private:
  std::string url_;
  std::atomic<bool> stop_{false};
  std::mutex mutex_;
  std::vector<double> ms_;
  std::thread thread_;
};

void WaitForNoSessions(const Server& server, double seconds) {
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  while (Clock::now() < end) {
    const auto m = server.Metrics();
    auto it = m.find("prism_sessions_active");
    if (it != m.end() && it->second == 0) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(250));
  }
}

// Abuse log lines in `lines`: how many, and whether any peer was logged twice for the same thing.
struct LogCheck {
  size_t lines = 0, repeats = 0, churn_lines = 0;
};

LogCheck CheckLog(const std::vector<json>& lines) {
  LogCheck c;
  std::set<std::string> seen;
  for (const json& j : lines) {
    const std::string event = j.value("event", "");
    std::string key;
    if (event == "error_sent") key = event + "|" + j.value("peer", "") + "|" + j.value("code", "");
    else if (event == "http_connection_without_request") key = event + "|" + j.value("peer", "");
    else if (event == "auth_refused") key = event + "|" + j.value("client_key", "");
    else if (event == "chunk_credits_exhausted") key = event + "|" + j.value("session", "");
    else if (event == "zmq_connection_churn") {
      ++c.lines;
      ++c.churn_lines;
      continue;
    } else continue;
    ++c.lines;
    if (!seen.insert(key).second) ++c.repeats;
  }
  return c;
}

struct Bars {
  double max_p95_ratio = 1.2;
  double max_open_ms = 1000;
  double max_healthz_ms = 100;
  double max_rss_ratio = 1.1;
};

// ParseCommandLine returns this when the benchmark should go on.
constexpr int kContinue = -1;

// The command line.
struct Settings {
  std::string abuser, zmq_endpoint, http, key, preset = "bunny-multicolor-forward", only, json_out;
  double seconds = 10, fps = 30, abuser_seconds = 10;
  int width = 320, height = 240, baseline_runs = 3, repeats = 2;
  bool check = false, check_latency = false, keep = false;
  std::vector<std::string> server_options;
};

// What every server group shares: this binary (the abusers run as it), its folder (prism-server's), the
// temp folder, the well-behaved session's frames and the bars.
struct Context {
  std::string self, bin_dir, tmp;
  Sequence seq;
  Bars bars;
};

// A server of one group (plain or CURVE), its folder and the well-behaved client's keys.
struct GroupServer {
  Server server;
  std::string client_pub, client_sec, dir;
};

// The reference runs at the start of a group.
struct Baseline {
  std::vector<double> p95;  // per run
  double p95_all = 0;       // over the frames of every run
  double rss_mb = 0;        // the highest after an ordinary session: where the server settles
};

// The results so far: the table's rows, the JSON and whether every bar held.
struct Report {
  json results = json::array();
  bool all_pass = true;
  std::vector<std::string> table;
};

// Parses the command line into `settings`: kContinue or the exit status.
int ParseCommandLine(int argc, char** argv, Settings* settings) {
  Settings& s = *settings;
  CLI::App app{
      "prism-bench-abuse: a well-behaved session at 30 frames/s beside each misbehaving peer of a real prism-server "
      "(127.0.0.1), and the bars: its frame-to-pose p95 within 1.2x of its value alone, a new session open within 1 s, "
      "/healthz within 100 ms, the server's RSS back within 10% afterwards, every abuser counted in a metric and "
      "logged at most once per peer."};
  app.add_option("--abuser", s.abuser, "run one abuser (internal: the benchmark starts itself this way)");
  app.add_option("--zmq", s.zmq_endpoint, "abuser mode: the server's ZeroMQ endpoint");
  app.add_option("--http", s.http, "abuser mode: the server's HTTP HOST:PORT");
  app.add_option("--server-key", s.key, "abuser mode: the server's CURVE public key");
  app.add_option("--abuser-seconds", s.abuser_seconds, "abuser mode: how long");
  app.add_option("--preset", s.preset, "the well-behaved session's scene")->capture_default_str();
  app.add_option("--width", s.width, "its frame width")->capture_default_str();
  app.add_option("--height", s.height, "its frame height")->capture_default_str();
  app.add_option("--seconds", s.seconds, "its length, s")->capture_default_str();
  app.add_option("--fps", s.fps, "its frame rate")->capture_default_str();
  app.add_option("--baseline-runs", s.baseline_runs, "runs without an abuser at the start (warm-up and RSS reference)")
      ->capture_default_str();
  app.add_option("--repeats", s.repeats,
                 "runs beside each abuser, and ordinary runs right before it; each p95 is the median of the runs' p95")
      ->capture_default_str();
  app.add_option("--only", s.only, "comma-separated abusers (default: all)");
  app.add_option("--json", s.json_out, "also write the results as JSON to this file");
  app.add_flag("--check", s.check,
               "exit 1 when a bar fails: the session ran, a new one opened within 1 s, /healthz within 100 ms, RSS "
               "within 10%, the abuser counted and logged at most once per peer");
  app.add_flag("--check-latency", s.check_latency,
               "with --check, the p95 ratio too (a timing: noisy on a shared machine)");
  app.add_option("--server-option", s.server_options, "KEY=VALUE passed to prism-server as --KEY VALUE (repeatable)");
  app.add_flag("--keep", s.keep, "keep the servers' folders (logs) in the temp dir");
  CLI11_PARSE(app, argc, argv);
  return kContinue;
}

// Starts the group's server (with CURVE keys from prism-server keygen, and this client's key on the
// allow-list): kContinue or the exit status.
int StartGroupServer(const Settings& s, const Context& c, bool curve, GroupServer* g) {
  std::vector<std::string> extra;
  for (const std::string& kv : s.server_options) {
    const size_t eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) {
      std::cerr << "prism-bench-abuse: --server-option wants KEY=VALUE, got '" << kv << "'\n";
      return 2;
    }
    extra.push_back("--" + kv.substr(0, eq));
    extra.push_back(kv.substr(eq + 1));
  }
  const std::string& dir = g->dir = c.tmp + (curve ? "/curve" : "/plain");
  fs::create_directories(dir);
  if (curve) {
    const std::string keys = dir + "/server.keys";
    const pid_t kg = Spawn({c.bin_dir + "/prism-server", "keygen", "--out", keys}, dir + "/pub.txt", dir + "/kg.log");
    int st = 0;
    waitpid(kg, &st, 0);
    std::ifstream(dir + "/pub.txt") >> g->server.public_key;
    prism::client::GenerateKeyPair(&g->client_pub, &g->client_sec);
    std::ofstream(dir + "/allowed.txt") << g->client_pub << "\n";
    extra.insert(extra.end(), {"--curve-keys", keys, "--allowed-clients", dir + "/allowed.txt"});
  }
  if (!g->server.Start(c.bin_dir, dir, extra)) {
    std::cerr << "prism-bench-abuse: prism-server did not start (see " << dir << "/server.log)\n";
    return 2;
  }
  return kContinue;
}

// A warm-up session, then the reference runs: kContinue or the exit status (the server stopped).
int RunBaseline(const Settings& s, const Context& c, bool curve, const GroupServer& g, Baseline* base) {
  const Server& server = g.server;
  (void)RunSession(server, c.seq, s.fps, g.client_pub, g.client_sec);
  std::vector<double> base_all;
  for (int r = 0; r < s.baseline_runs; ++r) {
    const SessionResult b = RunSession(server, c.seq, s.fps, g.client_pub, g.client_sec);
    if (!b.ok) {
      std::cerr << "prism-bench-abuse: baseline session failed: " << b.error << "\n";
      StopProcess(server.pid);
      return 2;
    }
    base->p95.push_back(b.p95());
    base_all.insert(base_all.end(), b.frame_to_pose_ms.begin(), b.frame_to_pose_ms.end());
    WaitForNoSessions(server, 10);
    base->rss_mb = std::max(base->rss_mb, server.RssMb());
    std::cerr << (curve ? "curve " : "") << "baseline run " << r << ": p50/p90/p95/p99 "
              << Percentile(b.frame_to_pose_ms, 0.5) << "/" << Percentile(b.frame_to_pose_ms, 0.9) << "/" << b.p95()
              << "/" << Percentile(b.frame_to_pose_ms, 0.99) << " ms, " << b.frame_to_pose_ms.size()
              << " poses (slowest: frame " << b.slowest_frame << ", " << b.slowest_ms << " ms), server RSS "
              << server.RssMb() << " MB\n";
  }
  base->p95_all = Percentile(base_all, 0.95);
  return kContinue;
}

// The well-behaved session's p95: the median over `repeats` ordinary runs right before an abuser of
// each run's p95 (the machine's speed drifts by more than the bar over the minutes the whole table
// takes, and one run in a few meets a slow spell of the shared host); `fallback` without any.
double NearBaselineP95(const Settings& s, const Context& c, const GroupServer& g, double fallback,
                       std::vector<double>* run_p95) {
  for (int k = 0; k < s.repeats; ++k) {
    const SessionResult b = RunSession(g.server, c.seq, s.fps, g.client_pub, g.client_sec);
    if (b.ok) run_p95->push_back(b.p95());
  }
  return run_p95->empty() ? fallback : Percentile(*run_p95, 0.5);
}

// What the well-behaved session, a new session, /healthz, the server's memory, metrics and log showed
// beside one abuser.
struct AbuserRun {
  SessionResult session;        // the frames of every run beside it
  std::vector<double> run_p95;  // each run's p95
  double open_ms = 0;
  std::vector<double> health;  // /healthz latencies, ms
  double rss_after = 0;
  double counted = 0;  // the abuser's metric's increase
  LogCheck log;
  double abuse_s = 0;  // how long the abuser ran
};

// Starts the abuser as this binary's abuser mode and runs the well-behaved sessions beside it.
AbuserRun MeasureBesideAbuser(const Settings& s, const Context& c, const GroupServer& g,
                              const prism::abuse::AbuserInfo& a) {
  const Server& server = g.server;
  AbuserRun run;
  const size_t log_offset = server.LogSize();
  const auto metrics_before = server.Metrics();
  HealthProbe probe(server.metrics_url);
  const double abuse_s = run.abuse_s = s.repeats * (s.seconds + 3) + 4;
  const std::string http_hp = server.metrics_url.substr(7);
  const pid_t pid = Spawn({c.self, "--abuser", a.name, "--zmq", server.endpoint, "--http", http_hp, "--server-key",
                           server.public_key, "--abuser-seconds", std::to_string(abuse_s)},
                          g.dir + "/abuser.out", g.dir + "/abusers.log");
  // Set up (it may render frames first), then a second at full strength.
  for (int i = 0; i < 1200; ++i) {
    std::ifstream ready(g.dir + "/abuser.out");
    std::string word;
    if (ready >> word && word == "ready") break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(1000));
  SessionResult& r = run.session;
  for (int k = 0; k < s.repeats; ++k) {
    const SessionResult one = RunSession(server, c.seq, s.fps, g.client_pub, g.client_sec);
    r.ok = k == 0 ? one.ok : r.ok && one.ok;
    if (!one.ok) r.error = one.error;
    r.frame_to_pose_ms.insert(r.frame_to_pose_ms.end(), one.frame_to_pose_ms.begin(), one.frame_to_pose_ms.end());
    if (one.ok) run.run_p95.push_back(one.p95());
  }
  run.open_ms = OpenTimeMs(server, c.seq, g.client_pub, g.client_sec);
  StopProcess(pid);
  run.health = probe.Stop();
  WaitForNoSessions(server, 20);
  // Where the RSS settles: after the server's periodic malloc_trim (every 10 s) has run once.
  std::this_thread::sleep_for(std::chrono::seconds(11));
  run.rss_after = server.RssMb();
  const auto metrics_after = server.Metrics();
  const auto value = [](const std::map<std::string, double>& m, const std::string& k) {
    auto it = m.find(k);
    return it == m.end() ? 0.0 : it->second;
  };
  run.counted = value(metrics_after, a.metric) - value(metrics_before, a.metric);
  run.log = CheckLog(server.LogSince(log_offset));
  return run;
}

// One abuser of the group: its runs, the bars, its table row and JSON into the report. A reference
// abuser raises *rss_base to where the server settled after it.
void RunAbuserCase(const Settings& s, const Context& c, const GroupServer& g, bool curve,
                   const prism::abuse::AbuserInfo* a, const Baseline& base, double* rss_base, Report* report) {
  const Bars& bars = c.bars;
  std::cerr << "abuser " << a->name << ": " << a->description << "\n";
  std::vector<double> near_run_p95;
  const double p95_near = NearBaselineP95(s, c, g, base.p95_all, &near_run_p95);
  WaitForNoSessions(g.server, 10);
  const AbuserRun run = MeasureBesideAbuser(s, c, g, *a);
  const SessionResult& r = run.session;
  const std::vector<double>& health = run.health;
  const double open_ms = run.open_ms, rss_after = run.rss_after, counted = run.counted;
  const LogCheck& log = run.log;
  const double p95 = r.ok ? Percentile(run.run_p95, 0.5) : -1;
  const double health_max = health.empty() ? -1 : *std::max_element(health.begin(), health.end());
  const double ratio = p95 > 0 ? p95 / p95_near : -1;
  // Connection churn is logged once per 10 s window instead of per peer (no peer identity).
  const size_t max_churn_lines = static_cast<size_t>(run.abuse_s / 10.0) + 2;
  std::vector<std::string> failed;
  if (!r.ok) failed.push_back("session: " + r.error);
  if (!(ratio > 0 && ratio <= bars.max_p95_ratio)) failed.push_back("p95");
  if (!(open_ms >= 0 && open_ms <= bars.max_open_ms)) failed.push_back("open");
  if (!(health_max >= 0 && health_max <= bars.max_healthz_ms)) failed.push_back("healthz");
  if (!(rss_after <= bars.max_rss_ratio * *rss_base)) failed.push_back("rss");
  if (!(counted > 0)) failed.push_back("counted");
  if (log.repeats > 0 || log.churn_lines > max_churn_lines) failed.push_back("log");
  const bool latency_only = failed.size() == 1 && failed[0] == "p95";
  if (a->reference) {
    failed.clear();
    // An ordinary neighbour's session leaves the allocator where two sessions at once put it: that
    // is where the server settles, and what the abusers are held to.
    *rss_base = std::max(*rss_base, rss_after);
  }
  const bool pass = failed.empty();
  report->all_pass = report->all_pass && (pass || (latency_only && !s.check_latency));
  std::string why;
  for (const std::string& f : failed) why += (why.empty() ? "" : ",") + f;
  char row[512];
  std::snprintf(row, sizeof(row), "| %-20s | %8.1f | %8.1f | %5.2f | %7.1f | %8.1f | %6.0f/%6.0f | %8.0f | %9zu | %s |",
                a->name.c_str(), p95_near, p95, ratio, open_ms, health_max, *rss_base, rss_after, counted, log.lines,
                a->reference ? "reference"
                : pass       ? "pass"
                             : ("FAIL " + why).c_str());
  report->table.push_back(row);
  std::cerr << row << "\n";
  report->results.push_back({{"abuser", a->name},
                             {"description", a->description},
                             {"curve", curve},
                             {"p95_ms_baseline", p95_near},
                             {"p95_ms_baseline_start", base.p95_all},
                             {"p95_ms_baseline_start_runs", base.p95},
                             {"p95_ms_baseline_runs", near_run_p95},
                             {"p95_ms", p95},
                             {"p95_ms_runs", run.run_p95},
                             {"p95_ms_all_frames", r.ok ? r.p95() : -1},
                             {"p95_ratio", ratio},
                             {"poses", r.frame_to_pose_ms.size()},
                             {"open_ms", open_ms},
                             {"healthz_max_ms", health_max},
                             {"healthz_p95_ms", Percentile(health, 0.95)},
                             {"healthz_probes", health.size()},
                             {"rss_mb_baseline", *rss_base},
                             {"rss_mb_after", rss_after},
                             {"metric", a->metric},
                             {"metric_delta", counted},
                             {"log_lines", log.lines},
                             {"log_repeats", log.repeats},
                             {"pass", pass},
                             {"failed", failed}});
}

// The abusers that need CURVE (curve) or not, among the wanted ones (all when none), beside one server:
// kContinue or the exit status.
int RunGroup(const Settings& s, const Context& c, bool curve, const std::set<std::string>& wanted, Report* report) {
  std::vector<const prism::abuse::AbuserInfo*> group;
  for (const auto& a : prism::abuse::Abusers())
    if (a.needs_curve == curve && (wanted.empty() || wanted.count(a.name) || a.reference)) group.push_back(&a);
  if (group.empty()) return kContinue;
  GroupServer g;
  if (const int exit = StartGroupServer(s, c, curve, &g); exit != kContinue) return exit;
  Baseline base;
  if (const int exit = RunBaseline(s, c, curve, g, &base); exit != kContinue) return exit;
  double rss_base = base.rss_mb;
  for (const prism::abuse::AbuserInfo* a : group) RunAbuserCase(s, c, g, curve, a, base, &rss_base, report);
  StopProcess(g.server.pid);
  return kContinue;
}

}  // namespace

int main(int argc, char** argv) {
  Settings s;
  if (const int exit = ParseCommandLine(argc, argv, &s); exit != kContinue) return exit;

  if (!s.abuser.empty()) {
    // The abuser shares this machine; a remote attacker would not share the server's CPU.
    setpriority(PRIO_PROCESS, 0, 19);
    prism::abuse::Target t{s.zmq_endpoint, s.http, s.key, s.abuser_seconds};
    return prism::abuse::RunAbuser(s.abuser, t);
  }

  Context c;
  c.self = fs::canonical("/proc/self/exe").string();
  c.bin_dir = fs::path(c.self).parent_path().string();
  c.tmp = (fs::temp_directory_path() / ("prism_bench_abuse_" + std::to_string(getpid()))).string();
  fs::create_directories(c.tmp);
  const int frames = static_cast<int>(s.seconds * s.fps);
  std::cerr << "rendering " << frames << " frames of " << s.preset << " at " << s.width << "x" << s.height << "\n";
  c.seq = Render(s.preset, s.width, s.height, frames);

  std::set<std::string> wanted;
  std::string name;
  for (std::stringstream ss(s.only); std::getline(ss, name, ',');)
    if (!name.empty()) wanted.insert(name);

  Report report;
  char row[512];
  std::snprintf(row, sizeof(row), "| %-20s | %8s | %8s | %5s | %7s | %8s | %13s | %8s | %9s | %s |", "abuser",
                "p95 base", "p95 with", "ratio", "open ms", "healthz", "RSS MB b/a", "counted", "log lines", "bars");
  report.table.push_back(row);
  report.table.push_back("|" + std::string(20 + 2, '-') +
                         "|----------|----------|-------|---------|----------|---------------|"
                         "----------|-----------|------|");

  for (const bool curve : {false, true}) {
    if (const int exit = RunGroup(s, c, curve, wanted, &report); exit != kContinue) return exit;
  }
  std::cout << "well-behaved session: " << s.preset << " " << s.width << "x" << s.height << ", " << frames
            << " frames at " << s.fps << " frames/s (JPEG, live); abusers at niceness 19; "
            << std::thread::hardware_concurrency() << " hardware threads\n";
  for (const std::string& line : report.table) std::cout << line << "\n";
  if (!s.json_out.empty()) std::ofstream(s.json_out) << report.results.dump(2) << "\n";
  if (s.keep) std::cerr << "kept " << c.tmp << "\n";
  else fs::remove_all(c.tmp);
  return s.check && !report.all_pass ? 1 : 0;
}
