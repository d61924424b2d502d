// libprism_client: stream frames to prism-server, get poses and the dense map back.
//
//   prism::client::Rig rig;                             // camera + the three lights
//   prism::client::Status s = prism::client::LoadRig("camera.yaml", &rig);
//   std::unique_ptr<prism::client::Session> session;
//   s = prism::client::Session::Open("tcp://127.0.0.1:5555", rig, {}, &session);
//   s = session->PushFrame(timestamp_ns, rgb, width, height, width * 3);   // RGB (not OpenCV's BGR), encoded inside
//   prism::client::Event event;
//   while (session->Poll(&event, 0)) { ... event.pose / event.chunk ... }
//   prism::client::Summary summary;
//   s = session->Close(60000, &summary);
//   std::vector<prism::client::Point> map = session->Map();  // the running map, one point per voxel
//
// No exceptions cross this API, and no ZeroMQ or protobuf type appears in it. A Session is not
// thread-safe: one thread calls it. Callbacks (SetEventCallback) run on that thread, inside PushFrame,
// Poll and Close.
//
// Reliability: when the connection drops (or the server restarts), the session reconnects by itself
// with backoff (SessionOptions::reconnect_timeout_ms) and resumes: the server resends every map chunk
// and pose the client missed, and the frames it never received are sent again. A session the server
// can no longer run (it restarted meanwhile) turns read-only: its persisted poses and chunks arrive,
// then a Summary whose reason says "interrupted". Session::Resume fetches the results of an ended
// session later (its id and resume_token()).
//
// Security: with SessionOptions::server_public_key set, the connection uses ZeroMQ CURVE (encrypted,
// and the server admits only the client public keys on its allow-list); a refused key is
// kUnauthenticated at once, not a timeout. GenerateKeyPair makes keys (as `prism-server keygen`).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace prism::client {

enum class Code {
  kOk = 0,
  kInvalidArgument,
  kNotFound,
  kResourceExhausted,
  kFailedPrecondition,
  kUnauthenticated,
  kDataLoss,
  kUnavailable,
  kInternal,
  kVersionMismatch,
  kTimeout,  // no answer from the server in time
};
const char* CodeName(Code code);

struct Status {
  Code code = Code::kOk;
  std::string message;
  bool retryable = false;
  bool ok() const { return code == Code::kOk; }
  std::string ToString() const;  // "RESOURCE_EXHAUSTED: message"
};

struct Camera {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  // k1 k2 p1 p2 k3 (OpenCV). Send the raw frames with their lens distortion: the server undistorts
  // every frame into a pinhole camera of the same size; poses and map chunks are not affected.
  std::array<double, 5> distortion{0, 0, 0, 0, 0};
};

struct Light {
  std::string name;
  bool directional = false;
  std::array<double, 3> position_in_camera{0, 0, 0};    // metres, point lights
  std::array<double, 3> direction_in_camera{0, 0, -1};  // towards the light, directional lights
  std::array<double, 3> color{1, 1, 1};
  double intensity = 0.25;
};

