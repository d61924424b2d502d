// prism-client: streams a sequence or a live source to prism-server and writes what comes back
// (subcommands stream, fetch, view). Any stream or fetch serves the live 3D view with --view HOST:PORT.
#include <prism/client/client.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "core/io/sequence.h"
#include "tools/capture/live_stream.h"
#include "tools/capture/video_source.h"
#include "tools/cli.h"
#include "tools/client/client_output.h"
#include "tools/client/folder_view.h"
#include "tools/client_rig.h"
#include "tools/view/view_server.h"

namespace {

namespace pc = prism::client;
namespace fs = std::filesystem;

constexpr char kStreamNotes[] =
    R"(--sequence sends the colour frames of a sequence (TUM layout with camera.yaml, e.g. prism-synth
output); --source captures them live from SRC, anything OpenCV's VideoCapture opens: a V4L2 device
(/dev/video0, or its index 0), a video file, a GStreamer pipeline ending in appsink, an RTSP URL.
A video file is read as fast as the server takes its frames (nothing lost; time stamps are the file's
own, frame index / frame rate) unless --realtime; a live source is time-stamped at capture (steady
clock) and a frame captured while the server has no room for it is dropped (the newest frame wins).
Photometric stereo reads the lights from the colours: docs/rig.md says why exposure and white balance
must not change during a run; where the driver refuses to lock them, a warning says so.

A frame of the sequence that cannot be read or decoded is not sent (a warning names it; counted in
summary.json's frames_unreadable); one the server refuses (e.g. of the wrong size) is counted in
"errors". Either way the session goes on. Ctrl-C (SIGINT) or SIGTERM stops sending and closes the
session normally.

Writes to DIR: trajectory.txt (TUM: timestamp tx ty tz qx qy qz qw, world_from_camera, metres once the
server has estimated the scale; tracked frames only, as prism-slam), tracking.txt (how each frame
aligned against its keyframe, as prism-slam writes it), map.ply (the running map: positions, normals,
colours; at the end the server rebuilds it at the final keyframe poses and sends it as one chunk that
replaces the map, "map_replaced" in the summary), chunks/<sequence>.drc (the Draco map chunks as
received; Debian's draco_decoder reads them), chunks.json (each chunk's points and whether it replaced
the map) and summary.json (also printed). Progress goes to stderr. DIR/session.json (written as soon as
the session is open) holds the session id and resume token: if the connection drops the client resumes
by itself (every missed chunk is resent).

Exit 0 = finished, 3 = the session was interrupted on the server (its persisted results are written),
1 = failure.)";

constexpr char kFetchNotes[] =
    R"(The persisted results of an ended or interrupted session, into the files `stream` writes. Exit 0 =
finished, 3 = the session was interrupted on the server, 1 = failure.)";

std::atomic<bool> g_stop{false};
std::atomic<prism::LiveStream*> g_live{nullptr};

void OnSignal(int) {
  g_stop = true;
  if (prism::LiveStream* live = g_live.load()) live->Stop();
}

int Fail(const std::string& m) {
  std::cerr << "prism-client: " << m << "\n";
  return 1;
}

struct Args {
  std::string command, server, sequence_dir, source, camera, record_dir, out_dir, fetch_id, fetch_token, client_keys;
  std::string view_address, view_dir;
  std::string codec;  // as given; empty = the default (PNG for a sequence, JPEG for a live source)
  bool realtime = false;
  prism::VideoSourceOptions capture;
  pc::SessionOptions options;
  int max_frames = 1 << 30, close_timeout_ms = 300000, view_linger_s = 0, view_wait_s = 0;
};

