// prism-bench-e2e: the networked system end to end on this machine, as JSON. Starts prism-server (next
// to this binary) on a free port, renders a preset in memory, and streams it through libprism_client
// once per codec, measuring what a device sees.
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "core/eval/trajectory_metrics.h"
#include "core/io/ply_io.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"
#include "prism/client/client.h"
#include "tools/cli.h"
#include "tools/client_rig.h"
#include "tools/http_get.h"
#include "tools/json_output.h"

extern char** environ;

namespace {

using Clock = std::chrono::steady_clock;

constexpr char kNotes[] =
    R"(prism-server runs on 127.0.0.1 with a free port (input policy upload, so no frame is dropped unless
--live); the preset is rendered in memory (512x512) and streamed through libprism_client once per codec,
as fast as the server's frame credits allow (or at --fps). --live opens the sessions as a live camera's
(a full frame queue drops its oldest frame, frames_dropped counts them, and the server's
skip-depth-update-backlog-live applies; the SDK still waits for a frame credit before each push).

Prints one JSON object, per codec: frames_per_s (frames sent / time until the last pose),
map_frames_per_s (frames sent / time until the session summary, i.e. every keyframe's chunks
delivered), map_complete_after_last_pose_s (the last keyframe's first chunk after the last pose: every
keyframe is in the map), map_done_after_last_pose_s (the session summary after the last pose: the map
rebuilt at the refined poses has arrived too), frame_to_pose_ms p50/p95 (frame sent -> its pose
received), keyframe_to_chunk_ms p50/p95 (the pose of the frame that became keyframe k + 1, which
finishes keyframe k, or the last pose for the last keyframe, -> keyframe k's first chunk),
uplink_bytes_per_frame, chunk_bits_per_point, chunks, keyframes; server_rss_mb before the first session and after each, server_peak_rss_mb;
ate_percent_of_path (the poses received, the refined ones replacing the first, tracked frames only,
against the rendered truth after a Sim(3) alignment), frames_depth_update_skipped and frames_dropped;
map: the session's final map (the SDK's Session::Map) scored as docs/benchmarks.md scores maps (prism-eval
cloud --object-only on the preset written by prism-synth, placed by the received poses' Sim(3) alignment):
fscore, precision, completeness, accuracy_median_mm;
server_ms_per_keyframe: from the server's /metrics, the mean per keyframe of its wait in the keyframe
queue, the dense stage's time on it (dense_total) and its parts (photometric, fusion, map, encode).
With --sessions N > 1, N sessions stream at once per codec and the codec's entry is {"sessions": [one
object as above per session]}; server_ms_per_keyframe then covers every session of the run.)";

// Two decimals are all a timing or a size here is worth.
double Round2(double v) { return std::round(v * 100) / 100; }

int Fail(const std::string& m) {
  std::cerr << "prism-bench-e2e: " << m << "\n";
  return 1;
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return -1;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * (v.size() - 1) + 0.5))];
}

double ProcStatusMb(pid_t pid, const std::string& key) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(f, line)) {
    if (line.rfind(key + ":", 0) == 0) return std::atof(line.c_str() + key.size() + 1) / 1024.0;  // kB
  }
  return -1;
}

// The command line.
struct Settings {
  std::string preset = "bunny-multicolor-forward", codecs = "png,jpeg,raw";
  int frames = 150;
  double fps = 0;
  bool live = false;
  int sessions = 1;                         // sessions at once per codec
  std::vector<std::string> server_options;  // --KEY VALUE pairs for prism-server
  std::string argv0;
  std::string truth_dir;  // the preset written by prism-synth: the true surface for prism-eval
};

// The preset rendered in memory.
struct RenderedPreset {
  prism::synth::SynthSetup setup;
  prism::Trajectory trajectory;
  std::vector<cv::Mat> images;
};