struct Rig {
  Camera camera;
  std::array<Light, 3> lights;                                 // red, green, blue
  std::array<double, 9> crosstalk{1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major (camera channel, light)
};

enum class Codec { kPng, kJpeg, kRaw };

struct SessionOptions {
  Codec codec = Codec::kPng;
  int jpeg_quality = 95;  // [1, 100]; JPEG is always 4:4:4
  // true: the server drops the oldest queued frame when full (live camera); false: it refuses new
  // frames (upload) and PushFrame waits for credit.
  bool live = false;
  // Map chunks the server may send ahead; the SDK grants one more per chunk it receives.
  int chunk_credits = 8;
  std::string client_name = "libprism_client";
  // How long Open waits for SessionOpened, and PushFrame for a frame credit, ms.
  int timeout_ms = 10000;
  // After a lost connection, how long to keep trying to resume (backoff 0.25 s doubling to 4 s), ms;
  // 0 = never reconnect (the session ends with a kUnavailable error).
  int reconnect_timeout_ms = 60000;
  // CURVE (Z85 keys, 40 characters): the server's public key, and this client's key pair (its public
  // key must be on the server's allow-list). All empty = plain TCP.
  std::string server_public_key;
  std::string client_public_key;
  std::string client_secret_key;
};

enum class TrackingState { kUnknown, kInitialising, kTracking, kLost };
// "initialising", "tracking", "lost", "unknown".
const char* TrackingStateName(TrackingState state);

// How the server's SLAM aligned a frame against its keyframe (Pose::tracking): distances are fractions
// of the keyframe's mean depth. A tracked frame whose inlier fraction drops or whose result lies far from
// its constant-velocity guess (guess_correction near step) is about to be lost.
struct TrackingQuality {
  double residual_rms = 0;      // grey levels, the inlier residuals at the finest pyramid level
  double visible_fraction = 0;  // of the keyframe's points, projecting into the frame
  double inlier_fraction = 0;   // of those, inliers
  uint32_t iterations = 0;      // Gauss-Newton iterations over all levels
  bool retried = false;         // the constant-velocity guess failed; tracked again from the last pose
  double step = 0;              // translation from the previous frame
  double rotation_deg = 0;      // rotation from the previous frame
  double guess_correction = 0;  // distance of the result from the constant-velocity guess
};

struct Pose {
  uint64_t frame_sequence_number = 0;
  int64_t timestamp_ns = 0;
  std::array<double, 4> rotation_xyzw{0, 0, 0, 1};  // world_from_camera, SLAM units
  std::array<double, 3> translation{0, 0, 0};
  TrackingState state = TrackingState::kUnknown;
  bool is_keyframe = false;
  double metres_per_unit = 0;  // 0 until the server has estimated the scale
  int64_t keyframe_id = -1;    // the keyframe this frame was tracked against, -1 = none
  // A later, better pose of a frame already received (sent at the end of a session for the frames
  // the SLAM moved afterwards: initialisation, loop closures); the latest pose of a frame wins.
  bool refined = false;
  // Set when the frame was aligned against a keyframe (not while initialising, lost or relocalised).
  bool has_tracking = false;
  TrackingQuality tracking;
};

struct Point {
  std::array<float, 3> position{0, 0, 0};  // metres
  std::array<float, 3> normal{0, 0, 0};
  std::array<uint8_t, 3> color{0, 0, 0};
};

struct MapChunk {
  uint64_t keyframe_id = 0;
  uint64_t sequence_number = 0;
  std::vector<uint8_t> draco;  // the chunk as sent (a .drc file)
  std::vector<Point> points;   // decoded
  // The server rebuilt its map at the final keyframe poses (end of the session): this chunk voids every
  // earlier one. Session::Map() clears itself before applying it; a client keeping its own map does the
  // same, and ignores older chunks that arrive after it.
  bool replaces_map = false;
};

struct Summary {
  uint64_t frames_received = 0, frames_dropped = 0, frames_rejected = 0;
  uint64_t keyframes = 0, keyframes_dropped = 0, keyframes_failed = 0;
  // Frames the server tracked without their depth update because it had fallen behind
  // (SessionSummary.frames_depth_update_skipped; its skip-depth-update-backlog option).
  uint64_t frames_depth_update_skipped = 0;
  uint64_t chunks_sent = 0, map_points = 0;
  double metres_per_unit = 0;
  std::string reason;
  // The server's check of the reconstruction against the co-moving lights' shading at the end:
  // kDistorted says the trajectory and map are probably distorted (SessionSummary.shading_check).
  enum class ShadingCheck { kNotRun, kConsistent, kDistorted };
  ShadingCheck shading_check = ShadingCheck::kNotRun;
  double shading_pair_spread = 0;
  // The server's SLAM start check (SessionSummary.start_check): kSecondStart says the first start
  // disagreed with the shading and a second start replaced it (every pose was sent again, refined).
  enum class StartCheck { kNotRun, kPassed, kSecondStart, kFirstKept };
  StartCheck start_check = StartCheck::kNotRun;
  double start_pair_spread = 0;  // the first start's pair spread
};

// "not_run", "passed", "second_start", "first_kept".
const char* StartCheckName(Summary::StartCheck check);

struct Event {
  enum class Kind { kPose, kChunk, kError, kSummary };
  Kind kind = Kind::kPose;
  Pose pose;
  MapChunk chunk;
  Status error;  // kError: a frame or the session failed (error.message says which)
  Summary summary;
};

class Session {
 public:
  // Connects a DEALER socket to `endpoint`, opens a session and waits for SessionOpened.
  static Status Open(const std::string& endpoint, const Rig& rig, const SessionOptions& options,
                     std::unique_ptr<Session>* session);
  // Re-attaches to a session by id and resume token: a running one goes on (its missed chunks and
  // poses are resent); an ended one (finished, or interrupted by a server restart) replays all its
  // persisted poses and chunks, then its Summary (read_only() is true). kNotFound for an unknown id,
  // kUnauthenticated for a wrong token.
  static Status Resume(const std::string& endpoint, const std::string& session_id, const std::string& resume_token,
                       const SessionOptions& options, std::unique_ptr<Session>* session);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Encodes and sends one RGB frame (8-bit, R first; rows `stride_bytes` apart). OpenCV captures and
  // decodes BGR (cv::VideoCapture, cv::imread): convert first (cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB)),
  // else red and blue swap, and with them the red and blue lights the photometric stereo tells apart.
  // The frame must be the calibration's size (Rig::camera), else the server refuses it. Waits up to
  // timeout_ms for a frame credit, handling incoming messages meanwhile. kResourceExhausted (retryable)
  // when no credit came in time.
  Status PushFrame(int64_t timestamp_ns, const uint8_t* rgb, int width, int height, int stride_bytes);
  // Sends already encoded bytes (testing, or a camera that encodes itself).
  Status PushEncoded(int64_t timestamp_ns, Codec codec, const std::vector<uint8_t>& bytes, int width, int height);
  // Frames sendable now.
  int frame_credits() const;