// The options `stream` and `fetch` share: the server, the output folder, the waits, CURVE and the view.
void AddSessionOptions(CLI::App* sub, Args* args) {
  pc::SessionOptions& o = args->options;
  sub->add_option("--server", args->server, "prism-server's endpoint, tcp://HOST:PORT")
      ->type_name("ENDPOINT")
      ->required();
  sub->add_option("--out", args->out_dir, "output folder (created)")->type_name("DIR")->required();
  sub->add_option("--timeout-ms", o.timeout_ms, "wait for the server this long (open, credits)")
      ->type_name("MS")
      ->check(CLI::PositiveNumber);
  sub->add_option("--close-timeout-ms", args->close_timeout_ms, "wait this long for the last keyframes at the end")
      ->type_name("MS")
      ->check(CLI::PositiveNumber);
  sub->add_option("--reconnect-timeout-ms", o.reconnect_timeout_ms,
                  "keep trying to resume a lost connection this long (0 = off)")
      ->type_name("MS")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--server-key", o.server_public_key, "the server's CURVE public key (Z85); enables CURVE")
      ->type_name("KEY");
  sub->add_option("--client-keys", args->client_keys, "this client's CURVE key pair (from `prism-server keygen`)")
      ->type_name("FILE");
  sub->add_option("--view", args->view_address,
                  "serve the live 3D view at http://ADDR/ (ADDR is HOST:PORT; port 0 = a free\n"
                  "one; the URL is printed): the map chunk by chunk, the camera's path and\n"
                  "frustum, the session's state. Bind 127.0.0.1 unless others should see it.")
      ->type_name("ADDR");
  sub->add_option("--view-wait", args->view_wait_s, "before streaming, wait up to S seconds for a browser")
      ->type_name("S")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--view-linger", args->view_linger_s, "after the session ends, serve the view S more seconds")
      ->type_name("S")
      ->check(CLI::NonNegativeNumber);
}

