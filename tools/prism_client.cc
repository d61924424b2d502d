// prism-client: streams a sequence to prism-server and writes what comes back.
//   prism-client stream --server tcp://HOST:PORT --sequence DIR --out DIR [--realtime] [--codec png|jpeg|raw]
//   prism-client fetch --server tcp://HOST:PORT --session ID --token TOKEN --out DIR
#include <prism/client/client.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "tools/client_rig.h"

namespace {

constexpr char kUsage[] = R"(usage: prism-client stream --server tcp://HOST:PORT --sequence DIR --out DIR [options]
       prism-client fetch --server tcp://HOST:PORT --session ID --token TOKEN --out DIR [options]

Streams the colour frames of a sequence (TUM layout with camera.yaml, e.g. prism-synth output) to
prism-server and writes to DIR: trajectory.txt (TUM: timestamp tx ty tz qx qy qz qw, world_from_camera,
metres once the server has estimated the scale; tracked frames only, as prism-slam), tracking.txt (how
each frame aligned against its keyframe, as prism-slam writes it), map.ply (the running map: positions, normals,
colours; at the end the server rebuilds it at the final keyframe poses and sends it as one chunk that
replaces the map, "map_replaced" in the summary), chunks/<sequence>.drc (the Draco map chunks as received; Debian's draco_decoder reads
them) and summary.json (also printed). Progress goes to stderr. DIR/session.json (written as soon as
the session is open) holds the session id and resume token: if the connection drops the client resumes
by itself (every missed chunk is resent); `fetch` gets the persisted results of an ended or interrupted
session later, into the same files. Exit 0 = finished, 3 = the session was interrupted on the server
(its persisted results are written), 1 = failure.

options:
  --realtime            send at the sequence's frame rate as a live camera: the server drops the oldest
                        queued frame when behind, and frames without credit are skipped here (counted)
  --codec C             png (lossless, default), jpeg (4:4:4) or raw
  --jpeg-quality Q      1..100 (default 95)
  --max-frames N        stop after N frames
  A frame of the sequence that cannot be read or decoded is not sent (a warning names it; counted in
  summary.json's frames_unreadable); one the server refuses (e.g. of the wrong size) is counted in
  "errors". Either way the session goes on.
  --timeout-ms MS       wait for the server this long (open, credits; default 20000)
  --close-timeout-ms MS wait this long for the last keyframes after the stream (default 300000)
  --reconnect-timeout-ms MS  keep trying to resume a lost connection this long (default 60000; 0 = off)
  --server-key KEY      the server's CURVE public key (Z85); enables CURVE
  --client-keys FILE    this client's CURVE key pair (a file from `prism-server keygen`)
  --help                this text
)";

int Fail(const std::string& m) {
  std::cerr << "prism-client: " << m << "\n";
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  namespace pc = prism::client;
  if (argc >= 2 && (std::string(argv[1]) == "--help" || std::string(argv[1]) == "-h")) {
    std::cout << kUsage;
    return 0;
  }
  const std::string command = argc >= 2 ? argv[1] : "";
  if (command != "stream" && command != "fetch") return Fail("expected the 'stream' or 'fetch' command (see --help)");
  std::string server, sequence_dir, out_dir, fetch_id, fetch_token, client_keys;
  bool realtime = false;
  pc::SessionOptions options;
  options.timeout_ms = 20000;
  int max_frames = 1 << 30, close_timeout_ms = 300000;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h") {
      std::cout << kUsage;
      return 0;
    }
    if (a == "--realtime") {
      realtime = true;
      continue;
    }
    if (i + 1 >= argc) return Fail("unknown argument or missing value: '" + a + "' (see --help)");
    const std::string v = argv[++i];
    char* end = nullptr;
    const long n = std::strtol(v.c_str(), &end, 10);
    const bool is_int = !v.empty() && *end == '\0';
    if (a == "--server") server = v;
    else if (a == "--sequence") sequence_dir = v;
    else if (a == "--out") out_dir = v;
    else if (a == "--codec" && v == "png") options.codec = pc::Codec::kPng;
    else if (a == "--codec" && (v == "jpeg" || v == "jpg")) options.codec = pc::Codec::kJpeg;
    else if (a == "--codec" && v == "raw") options.codec = pc::Codec::kRaw;
    else if (a == "--jpeg-quality" && is_int && n >= 1 && n <= 100) options.jpeg_quality = static_cast<int>(n);
    else if (a == "--max-frames" && is_int && n >= 1) max_frames = static_cast<int>(n);
    else if (a == "--timeout-ms" && is_int && n >= 1) options.timeout_ms = static_cast<int>(n);
    else if (a == "--close-timeout-ms" && is_int && n >= 1) close_timeout_ms = static_cast<int>(n);
    else if (a == "--reconnect-timeout-ms" && is_int && n >= 0) options.reconnect_timeout_ms = static_cast<int>(n);
    else if (a == "--session") fetch_id = v;
    else if (a == "--token") fetch_token = v;
    else if (a == "--server-key") options.server_public_key = v;
    else if (a == "--client-keys") client_keys = v;
    else return Fail("unknown argument or bad value: '" + a + " " + v + "' (see --help)");
  }
  if (!client_keys.empty()) {
    // "public = KEY" and "secret = KEY" lines (prism-server keygen's format).
    std::ifstream in(client_keys);
    if (!in) return Fail("cannot read --client-keys '" + client_keys + "'");
    std::string line;
    while (std::getline(in, line)) {
      const size_t eq = line.find('=');
      if (eq == std::string::npos || line[0] == '#') continue;
      std::string key = line.substr(0, eq), value = line.substr(eq + 1);
      auto trim = [](std::string& x) {
        x.erase(0, x.find_first_not_of(" \t"));
        x.erase(x.find_last_not_of(" \t\r") + 1);
      };
      trim(key);
      trim(value);
      if (key == "public") options.client_public_key = value;
      else if (key == "secret") options.client_secret_key = value;
    }
    if (options.client_public_key.empty() || options.client_secret_key.empty())
      return Fail("--client-keys '" + client_keys + "' needs 'public = ...' and 'secret = ...' lines");
  }
  if (command == "fetch") {
    if (server.empty() || fetch_id.empty() || fetch_token.empty() || out_dir.empty())
      return Fail("fetch needs --server, --session, --token and --out (see --help)");
  } else if (server.empty() || sequence_dir.empty() || out_dir.empty()) {
    return Fail("--server, --sequence and --out are required (see --help)");
  }
  options.live = realtime;
  options.client_name = "prism-client";
  std::error_code ec;
  std::filesystem::create_directories(out_dir + "/chunks", ec);
  if (ec) return Fail("cannot create '" + out_dir + "/chunks': " + ec.message());
  std::unique_ptr<pc::Session> session;
  if (command == "fetch") {
    pc::Status st = pc::Session::Resume(server, fetch_id, fetch_token, options, &session);
    if (!st.ok()) return Fail("cannot fetch session " + fetch_id + " from " + server + ": " + st.ToString());
  }

  prism::Sequence empty_sequence;
  prism::StatusOr<prism::Sequence> seq =
      command == "fetch" ? prism::StatusOr<prism::Sequence>(empty_sequence) : prism::LoadSequence(sequence_dir);
  if (!seq.ok()) return Fail(seq.status().ToString());
  if (command == "stream" && !seq->has_calibration)
    return Fail("sequence '" + sequence_dir + "' has no camera.yaml (the rig calibration)");

  const pc::Rig rig = prism::ToClientRig(seq->calibration);

  pc::Status st;
  if (!session) {
    st = pc::Session::Open(server, rig, options, &session);
    if (!st.ok()) return Fail("cannot open a session on " + server + ": " + st.ToString());
  }
  std::cerr << "prism-client: session " << session->session_id() << " on " << server << "\n";
  {
    nlohmann::ordered_json j;
    j["session"] = session->session_id();
    j["token"] = session->resume_token();
    j["server"] = server;
    std::ofstream(out_dir + "/session.json") << j.dump() << "\n";
  }

  std::map<uint64_t, pc::Pose> poses;  // by frame sequence number: the latest (refined) pose wins
  size_t refined_poses = 0;
  size_t chunks = 0, chunk_bytes = 0, frame_errors = 0, skipped = 0, unreadable = 0;
  bool remapped = false;  // a chunk replaced the map (rebuilt at the final keyframe poses)
  std::string fatal;
  auto drain = [&](int timeout_ms) {
    pc::Event e;
    while (session->Poll(&e, timeout_ms)) {
      timeout_ms = 0;
      if (e.kind == pc::Event::Kind::kPose) {
        refined_poses += e.pose.refined ? 1 : 0;
        poses[e.pose.frame_sequence_number] = e.pose;
      } else if (e.kind == pc::Event::Kind::kChunk) {
        char name[64];
        std::snprintf(name, sizeof(name), "/chunks/%06llu.drc",
                      static_cast<unsigned long long>(e.chunk.sequence_number));
        std::ofstream(out_dir + name, std::ios::binary)
            .write(reinterpret_cast<const char*>(e.chunk.draco.data()),
                   static_cast<std::streamsize>(e.chunk.draco.size()));
        ++chunks;
        chunk_bytes += e.chunk.draco.size();
        remapped = remapped || e.chunk.replaces_map;
        std::cerr << "prism-client: chunk " << e.chunk.sequence_number;
        if (e.chunk.replaces_map) std::cerr << " (the map rebuilt at the final keyframe poses)";
        else std::cerr << " (keyframe " << e.chunk.keyframe_id << ")";
        std::cerr << ": " << e.chunk.points.size() << " points, " << e.chunk.draco.size() << " bytes\n";
      } else if (e.kind == pc::Event::Kind::kError) {
        ++frame_errors;
        std::cerr << "prism-client: server error: " << e.error.ToString() << "\n";
        if (e.error.code == pc::Code::kNotFound || e.error.code == pc::Code::kInternal ||
            e.error.code == pc::Code::kUnavailable)
          fatal = e.error.ToString();
      }
    }
  };

  const auto start = std::chrono::steady_clock::now();
  const size_t n = std::min(seq->frames.size(), static_cast<size_t>(max_frames));
  const double t0 = n ? seq->frames[0].timestamp_s : 0.0;
  for (size_t i = 0; i < n && fatal.empty() && !session->read_only(); ++i) {
    prism::StatusOr<cv::Mat> rgb = seq->ReadRgb(i);
    if (!rgb.ok()) {  // the session goes on without it (counted; summary.json's frames_unreadable)
      ++unreadable;
      std::cerr << "prism-client: frame " << i << ": " << rgb.status().ToString() << "; not sent\n";
      continue;
    }
    if (realtime) {
      std::this_thread::sleep_until(start + std::chrono::duration<double>(seq->frames[i].timestamp_s - t0));
      drain(0);
      if (session->frame_credits() <= 0) {  // a live camera does not wait
        ++skipped;
        continue;
      }
    }
    const int64_t ts = static_cast<int64_t>(seq->frames[i].timestamp_s * 1e9 + 0.5);
    st = session->PushFrame(ts, rgb->ptr<uint8_t>(), rgb->cols, rgb->rows, static_cast<int>(rgb->step));
    if (!st.ok() && (session->read_only() || st.code == pc::Code::kFailedPrecondition)) {
      // The session ended on the server (interrupted, failed or reaped): collect what arrived and what
      // it persisted, then report.
      std::cerr << "prism-client: frame " << i << ": " << st.ToString() << " (read-only " << session->read_only()
                << ", reconnects " << session->reconnects() << ")\n";
      break;
    }
    if (!st.ok()) return Fail("frame " + std::to_string(i) + ": " + st.ToString());
    drain(0);
    if ((i + 1) % 10 == 0 || i + 1 == n)
      std::cerr << "prism-client: sent " << (i + 1) << "/" << n << " frames, " << poses.size() << " poses, " << chunks
                << " chunks\n";
  }
  if (!fatal.empty()) return Fail("the session failed: " + fatal);
  if (session->read_only() && command == "stream")
    std::cerr << "prism-client: the server lost the running session (restart); fetching what it persisted\n";
  pc::Summary summary;
  std::cerr << "prism-client: stream done; waiting for the last keyframes\n";
  // Close, handling events as they come (chunks keep arriving while the server finishes).
  st = session->Close(close_timeout_ms, &summary);
  drain(0);
  if (!st.ok()) return Fail("close: " + st.ToString());
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  // Trajectory, scaled to metres by the final session scale when known.
  const double s = summary.metres_per_unit > 0 ? summary.metres_per_unit : 1.0;
  {
    std::ofstream traj(out_dir + "/trajectory.txt");
    traj << "# timestamp tx ty tz qx qy qz qw (world_from_camera, metres per unit " << s << ")\n";
    char line[256];
    for (const auto& [sequence, p] : poses) {
      if (p.state != pc::TrackingState::kTracking) continue;  // provisional (initialising) or lost
      std::snprintf(line, sizeof(line), "%.6f %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n", p.timestamp_ns * 1e-9,
                    p.translation[0] * s, p.translation[1] * s, p.translation[2] * s, p.rotation_xyzw[0],
                    p.rotation_xyzw[1], p.rotation_xyzw[2], p.rotation_xyzw[3]);
      traj << line;
    }
  }
  {
    // As prism-slam's tracking.txt: each frame aligned against a keyframe, as the server tracked it.
    std::ofstream tracking(out_dir + "/tracking.txt");
    tracking << "# timestamp keyframe_id residual_rms visible_fraction inlier_fraction iterations retried step "
                "rotation_deg guess_correction\n";
    char line[256];
    for (const auto& [sequence, p] : poses) {
      if (!p.has_tracking) continue;
      const pc::TrackingQuality& q = p.tracking;
      std::snprintf(line, sizeof(line), "%.6f %lld %g %g %g %u %d %g %g %g\n", p.timestamp_ns * 1e-9,
                    static_cast<long long>(p.keyframe_id), q.residual_rms, q.visible_fraction, q.inlier_fraction,
                    q.iterations, q.retried ? 1 : 0, q.step, q.rotation_deg, q.guess_correction);
      tracking << line;
    }
  }
  const std::vector<pc::Point> map = session->Map();
  prism::PointCloud cloud;
  for (const pc::Point& p : map) {
    cloud.positions.emplace_back(p.position[0], p.position[1], p.position[2]);
    cloud.normals.emplace_back(p.normal[0], p.normal[1], p.normal[2]);
    cloud.colors.emplace_back(p.color[0], p.color[1], p.color[2]);
  }
  if (prism::Status w = prism::WritePointCloudPly(out_dir + "/map.ply", cloud); !w.ok()) return Fail(w.ToString());
  const size_t sent = n - skipped - unreadable;
  nlohmann::ordered_json j;
  j["session"] = session->session_id();
  j["frames_sent"] = sent;
  j["frames_skipped"] = skipped;
  j["frames_unreadable"] = unreadable;
  j["poses"] = poses.size();
  j["refined_poses"] = refined_poses;
  j["chunks"] = chunks;
  j["chunk_bytes"] = chunk_bytes;
  j["map_points"] = map.size();
  j["map_replaced"] = remapped;
  j["errors"] = frame_errors;
  j["uplink_bytes"] = session->bytes_sent();
  j["uplink_bytes_per_frame"] = sent > 0 ? static_cast<double>(session->bytes_sent()) / static_cast<double>(sent) : 0.0;
  j["seconds"] = seconds;
  j["frames_per_s"] = seconds > 0 ? static_cast<double>(sent) / seconds : 0.0;
  j["server_keyframes"] = summary.keyframes;
  j["server_keyframes_failed"] = summary.keyframes_failed;
  j["server_map_points"] = summary.map_points;
  j["server_frames_depth_update_skipped"] = summary.frames_depth_update_skipped;
  j["metres_per_unit"] = summary.metres_per_unit;
  j["shading_check"] = summary.shading_check == pc::Summary::ShadingCheck::kConsistent  ? "consistent"
                       : summary.shading_check == pc::Summary::ShadingCheck::kDistorted ? "distorted"
                                                                                        : "not_run";
  j["shading_pair_spread"] = summary.shading_pair_spread;
  j["start_check"] = pc::StartCheckName(summary.start_check);
  j["start_pair_spread"] = summary.start_pair_spread;
  j["reconnects"] = session->reconnects();
  j["reason"] = summary.reason;
  const std::string json = j.dump(-1, ' ', false, nlohmann::ordered_json::error_handler_t::replace) + "\n";
  std::cout << json;
  std::ofstream(out_dir + "/summary.json") << json;
  if (session->reconnects() > 0)
    std::cerr << "prism-client: resumed after " << session->reconnects() << " lost connection(s)\n";
  return summary.reason.rfind("interrupted", 0) == 0 ? 3 : 0;
}