  // Next event, waiting up to timeout_ms (0 = do not wait). false when none. With a callback set, events
  // go to the callback instead and Poll returns false.
  bool Poll(Event* event, int timeout_ms);
  void SetEventCallback(std::function<void(const Event&)> callback);

  // Ends the stream, waits until the server has finished the keyframes in flight and sent their chunks
  // and the summary (at most timeout_ms). Events received meanwhile stay pollable.
  Status Close(int timeout_ms, Summary* summary);

  // The running map: every chunk received so far, merged by voxel (a later chunk replaces a voxel);
  // from a chunk with replaces_map on (the map rebuilt at the final keyframe poses) only that chunk and
  // the ones after it.
  std::vector<Point> Map() const;
  const std::string& session_id() const;
  // The secret that lets this client (or another) resume the session; keep it with the id.
  const std::string& resume_token() const;
  // The session has ended on the server; only its persisted results (and the Summary) still come.
  bool read_only() const;
  // Successful automatic resumes after a lost connection.
  int reconnects() const;
  // Bytes of frame payloads sent so far.
  uint64_t bytes_sent() const;

 private:
  struct Impl;
  explicit Session(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Reads a rig calibration file (camera.yaml, OpenCV FileStorage YAML: width height fx fy cx cy,
// distortion, three lights, crosstalk; the format prism-synth writes, README "Calibration") into `rig`.
// kNotFound when the file cannot be opened, kInvalidArgument (naming the field) when it is malformed.
Status LoadRig(const std::string& path, Rig* rig);

// Reads a Draco map chunk (a .drc from the server) into points.
Status DecodeChunk(const uint8_t* data, size_t size, std::vector<Point>* points);

// A CURVE key pair, Z85-encoded (40 characters each). kUnavailable when libzmq has no CURVE.
Status GenerateKeyPair(std::string* public_key, std::string* secret_key);

}  // namespace prism::client