// Parses argv into args: cli::kContinue, or the exit status.
int Parse(int argc, char** argv, Args* args) {
  args->options.timeout_ms = 20000;
  CLI::App app{"", "prism-client"};
  prism::cli::Setup(&app, "streams a sequence or a live camera to prism-server and writes what comes back",
                    {"prism-client stream --server tcp://HOST:PORT --sequence DIR --out DIR [options]",
                     "prism-client stream --server tcp://HOST:PORT --source SRC --camera FILE --out DIR [options]",
                     "prism-client fetch --server tcp://HOST:PORT --session ID --token TOKEN --out DIR [options]",
                     "prism-client view DIR [--view HOST:PORT]"},
                    "'prism-client COMMAND --help' lists its options.");
  app.require_subcommand(1);

  CLI::App* stream = app.add_subcommand("stream", "stream a sequence folder or a live source to a session");
  prism::cli::Setup(stream, stream->get_description(),
                    {"prism-client stream --server tcp://HOST:PORT --sequence DIR --out DIR [options]",
                     "prism-client stream --server tcp://HOST:PORT --source SRC --camera FILE --out DIR [options]"},
                    kStreamNotes);
  AddSessionOptions(stream, args);
  pc::SessionOptions& o = args->options;
  stream->add_option("--sequence", args->sequence_dir, "the sequence folder to send")->type_name("DIR");
  stream->add_option("--source", args->source, "capture live from SRC (a device, file, pipeline or URL)")
      ->type_name("SRC");
  stream->add_flag("--realtime", args->realtime,
                   "send at the sequence's (or video file's) frame rate as a live camera:\n"
                   "frames the server has no room for are skipped (frames_skipped)");
  stream
      ->add_option("--codec", args->codec,
                   "png (lossless; default for --sequence), jpeg (4:4:4; default for --source)\nor raw")
      ->type_name("C")
      ->check(CLI::IsMember({"png", "jpeg", "jpg", "raw"}));
  stream->add_option("--jpeg-quality", o.jpeg_quality, "1-100")->type_name("Q")->check(CLI::Range(1, 100));
  stream->add_option("--max-frames", args->max_frames, "stop after N frames (default: all)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::PositiveNumber);
  stream->add_option("--camera", args->camera, "--source: the rig calibration (camera.yaml) at the capture size")
      ->type_name("FILE");
  stream->add_option("--exposure", args->capture.exposure, "--source: set and lock the exposure (V4L2: 100 us units)")
      ->type_name("V")
      ->default_str("");
  stream->add_flag("--lock-exposure", args->capture.lock_exposure, "--source: lock the exposure where it is now");
  stream->add_option("--white-balance", args->capture.white_balance_k, "--source: set and lock the white balance, K")
      ->type_name("K")
      ->default_str("");
  stream->add_flag("--lock-white-balance", args->capture.lock_white_balance,
                   "--source: lock the white balance where it is now");
  stream
      ->add_option("--record", args->record_dir,
                   "--source: also write the captured frames as a sequence folder (rgb.txt,\n"
                   "rgb/, camera.yaml) that `stream --sequence DIR` replays")
      ->type_name("DIR");

  CLI::App* fetch = app.add_subcommand("fetch", "get the persisted results of an ended or interrupted session");
  prism::cli::Setup(fetch, fetch->get_description(),
                    {"prism-client fetch --server tcp://HOST:PORT --session ID --token TOKEN --out DIR [options]"},
                    kFetchNotes);
  AddSessionOptions(fetch, args);
  fetch->add_option("--session", args->fetch_id, "the session id (DIR/session.json of the stream)")
      ->type_name("ID")
      ->required();
  fetch->add_option("--token", args->fetch_token, "its resume token (same file)")->type_name("TOKEN")->required();

  CLI::App* view = app.add_subcommand("view", "show a finished session's folder in the browser");
  prism::cli::Setup(view, view->get_description(), {"prism-client view DIR [--view HOST:PORT]"},
                    "DIR is what `stream` or `fetch` wrote. The URL is printed; Ctrl-C ends it.");
  view->add_option("DIR", args->view_dir, "the folder")->type_name("")->required();
  view->add_option("--view", args->view_address, "serve it at http://ADDR/ (HOST:PORT; port 0 = a free one)")
      ->type_name("ADDR")
      ->default_str("127.0.0.1:0");

  if (const int exit = prism::cli::Parse(&app, argc, argv, /*usage_exit=*/1); exit != prism::cli::kContinue)
    return exit;
  args->command = stream->parsed() ? "stream" : fetch->parsed() ? "fetch" : "view";
  if (!args->codec.empty()) {
    o.codec = args->codec == "raw" ? pc::Codec::kRaw : args->codec == "png" ? pc::Codec::kPng : pc::Codec::kJpeg;
  }
  std::string error;
  if (args->command == "stream") {
    if (args->sequence_dir.empty() == args->source.empty())
      error = "stream needs either --sequence DIR or --source SRC (see --help)";
    else if (!args->source.empty() && args->camera.empty())
      error = "--source needs --camera FILE, the rig calibration (camera.yaml) of the camera at its capture size";
    else if (args->source.empty() && (!args->camera.empty() || !args->record_dir.empty()))
      error = "--camera and --record go with --source (a --sequence brings its own camera.yaml)";
  }
  return error.empty() ? prism::cli::kContinue : Fail(error);
}

// "public = KEY" and "secret = KEY" lines (prism-server keygen's format).
std::string ReadClientKeys(const std::string& path, pc::SessionOptions* options) {
  std::ifstream in(path);
  if (!in) return "cannot read --client-keys '" + path + "'";
  std::string line;
  auto trim = [](std::string& x) {
    x.erase(0, x.find_first_not_of(" \t"));
    x.erase(x.find_last_not_of(" \t\r") + 1);
  };
  while (std::getline(in, line)) {
    const size_t eq = line.find('=');
    if (eq == std::string::npos || line[0] == '#') continue;
    std::string key = line.substr(0, eq), value = line.substr(eq + 1);
    trim(key);
    trim(value);
    if (key == "public") options->client_public_key = value;
    else if (key == "secret") options->client_secret_key = value;
  }
  if (options->client_public_key.empty() || options->client_secret_key.empty())
    return "--client-keys '" + path + "' needs 'public = ...' and 'secret = ...' lines";
  return "";
}

// Progress on one refreshing stderr line (a terminal), or a line every few seconds (a log file).
class ProgressLine {
 public:
  ProgressLine() : tty_(isatty(2) == 1) {}
  void Show(const prism::LiveStats& s) {
    char line[256];
    std::snprintf(line, sizeof(line),
                  "prism-client: %5.1f frames/s, %llu sent, %llu dropped, %s, %zu map points, %llu chunks, %.0f s",
                  s.frames_per_s, static_cast<unsigned long long>(s.sent), static_cast<unsigned long long>(s.dropped()),
                  prism::client::TrackingStateName(s.tracking), s.map_points, static_cast<unsigned long long>(s.chunks),
                  s.seconds);
    if (tty_) {
      std::fprintf(stderr, "\r%-110s", line);
      open_ = true;
    } else if (s.seconds >= next_log_s_) {
      std::fprintf(stderr, "%s\n", line);
      next_log_s_ = s.seconds + kLogIntervalS;
    }
  }
  void End() {
    if (open_) std::fprintf(stderr, "\n");
    open_ = false;
  }

 private:
  static constexpr double kLogIntervalS = 5.0;
  bool tty_, open_ = false;
  double next_log_s_ = 0;
};

struct StreamCounts {
  size_t frames = 0, sent = 0, skipped = 0, unreadable = 0;
};

// Sends the frames of a sequence folder (as fast as credits allow, or at its frame rate).
std::string StreamSequence(const Args& args, const prism::Sequence& seq, pc::Session* session,
                           prism::ClientOutput* output, prism::ViewServer* view, StreamCounts* counts) {
  const auto start = std::chrono::steady_clock::now();
  const size_t n = std::min(seq.frames.size(), static_cast<size_t>(args.max_frames));
  counts->frames = n;
  const double t0 = n ? seq.frames[0].timestamp_s : 0.0;
  auto drain = [&] {
    pc::Event e;
    while (session->Poll(&e, 0)) output->OnEvent(e);
  };
  prism::ViewStatus status;
  status.session = session->session_id();
  status.source = args.sequence_dir;
  status.state = "streaming";
  size_t chunks_seen = 0;
  for (size_t i = 0; i < n && output->fatal().empty() && !session->read_only() && !g_stop; ++i) {
    prism::StatusOr<cv::Mat> rgb = seq.ReadRgb(i);
    if (!rgb.ok()) {  // the session goes on without it (counted; summary.json's frames_unreadable)
      ++counts->unreadable;
      std::cerr << "prism-client: frame " << i << ": " << rgb.status().ToString() << "; not sent\n";
      continue;
    }
    if (args.realtime) {
      std::this_thread::sleep_until(start + std::chrono::duration<double>(seq.frames[i].timestamp_s - t0));
      drain();
      if (session->frame_credits() <= 0) {  // a live camera does not wait
        ++counts->skipped;
        continue;
      }
    }
    const int64_t ts = static_cast<int64_t>(seq.frames[i].timestamp_s * 1e9 + 0.5);
    const pc::Status st =
        session->PushFrame(ts, rgb->ptr<uint8_t>(), rgb->cols, rgb->rows, static_cast<int>(rgb->step));
    if (!st.ok() && (session->read_only() || st.code == pc::Code::kFailedPrecondition)) {
      // The session ended on the server (interrupted, failed or reaped): collect what arrived and what
      // it persisted, then report.
      std::cerr << "prism-client: frame " << i << ": " << st.ToString() << " (read-only " << session->read_only()
                << ", reconnects " << session->reconnects() << ")\n";
      break;
    }
    if (!st.ok()) return "frame " + std::to_string(i) + ": " + st.ToString();
    ++counts->sent;
    drain();
    if ((i + 1) % 10 == 0 || i + 1 == n)
      std::cerr << "prism-client: sent " << (i + 1) << "/" << n << " frames, " << output->poses() << " poses, "
                << output->chunks() << " chunks\n";
    if (view) {
      const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      if (output->chunks() != chunks_seen) {
        chunks_seen = output->chunks();
        status.map_points = session->Map().size();
      }
      status.tracking = prism::client::TrackingStateName(output->tracking());
      status.frames_sent = counts->sent;
      status.frames_dropped = counts->skipped;
      status.poses = output->poses();
      status.frames_per_s = seconds > 0 ? static_cast<double>(counts->sent) / seconds : 0.0;
      status.seconds = seconds;
      view->SetStatus(status);
    }
  }
  return "";
}

// The live source (--source) and its recording (--record), opened before the session so that a bad
// source or folder fails at once.
struct Capture {
  std::unique_ptr<prism::VideoSource> source;
  std::unique_ptr<prism::SequenceRecorder> recorder;
};

std::string OpenCapture(const Args& args, const pc::Rig& rig, Capture* capture) {
  prism::VideoSourceOptions options = args.capture;
  options.source = args.source;
  options.width = rig.camera.width;
  options.height = rig.camera.height;
  prism::StatusOr<std::unique_ptr<prism::VideoSource>> source = prism::VideoSource::Open(options);
  if (!source.ok()) return source.status().ToString();
  capture->source = std::move(*source);
  std::cerr << "prism-client: capturing from '" << args.source << "' (" << capture->source->backend() << ", "
            << (capture->source->is_file() ? "video file" : "live") << ", " << capture->source->frames_per_s()
            << " frames/s)\n";
  for (const std::string& note : capture->source->notes()) std::cerr << "prism-client: " << note << "\n";
  int width = 0, height = 0;
  if (prism::Status s = capture->source->PeekSize(&width, &height); !s.ok())
    return "source '" + args.source + "' gave no frame: " + s.ToString();
  if (width != rig.camera.width || height != rig.camera.height)
    return "source '" + args.source + "' gives " + std::to_string(width) + "x" + std::to_string(height) +
           " frames, but --camera '" + args.camera + "' is calibrated for " + std::to_string(rig.camera.width) + "x" +
           std::to_string(rig.camera.height) +
           " (calibrate the camera at the size it captures, or make it capture the calibrated size)";
  if (!args.record_dir.empty()) {
    prism::StatusOr<std::unique_ptr<prism::SequenceRecorder>> r =
        prism::SequenceRecorder::Create(args.record_dir, args.camera);
    if (!r.ok()) return r.status().ToString();
    capture->recorder = std::move(*r);
  }
  return "";
}

// Streams the capture (tools/capture/live_stream.h); the capture's fields go into j.
std::string StreamSource(const Args& args, const pc::Rig& rig, Capture* capture, pc::Session* session,
                         prism::ClientOutput* output, prism::ViewServer* view, nlohmann::ordered_json* j) {
  prism::SequenceRecorder* recorder = capture->recorder.get();
  prism::LiveStreamOptions live;
  live.realtime = args.realtime;
  live.max_frames = args.max_frames;
  live.width = rig.camera.width;
  live.height = rig.camera.height;
  prism::LiveStream stream(session, capture->source.get(), recorder, live);
  g_live = &stream;
  if (g_stop) stream.Stop();
  ProgressLine progress;
  prism::ViewStatus status;
  status.session = session->session_id();
  status.source = args.source;
  status.state = "streaming";
  const prism::Status st = stream.Run([&](const pc::Event& e) { output->OnEvent(e); },
                                      [&](const prism::LiveStats& s) {
                                        progress.Show(s);
                                        if (!view) return;
                                        status.frames_per_s = s.frames_per_s;
                                        status.frames_sent = s.sent;
                                        status.frames_dropped = s.dropped();
                                        status.poses = s.poses;
                                        status.tracking = prism::client::TrackingStateName(s.tracking);
                                        status.map_points = s.map_points;
                                        status.seconds = s.seconds;
                                        view->SetStatus(status);
                                      });
  g_live = nullptr;
  progress.End();
  const prism::LiveStats& s = stream.stats();
  std::cerr << "prism-client: capture ended (" << s.end << ")\n";
  std::string error = st.ok() ? "" : st.ToString();
  if (recorder) {
    const prism::Status r = recorder->Finish();
    std::cerr << "prism-client: recorded " << recorder->written() << " frames into " << args.record_dir
              << (recorder->dropped() ? " (" + std::to_string(recorder->dropped()) + " not recorded: disk too slow)"
                                      : std::string())
              << "\n";
    if (!r.ok() && error.empty()) error = r.ToString();
  }
  (*j)["source"] = args.source;
  (*j)["frames_captured"] = s.captured;
  (*j)["frames_sent"] = s.sent;
  (*j)["frames_skipped"] = s.dropped();
  (*j)["frames_skipped_no_credit"] = s.skipped_no_credit;
  (*j)["frames_skipped_stale"] = s.skipped_stale;
  (*j)["frames_per_s"] = s.frames_per_s;
  (*j)["capture_end"] = s.end;
  (*j)["exposure_locked"] = capture->source->exposure_locked();
  (*j)["white_balance_locked"] = capture->source->white_balance_locked();
  if (recorder) {
    (*j)["recorded"] = recorder->written();
    (*j)["record_dropped"] = recorder->dropped();
  }
  return error;
}

// After the session: keep the view up for a while (or until Ctrl-C) so a person can look at it.
void Linger(prism::ViewServer* view, int seconds) {
  if (!view || seconds <= 0) return;
  std::cerr << "prism-client: the view stays at " << view->url() << " for " << seconds << " s (Ctrl-C ends it)\n";
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(seconds);
  while (!g_stop && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
}

int Run(Args& args) {
  signal(SIGINT, OnSignal);
  signal(SIGTERM, OnSignal);
  if (!args.client_keys.empty())
    if (std::string e = ReadClientKeys(args.client_keys, &args.options); !e.empty()) return Fail(e);
  const bool live = !args.source.empty();
  if (live && args.codec.empty()) args.options.codec = pc::Codec::kJpeg;  // JPEG 4:4:4 for live capture
  args.options.client_name = "prism-client";

  // The rig: the sequence's camera.yaml, or --camera for a live source.
  pc::Rig rig;
  prism::Sequence seq;
  if (args.command == "stream" && !live) {
    prism::StatusOr<prism::Sequence> s = prism::LoadSequence(args.sequence_dir);
    if (!s.ok()) return Fail(s.status().ToString());
    if (!s->has_calibration)
      return Fail("sequence '" + args.sequence_dir + "' has no camera.yaml (the rig calibration)");
    seq = std::move(*s);
    rig = prism::ToClientRig(seq.calibration);
  }
  Capture capture;
  if (live) {
    if (pc::Status s = pc::LoadRig(args.camera, &rig); !s.ok()) return Fail("--camera: " + s.ToString());
    if (std::string e = OpenCapture(args, rig, &capture); !e.empty()) return Fail(e);
  }
  // The live policy (the server drops the oldest queued frame, and skips depth updates sooner when
  // behind) for a camera and for --realtime. A video file read as fast as the server takes it waits
  // for credits and loses nothing, as an upload: it gets the upload policy, so that it streams as its
  // frames stored in a folder would.
  args.options.live = args.realtime || (live && !capture.source->is_file());
  std::error_code ec;
  fs::create_directories(args.out_dir + "/chunks", ec);
  if (ec) return Fail("cannot create '" + args.out_dir + "/chunks': " + ec.message());

  std::unique_ptr<prism::ViewServer> view;
  if (!args.view_address.empty()) {
    prism::StatusOr<std::string> web = prism::ViewServer::FindWebDir();
    if (!web.ok()) return Fail(web.status().ToString());
    prism::StatusOr<std::unique_ptr<prism::ViewServer>> v = prism::ViewServer::Start(args.view_address, *web);
    if (!v.ok()) return Fail(v.status().ToString());
    view = std::move(*v);
    view->SetCamera(rig.camera);
    std::cerr << "prism-client: live view at " << view->url() << "\n";
    if (args.view_wait_s > 0) {
      std::cerr << "prism-client: waiting up to " << args.view_wait_s << " s for a browser to open it\n";
      if (!view->WaitForPage(args.view_wait_s * 1000, g_stop))
        std::cerr << "prism-client: no browser came; streaming anyway\n";
    }
  }

  std::unique_ptr<pc::Session> session;
  pc::Status st = args.command == "fetch"
                      ? pc::Session::Resume(args.server, args.fetch_id, args.fetch_token, args.options, &session)
                      : pc::Session::Open(args.server, rig, args.options, &session);
  if (!st.ok())
    return Fail((args.command == "fetch" ? "cannot fetch session " + args.fetch_id + " from "
                                         : std::string("cannot open a session on ")) +
                args.server + ": " + st.ToString());
  std::cerr << "prism-client: session " << session->session_id() << " on " << args.server << "\n";
  {
    nlohmann::ordered_json j;
    j["session"] = session->session_id();
    j["token"] = session->resume_token();
    j["server"] = args.server;
    std::ofstream(args.out_dir + "/session.json") << j.dump() << "\n";
  }
  prism::ClientOutput output(args.out_dir, view.get());
  nlohmann::ordered_json capture_fields;
  StreamCounts counts;
  const auto start = std::chrono::steady_clock::now();
  std::string error;
  if (args.command == "stream")
    error = live ? StreamSource(args, rig, &capture, session.get(), &output, view.get(), &capture_fields)
                 : StreamSequence(args, seq, session.get(), &output, view.get(), &counts);
  if (!error.empty() && session->bytes_sent() == 0) return Fail(error);  // nothing sent: nothing to collect
  if (!error.empty()) std::cerr << "prism-client: " << error << "; closing the session\n";
  if (!output.fatal().empty()) return Fail("the session failed: " + output.fatal());
  if (session->read_only() && args.command == "stream")
    std::cerr << "prism-client: the server lost the running session (restart); fetching what it persisted\n";
  if (view) {
    prism::ViewStatus status;
    status.session = session->session_id();
    status.state = "closing";
    status.poses = output.poses();
    view->SetStatus(status);
  }
  std::cerr << "prism-client: stream done; waiting for the last keyframes\n";
  // Close, handling events as they come (chunks keep arriving while the server finishes).
  pc::Summary summary;
  // Events handled as they arrive inside Close (the last keyframes' chunks reach the view one by one).
  pc::Event e;
  while (session->Poll(&e, 0)) output.OnEvent(e);
  session->SetEventCallback([&output](const pc::Event& event) { output.OnEvent(event); });
  st = session->Close(args.close_timeout_ms, &summary);
  session->SetEventCallback(nullptr);
  while (session->Poll(&e, 0)) output.OnEvent(e);
  if (!st.ok()) return Fail("close: " + st.ToString());
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  prism::StatusOr<nlohmann::ordered_json> j = output.Write(*session, summary);
  if (!j.ok()) return Fail(j.status().ToString());
  if (live) {
    for (auto& [k, v] : capture_fields.items()) (*j)[k] = v;
  } else if (args.command == "stream") {
    (*j)["frames_sent"] = counts.sent;
    (*j)["frames_skipped"] = counts.skipped;
    (*j)["frames_unreadable"] = counts.unreadable;
    (*j)["frames_per_s"] = seconds > 0 ? static_cast<double>(counts.sent) / seconds : 0.0;
  }
  const double sent = (*j).value("frames_sent", 0.0);
  (*j)["uplink_bytes_per_frame"] = sent > 0 ? static_cast<double>(session->bytes_sent()) / sent : 0.0;
  (*j)["seconds"] = seconds;
  if (prism::Status w = output.WriteSummary(*j); !w.ok()) return Fail(w.ToString());
  if (session->reconnects() > 0)
    std::cerr << "prism-client: resumed after " << session->reconnects() << " lost connection(s)\n";
  if (view) {
    view->SetMetresPerUnit(summary.metres_per_unit);
    prism::ViewStatus status;
    status.session = session->session_id();
    status.source = live ? args.source : args.sequence_dir;
    status.state = error.empty() ? "finished" : "failed: " + error;
    status.frames_sent = static_cast<uint64_t>(sent);
    status.frames_per_s = (*j).value("frames_per_s", 0.0);
    status.tracking = prism::client::TrackingStateName(output.tracking());
    status.poses = output.poses();
    status.map_points = session->Map().size();
    status.seconds = seconds;
    view->SetStatus(status);
    Linger(view.get(), args.view_linger_s);
  }
  if (!error.empty()) return 1;
  return summary.reason.rfind("interrupted", 0) == 0 ? 3 : 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  if (const int exit = Parse(argc, argv, &args); exit != prism::cli::kContinue) return exit;
  if (args.command == "view") {
    signal(SIGINT, OnSignal);
    signal(SIGTERM, OnSignal);
    return prism::ServeFolderView(args.view_dir, args.view_address.empty() ? "127.0.0.1:0" : args.view_address, g_stop);
  }
  return Run(args);
}