// Runs a program next to this one (argv0's folder) with its stdout in `out_file`; its exit status, or -1
// when it could not start.
int RunNextTo(const std::string& argv0, const std::string& program, std::vector<std::string> args,
              const std::string& out_file) {
  const std::string dir = std::filesystem::path(argv0).parent_path().string();
  const std::string binary = (dir.empty() ? std::string(".") : dir) + "/" + program;
  args.insert(args.begin(), binary);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
  std::vector<char*> cargs;
  for (std::string& a : args) cargs.push_back(a.data());
  cargs.push_back(nullptr);
  pid_t pid = 0;
  const int spawned = posix_spawn(&pid, binary.c_str(), &actions, nullptr, cargs.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (spawned != 0) return -1;
  int status = 0;
  waitpid(pid, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

// A prism-server process on a free port, with its files in a temporary folder.
struct ServerProcess {
  pid_t pid = 0;
  std::string tmp, err_file, endpoint, metrics_url;

  // Stops the server and removes its folder.
  void Stop() {
    kill(pid, SIGTERM);
    int status = 0;
    waitpid(pid, &status, 0);
    std::filesystem::remove_all(tmp);
  }
};

// Parses the command line into `settings`: prism::cli::kContinue or the exit status.
int ParseCommandLine(int argc, char** argv, Settings* settings) {
  Settings& s = *settings;
  std::vector<std::string> server_option_pairs;
  CLI::App app{"", "prism-bench-e2e"};
  prism::cli::Setup(&app, "the networked system end to end: prism-server and the SDK streaming a rendered preset",
                    {"prism-bench-e2e [--preset NAME] [--frames N] [--codecs png,jpeg,raw] [--fps F] [--live]",
                     "                [--sessions N] [--server-option KEY=VALUE ...]"},
                    kNotes);
  app.add_option("--preset", s.preset, "the scene (prism-synth --list-presets)")->type_name("NAME");
  app.add_option("--frames", s.frames, "frames rendered and streamed, >= 20")
      ->type_name("N")
      ->check(CLI::Range(20, 1 << 20));
  app.add_option("--codecs", s.codecs, "the codecs, one session each, comma-separated")->type_name("LIST");
  app.add_option("--fps", s.fps, "push at F frames/s as a live camera (0 = as fast as credits allow)")
      ->type_name("F")
      ->check(CLI::NonNegativeNumber);
  app.add_flag("--live", s.live, "open the sessions as a live camera's");
  app.add_option("--sessions", s.sessions, "sessions streaming at once per codec, 1-8")
      ->type_name("N")
      ->check(CLI::Range(1, 8));
  app.add_option("--server-option", server_option_pairs, "passed to prism-server as --KEY VALUE (repeatable)")
      ->type_name("KEY=VALUE")
      ->expected(1)
      ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
  if (const int exit = prism::cli::Parse(&app, argc, argv, /*usage_exit=*/1); exit != prism::cli::kContinue)
    return exit;
  for (const std::string& v : server_option_pairs) {
    const size_t eq = v.find('=');
    if (eq == std::string::npos || eq == 0) return Fail("--server-option wants KEY=VALUE, got '" + v + "'");
    s.server_options.push_back("--" + v.substr(0, eq));
    s.server_options.push_back(v.substr(eq + 1));
  }
  return prism::cli::kContinue;
}

// Renders the preset's frames: prism::cli::kContinue or the exit status.
int Render(const Settings& s, RenderedPreset* rendered) {
  prism::synth::PresetOptions po;
  po.frames = s.frames;
  prism::StatusOr<prism::synth::SynthSetup> setup = prism::synth::MakePreset(s.preset, po);
  if (!setup.ok()) return Fail(setup.status().ToString());
  rendered->setup = std::move(setup).value();
  const prism::synth::SynthSetup& preset = rendered->setup;
  rendered->trajectory = prism::synth::MakeTrajectory(preset.trajectory);
  const prism::Trajectory& trajectory = rendered->trajectory;
  std::vector<cv::Mat>& images = rendered->images;
  images.resize(s.frames);
  {
    prism::ThreadPool pool;
    pool.ParallelFor(0, s.frames, [&](std::ptrdiff_t i) {
      images[i] = prism::synth::RenderFrame(preset.scene, preset.rig, trajectory[i].world_from_camera, preset.render,
                                            1000003ull + static_cast<uint64_t>(i))
                      .rgb;
    });
  }
  return prism::cli::kContinue;
}

// Starts prism-server (next to argv0) and waits for its endpoint: prism::cli::kContinue or the exit status.
int StartServer(const std::string& argv0, const std::vector<std::string>& server_options, ServerProcess* server) {
  const std::string dir = std::filesystem::path(argv0).parent_path().string();
  const std::string binary = (dir.empty() ? std::string(".") : dir) + "/prism-server";
  const std::string tmp =
      (std::filesystem::temp_directory_path() / ("prism_bench_e2e_" + std::to_string(getpid()))).string();
  server->tmp = tmp;
  std::filesystem::create_directories(tmp);
  const std::string out_file = tmp + "/server.json", err_file = tmp + "/server.log";
  server->err_file = err_file;
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, err_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  const std::string data_dir = tmp + "/data";
  std::vector<std::string> args = {
      binary, "--bind",    "tcp://127.0.0.1:*", "--data-dir",  data_dir, "--input-policy", "upload", "--keyframe-queue",
      "64",   "--metrics", "127.0.0.1:0",       "--log-level", "warning"};
  args.insert(args.end(), server_options.begin(), server_options.end());
  std::vector<char*> cargs;
  for (std::string& s : args) cargs.push_back(s.data());
  cargs.push_back(nullptr);
  if (posix_spawn(&server->pid, binary.c_str(), &actions, nullptr, cargs.data(), environ) != 0)
    return Fail("cannot start '" + binary + "'");
  std::string& endpoint = server->endpoint;
  for (int i = 0; i < 200 && endpoint.empty(); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    std::ifstream f(out_file);
    std::string s((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
    const size_t a = s.find("\"endpoint\": \"");
    if (a != std::string::npos) endpoint = s.substr(a + 13, s.find('"', a + 13) - (a + 13));
    const size_t m = s.find("\"metrics\": \"");
    if (m != std::string::npos) server->metrics_url = s.substr(m + 12, s.find('"', m + 12) - (m + 12));
  }
  if (endpoint.empty()) {
    server->Stop();
    return Fail("prism-server did not report its endpoint (see " + err_file + ")");
  }
  return prism::cli::kContinue;
}

// What one session's events show, with their arrival times (the session's event callback).
struct StreamEvents {
  std::map<uint64_t, Clock::time_point> sent;  // frame sequence number -> send time
  std::vector<double> frame_to_pose;
  // Keyframe id -> arrival of the pose of the frame that became it. Keyframes are numbered in
  // creation order and the first one's frame is still initialising when its pose is sent, so the
  // n-th live is_keyframe pose made keyframe n.
  std::map<uint64_t, Clock::time_point> keyframe_pose_time;
  uint64_t live_keyframes = 0;
  std::map<uint64_t, Clock::time_point> chunk_time;  // keyframe id -> first chunk arrival
  uint64_t chunk_bytes = 0, chunk_points = 0, chunks = 0;
  Clock::time_point last_pose;
  // The latest pose of each tracked frame (a refined one replaces the first).
  std::map<uint64_t, prism::Rigid3d> tracked_poses;

  void Handle(const prism::client::Event& e);
};

void StreamEvents::Handle(const prism::client::Event& e) {
  const auto now = Clock::now();
  if (e.kind == prism::client::Event::Kind::kPose) {
    if (e.pose.state == prism::client::TrackingState::kTracking) {
      const auto& q = e.pose.rotation_xyzw;
      prism::Rigid3d p;
      p.rotation = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).normalized();
      p.translation = Eigen::Vector3d(e.pose.translation[0], e.pose.translation[1], e.pose.translation[2]);
      tracked_poses[e.pose.frame_sequence_number] = p;
    } else {
      tracked_poses.erase(e.pose.frame_sequence_number);
    }
  }
  if (e.kind == prism::client::Event::Kind::kPose && !e.pose.refined) {
    auto it = sent.find(e.pose.frame_sequence_number);
    if (it != sent.end()) frame_to_pose.push_back(std::chrono::duration<double, std::milli>(now - it->second).count());
    if (e.pose.is_keyframe) keyframe_pose_time.emplace(++live_keyframes, now);
    last_pose = now;
  } else if (e.kind == prism::client::Event::Kind::kChunk) {
    ++chunks;
    chunk_bytes += e.chunk.draco.size();
    chunk_points += e.chunk.points.size();
    if (!e.chunk.replaces_map) chunk_time.emplace(e.chunk.keyframe_id, now);
  }
}

// Pushes every frame (at --fps from t0, or as fast as credits allow), recording when each was sent: an
// empty string, or what failed.
std::string PushFrames(const Settings& settings, const RenderedPreset& rendered, Clock::time_point t0,
                       prism::client::Session* session, StreamEvents* events) {
  const double fps = settings.fps;
  const std::vector<cv::Mat>& images = rendered.images;
  for (int i = 0; i < settings.frames; ++i) {
    if (fps > 0) {
      // Wait for the frame's time while taking events: callbacks run only inside the session's calls, so
      // a sleep would hold every pose until the next frame and quantise frame-to-pose to the interval.
      const auto due = t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(i / fps));
      prism::client::Event ignored;
      for (auto now = Clock::now(); now < due; now = Clock::now())
        session->Poll(&ignored,
                      std::max(1, static_cast<int>(std::chrono::duration<double, std::milli>(due - now).count())));
    }
    events->sent[static_cast<uint64_t>(i)] = Clock::now();
    const prism::client::Status s =
        session->PushFrame(static_cast<int64_t>(rendered.trajectory[i].timestamp_s * 1e9), images[i].data,
                           images[i].cols, images[i].rows, static_cast<int>(images[i].step));
    if (!s.ok()) return "push frame " + std::to_string(i) + ": " + s.ToString();
  }
  return "";
}

// The ATE of the tracked poses received as a percentage of the path (Sim(3)-aligned to the rendered
// truth); -1 when too few to align.
double AtePercentOfPath(const StreamEvents& events, const prism::Trajectory& trajectory, int frames) {
  double ate_percent = -1;
  prism::Trajectory gt, est;
  for (const auto& [seq, pose] : events.tracked_poses) {
    if (seq >= static_cast<uint64_t>(frames)) continue;
    gt.push_back(trajectory[seq]);
    est.push_back({trajectory[seq].timestamp_s, pose});
  }
  prism::TrajectoryEvalOptions eo;
  eo.alignment = prism::AlignmentModel::kSim3;
  const prism::StatusOr<prism::AteResult> ate = prism::ComputeAte(gt, est, eo);
  if (ate.ok() && ate->trajectory_length_m > 0) ate_percent = 100.0 * ate->error_m.rmse / ate->trajectory_length_m;
  return ate_percent;
}

// Where a keyframe's time went on the server during one run: the mean ms per keyframe of the keyframe
// queue's wait, the dense stage and its parts (from the differences of the histograms' totals).
prism::Json DenseBreakdown(const std::map<std::string, double>& before, const std::map<std::string, double>& after) {
  auto delta = [&](const std::string& name) {
    auto a = after.find(name);
    auto b = before.find(name);
    return (a == after.end() ? 0.0 : a->second) - (b == before.end() ? 0.0 : b->second);
  };
  auto mean_ms = [&](const std::string& family, const std::string& labels) {
    const std::string suffix = labels.empty() ? "" : "{" + labels + "}";
    const double n = delta(family + "_count" + suffix);
    return n > 0 ? Round2(1000.0 * delta(family + "_sum" + suffix) / n) : -1.0;
  };
  prism::Json j = {{"keyframes", delta("prism_dense_keyframe_seconds_count")},
                   {"queue_wait", mean_ms("prism_keyframe_wait_seconds", "")},
                   {"dense_total", mean_ms("prism_dense_keyframe_seconds", "")}};
  for (const char* part : {"photometric", "fusion", "map", "encode"})
    j[part] = mean_ms("prism_dense_part_seconds", std::string("part=\"") + part + "\"");
  return j;
}

// The session's final map against the preset's true object surface, as docs/benchmarks.md scores maps:
// prism-eval cloud --object-only, the map placed by the Sim(3) alignment of the received poses (in
// metres) to the truth. F-score, precision, completeness and median accuracy (mm); an empty object when
// it could not be scored.
prism::Json ScoreMap(const Settings& settings, const RenderedPreset& rendered, const StreamEvents& events,
                     const std::vector<prism::client::Point>& map, double metres_per_unit, const std::string& tag) {
  if (settings.truth_dir.empty() || map.empty() || !(metres_per_unit > 0)) return prism::Json::object();
  const std::string base = settings.truth_dir + "/../" + tag;
  prism::PointCloud cloud;
  for (const prism::client::Point& p : map) cloud.positions.emplace_back(p.position[0], p.position[1], p.position[2]);
  if (!prism::WritePointCloudPly(base + "_map.ply", cloud).ok()) return prism::Json::object();
  {
    std::ofstream t(base + "_trajectory_metres.txt");
    t << std::setprecision(17);
    for (const auto& [seq, pose] : events.tracked_poses) {
      if (seq >= rendered.trajectory.size()) continue;
      const Eigen::Quaterniond q(pose.rotation);
      const Eigen::Vector3d c = pose.translation * metres_per_unit;
      t << rendered.trajectory[seq].timestamp_s << " " << c.x() << " " << c.y() << " " << c.z() << " " << q.x() << " "
        << q.y() << " " << q.z() << " " << q.w() << "\n";
    }
  }
  const int exit = RunNextTo(settings.argv0, "prism-eval",
                             {"cloud", "--sequence", settings.truth_dir, "--cloud", base + "_map.ply", "--object-only",
                              "--align-trajectory", base + "_trajectory_metres.txt"},
                             base + "_eval.json");
  if (exit != 0) return prism::Json::object();
  std::ifstream f(base + "_eval.json");
  const nlohmann::json e = nlohmann::json::parse(f, nullptr, /*allow_exceptions=*/false);
  if (e.is_discarded() || !e.contains("fscore")) return prism::Json::object();
  auto round3 = [](double v) { return std::round(v * 1000) / 1000; };
  return {{"fscore", round3(e["fscore"].get<double>())},
          {"precision", round3(e["precision"].get<double>())},
          {"completeness", round3(e["completeness"].get<double>())},
          {"accuracy_median_mm", Round2(1000 * e["accuracy_median_m"].get<double>())}};
}

// Streams the frames through one session with the codec and measures it into *result (the server's
// RSS after it included): an empty string, or what failed.
std::string RunCodec(const Settings& settings, const RenderedPreset& rendered, const prism::client::Rig& rig,
                     const ServerProcess& server, const std::string& codec_name, const std::string& tag,
                     prism::Json* result) {
  const std::string& endpoint = server.endpoint;
  const pid_t server_pid = server.pid;
  const std::map<std::string, double> totals_before = prism::FetchMetrics(server.metrics_url, 5000);
  const int frames = settings.frames;
  prism::client::SessionOptions so;
  if (codec_name == "png") so.codec = prism::client::Codec::kPng;
  else if (codec_name == "jpeg") so.codec = prism::client::Codec::kJpeg;
  else if (codec_name == "raw") so.codec = prism::client::Codec::kRaw;
  else return "unknown codec '" + codec_name + "'";
  so.timeout_ms = 60000;
  so.live = settings.live;
  std::unique_ptr<prism::client::Session> session;
  prism::client::Status s = prism::client::Session::Open(endpoint, rig, so, &session);
  if (!s.ok()) return "open: " + s.ToString();
  StreamEvents events;
  session->SetEventCallback([&events](const prism::client::Event& e) { events.Handle(e); });
  const auto t0 = Clock::now();
  if (std::string error = PushFrames(settings, rendered, t0, session.get(), &events); !error.empty()) return error;
  // The sequence numbers the SDK assigns are 0, 1, 2... in push order (checked by the pose count).
  prism::client::Summary summary;
  s = session->Close(600000, &summary);
  if (!s.ok()) return "close: " + s.ToString();
  const auto t_done = Clock::now();
  const double seconds = std::chrono::duration<double>(events.last_pose - t0).count();
  const double ate_percent = AtePercentOfPath(events, rendered.trajectory, frames);
  const double map_seconds = std::chrono::duration<double>(t_done - t0).count();
  std::vector<double> kf_to_chunk;
  Clock::time_point last_chunk = events.last_pose;
  for (const auto& [kf, t] : events.chunk_time) {
    // Keyframe kf is finished when keyframe kf + 1 is made, or at the end of the stream (the last pose).
    auto next = events.keyframe_pose_time.find(kf + 1);
    const Clock::time_point finished = next != events.keyframe_pose_time.end() ? next->second : events.last_pose;
    kf_to_chunk.push_back(std::chrono::duration<double, std::milli>(t - finished).count());
    last_chunk = std::max(last_chunk, t);
  }
  const std::vector<double>& frame_to_pose = events.frame_to_pose;
  *result = {
      {"frames_per_s", Round2(frames / std::max(1e-9, seconds))},
      {"map_frames_per_s", Round2(frames / std::max(1e-9, map_seconds))},
      {"map_complete_after_last_pose_s", Round2(std::chrono::duration<double>(last_chunk - events.last_pose).count())},
      {"map_done_after_last_pose_s", Round2(map_seconds - seconds)},
      {"poses", frame_to_pose.size()},
      {"frame_to_pose_ms_p50", Round2(Percentile(frame_to_pose, 0.5))},
      {"frame_to_pose_ms_p95", Round2(Percentile(frame_to_pose, 0.95))},
      {"keyframe_to_chunk_ms_p50", Round2(Percentile(kf_to_chunk, 0.5))},
      {"keyframe_to_chunk_ms_p95", Round2(Percentile(kf_to_chunk, 0.95))},
      {"uplink_bytes_per_frame", Round2(static_cast<double>(session->bytes_sent()) / frames)},
      {"chunks", events.chunks},
      {"chunk_bits_per_point", Round2(events.chunk_points ? 8.0 * events.chunk_bytes / events.chunk_points : -1)},
      {"keyframes", summary.keyframes},
      {"keyframes_dropped", summary.keyframes_dropped},
      {"keyframes_failed", summary.keyframes_failed},
      {"frames_depth_update_skipped", summary.frames_depth_update_skipped},
      {"frames_dropped", summary.frames_dropped},
      {"ate_percent_of_path", Round2(ate_percent)},
      {"server_rss_mb_after", Round2(ProcStatusMb(server_pid, "VmRSS"))},
      {"server_ms_per_keyframe", DenseBreakdown(totals_before, prism::FetchMetrics(server.metrics_url, 5000))},
      {"map", ScoreMap(settings, rendered, events, session->Map(), summary.metres_per_unit, tag)}};
  return "";
}

}  // namespace

int main(int argc, char** argv) {
  Settings settings;
  if (const int exit = ParseCommandLine(argc, argv, &settings); exit != prism::cli::kContinue) return exit;
  RenderedPreset rendered;
  if (const int exit = Render(settings, &rendered); exit != prism::cli::kContinue) return exit;
  ServerProcess server;
  if (const int exit = StartServer(argv[0], settings.server_options, &server); exit != prism::cli::kContinue)
    return exit;
  // The preset again on disk (the same frames: prism-synth's seed 1 is this render's) for ScoreMap.
  settings.argv0 = argv[0];
  settings.truth_dir = server.tmp + "/truth";
  if (RunNextTo(argv[0], "prism-synth",
                {"--preset", settings.preset, "--frames", std::to_string(settings.frames), "--seed", "1", "--out",
                 settings.truth_dir},
                server.tmp + "/synth.out") != 0) {
    std::cerr << "prism-bench-e2e: prism-synth could not write the preset; the maps are not scored\n";
    settings.truth_dir.clear();
  }

  const prism::RigCalibration& rig = rendered.setup.rig;
  prism::Json json;
  json["preset"] = settings.preset;
  json["frames"] = settings.frames;
  json["push_fps"] = Round2(settings.fps);
  json["live"] = settings.live;
  json["size"] = std::to_string(rig.camera.width) + "x" + std::to_string(rig.camera.height);
  json["hardware_threads"] = std::thread::hardware_concurrency();
  json["server_rss_mb_idle"] = Round2(ProcStatusMb(server.pid, "VmRSS"));
  json["codecs"] = prism::Json::object();
  const prism::client::Rig client_rig = prism::ToClientRig(rig);
  std::stringstream codec_list(settings.codecs);
  std::string codec_name;
  while (std::getline(codec_list, codec_name, ',')) {
    std::vector<prism::Json> results(static_cast<size_t>(settings.sessions));
    std::vector<std::string> errors(results.size());
    std::vector<std::thread> threads;
    for (size_t i = 0; i < results.size(); ++i)
      threads.emplace_back([&, i] {
        errors[i] = RunCodec(settings, rendered, client_rig, server, codec_name, codec_name + "_" + std::to_string(i),
                             &results[i]);
      });
    for (std::thread& t : threads) t.join();
    for (const std::string& error : errors) {
      if (error.empty()) continue;
      server.Stop();
      return Fail(error);
    }
    if (settings.sessions == 1) {
      json["codecs"][codec_name] = results[0];
    } else {
      json["codecs"][codec_name] = prism::Json{{"sessions", results}};
    }
  }
  json["server_peak_rss_mb"] = Round2(ProcStatusMb(server.pid, "VmHWM"));
  server.Stop();
  std::cout << prism::JsonText(json, 2);
  return 0;
}
