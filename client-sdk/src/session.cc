#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <deque>
#include <exception>
#include <thread>
#include <unordered_map>
#include <unordered_set>

#include <zmq.hpp>

#include "client-sdk/src/rig_wire.h"
#include "core/codec/frame_encoder.h"
#include "core/codec/map_chunk_codec.h"
#include "prism/client/client.h"
#include "prism/v1/session.pb.h"

namespace prism::client {
namespace {

using Clock = std::chrono::steady_clock;

Code FromWire(v1::ErrorCode c) {
  switch (c) {
    case v1::ERROR_CODE_INVALID_ARGUMENT:
      return Code::kInvalidArgument;
    case v1::ERROR_CODE_NOT_FOUND:
      return Code::kNotFound;
    case v1::ERROR_CODE_RESOURCE_EXHAUSTED:
      return Code::kResourceExhausted;
    case v1::ERROR_CODE_FAILED_PRECONDITION:
      return Code::kFailedPrecondition;
    case v1::ERROR_CODE_UNAUTHENTICATED:
      return Code::kUnauthenticated;
    case v1::ERROR_CODE_DATA_LOSS:
      return Code::kDataLoss;
    case v1::ERROR_CODE_UNAVAILABLE:
      return Code::kUnavailable;
    case v1::ERROR_CODE_VERSION_MISMATCH:
      return Code::kVersionMismatch;
    default:
      return Code::kInternal;
  }
}

Status Make(Code code, std::string message, bool retryable = false) {
  return Status{code, std::move(message), retryable};
}

v1::FrameCodec ToWire(Codec c) {
  switch (c) {
    case Codec::kPng:
      return v1::FRAME_CODEC_PNG;
    case Codec::kJpeg:
      return v1::FRAME_CODEC_JPEG;
    case Codec::kRaw:
      return v1::FRAME_CODEC_RAW;
  }
  return v1::FRAME_CODEC_UNSPECIFIED;
}

FrameCodec ToCore(Codec c) {
  return c == Codec::kJpeg ? FrameCodec::kJpeg : c == Codec::kRaw ? FrameCodec::kRaw : FrameCodec::kPng;
}

std::vector<Point> ToPoints(const PointCloud& cloud) {
  std::vector<Point> points(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    for (int a = 0; a < 3; ++a) points[i].position[a] = cloud.positions[i][a];
    if (cloud.HasNormals())
      for (int a = 0; a < 3; ++a) points[i].normal[a] = cloud.normals[i][a];
    if (cloud.HasColors())
      for (int a = 0; a < 3; ++a) points[i].color[a] = cloud.colors[i][a];
  }
  return points;
}

}  // namespace

const char* StartCheckName(Summary::StartCheck check) {
  switch (check) {
    case Summary::StartCheck::kPassed:
      return "passed";
    case Summary::StartCheck::kSecondStart:
      return "second_start";
    case Summary::StartCheck::kFirstKept:
      return "first_kept";
    case Summary::StartCheck::kNotRun:
      break;
  }
  return "not_run";
}

const char* CodeName(Code code) {
  switch (code) {
    case Code::kOk:
      return "OK";
    case Code::kInvalidArgument:
      return "INVALID_ARGUMENT";
    case Code::kNotFound:
      return "NOT_FOUND";
    case Code::kResourceExhausted:
      return "RESOURCE_EXHAUSTED";
    case Code::kFailedPrecondition:
      return "FAILED_PRECONDITION";
    case Code::kUnauthenticated:
      return "UNAUTHENTICATED";
    case Code::kDataLoss:
      return "DATA_LOSS";
    case Code::kUnavailable:
      return "UNAVAILABLE";
    case Code::kInternal:
      return "INTERNAL";
    case Code::kVersionMismatch:
      return "VERSION_MISMATCH";
    case Code::kTimeout:
      return "TIMEOUT";
  }
  return "?";
}

const char* TrackingStateName(TrackingState state) {
  switch (state) {
    case TrackingState::kInitialising:
      return "initialising";
    case TrackingState::kTracking:
      return "tracking";
    case TrackingState::kLost:
      return "lost";
    default:
      return "unknown";
  }
}

std::string Status::ToString() const { return ok() ? "OK" : std::string(CodeName(code)) + ": " + message; }

Status DecodeChunk(const uint8_t* data, size_t size, std::vector<Point>* points) {
  StatusOr<PointCloud> cloud = DecodeMapChunk(data, size);
  if (!cloud.ok()) return Make(Code::kDataLoss, cloud.status().message());
  *points = ToPoints(*cloud);
  return Status();
}

struct Session::Impl {
  zmq::context_t context{1};
  std::unique_ptr<zmq::socket_t> socket;
  std::unique_ptr<zmq::socket_t> monitor;  // ZMQ socket events of `socket` (disconnects, CURVE refusals)
  std::string endpoint;
  SessionOptions options;
  Rig rig;
  std::string session_id, resume_token;
  int64_t frame_credits = 0;
  double voxel_m = 0.002;
  uint64_t next_sequence = 0;
  uint64_t bytes_sent = 0;
  bool opened = false, closed = false, summary_received = false, close_sent = false;
  bool read_only = false;
  // The server's per-session frame-rate limit (0 = none), kept here so frames are paced, not refused.
  double max_frame_rate_hz = 0, rate_tokens = 0, rate_burst = 1;
  uint64_t max_frame_bytes = 0;  // from SessionOpened; 0 = unknown
  Clock::time_point rate_refilled = Clock::now();
  // Reply to the last OpenSession (new or resume).
  bool got_opened = false;
  uint64_t resume_next_frame = 0;
  Status open_error;
  // Connection state from the monitor.
  bool need_reconnect = false, reconnecting = false;
  int reconnects = 0;
  // Resume bookkeeping: what was received, and the frames not yet answered by a pose.
  int64_t last_chunk = -1;
  uint64_t next_pose = 0;
  std::unordered_set<uint64_t> chunks_seen;
  struct SentFrame {
    v1::Envelope envelope;
    std::vector<uint8_t> bytes;
  };
  std::deque<SentFrame> unanswered;  // at most kMaxUnanswered
  static constexpr size_t kMaxUnanswered = 64;
  Summary summary;
  std::deque<Event> events;
  std::function<void(const Event&)> callback;
  std::unordered_map<uint64_t, Point> map;  // by voxel
  int64_t map_replaced_at = -1;             // sequence of the latest chunk with replaces_map
  std::vector<uint8_t> encode_buffer;

  static uint64_t VoxelKey(const Point& p, double voxel_m) {
    const Eigen::Vector3i v =
        VoxelOfDecodedPoint(Eigen::Vector3f(p.position[0], p.position[1], p.position[2]), voxel_m);
    auto u = [](int c) { return static_cast<uint64_t>(static_cast<uint32_t>(c) & 0x1FFFFFu); };
    return u(v.x()) | (u(v.y()) << 21) | (u(v.z()) << 42);
  }

  void Emit(Event&& e) {
    if (callback) callback(e);
    else events.push_back(std::move(e));
  }

  // A fresh DEALER (and its monitor) connected to the endpoint; the old one is dropped unsent.
  Status Connect() {
    static std::atomic<uint64_t> monitor_counter{0};
    try {
      monitor.reset();
      socket.reset();
      socket = std::make_unique<zmq::socket_t>(context, zmq::socket_type::dealer);
      socket->set(zmq::sockopt::linger, 1000);
      socket->set(zmq::sockopt::heartbeat_ivl, 1000);
      socket->set(zmq::sockopt::heartbeat_timeout, 5000);
      socket->set(zmq::sockopt::heartbeat_ttl, 5000);
      socket->set(zmq::sockopt::reconnect_ivl, 100);
      socket->set(zmq::sockopt::reconnect_ivl_max, 2000);
      if (!options.server_public_key.empty()) {
        if (!zmq_has("curve")) return Make(Code::kUnavailable, "this libzmq has no CURVE support");
        if (options.server_public_key.size() != 40 || options.client_public_key.size() != 40 ||
            options.client_secret_key.size() != 40)
          return Make(Code::kInvalidArgument,
                      "CURVE needs server_public_key, client_public_key and client_secret_key (Z85, 40 characters)");
        socket->set(zmq::sockopt::curve_serverkey, options.server_public_key);
        socket->set(zmq::sockopt::curve_publickey, options.client_public_key);
        socket->set(zmq::sockopt::curve_secretkey, options.client_secret_key);
      }
      const std::string monitor_endpoint = "inproc://prism-client-monitor-" + std::to_string(++monitor_counter);
      if (zmq_socket_monitor(socket->handle(), monitor_endpoint.c_str(),
                             ZMQ_EVENT_DISCONNECTED | ZMQ_EVENT_HANDSHAKE_FAILED_AUTH |
                                 ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL | ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL) != 0)
        return Make(Code::kInternal, "zmq_socket_monitor failed");
      monitor = std::make_unique<zmq::socket_t>(context, zmq::socket_type::pair);
      monitor->set(zmq::sockopt::linger, 0);
      monitor->connect(monitor_endpoint);
      socket->connect(endpoint);
    } catch (const zmq::error_t& e) {
      return Make(Code::kInvalidArgument, "cannot connect to '" + endpoint + "': " + e.what());
    }
    return Status();
  }

  bool SendEnvelope(const v1::Envelope& env, const std::vector<uint8_t>* payload = nullptr) {
    const std::string header = env.SerializeAsString();
    try {
      if (payload) {
        if (!socket->send(zmq::buffer(header), zmq::send_flags::sndmore)) return false;
        return socket->send(zmq::buffer(*payload), zmq::send_flags::none).has_value();
      }
      return socket->send(zmq::buffer(header), zmq::send_flags::none).has_value();
    } catch (const zmq::error_t&) {
      return false;
    }
  }

  v1::Envelope NewEnvelope() {
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    return env;
  }

  v1::Envelope OpenEnvelope() {
    v1::Envelope env = NewEnvelope();
    v1::OpenSession* o = env.mutable_open_session();
    o->set_protocol_version(v1::PROTOCOL_VERSION_1);
    o->set_codec(ToWire(options.codec));
    o->set_client_name(options.client_name);
    o->set_input_policy(options.live ? v1::INPUT_POLICY_LIVE : v1::INPUT_POLICY_UPLOAD);
    o->set_initial_chunk_credits(static_cast<uint32_t>(options.chunk_credits));
    if (!session_id.empty()) {
      o->set_resume_session_id(session_id);
      o->set_resume_token(resume_token);
      o->set_resume_next_chunk(static_cast<uint64_t>(last_chunk + 1));
      o->set_resume_next_pose(next_pose);
      return env;
    }
    RigToWire(rig, o->mutable_calibration());
    return env;
  }

  // Sends OpenSession (new or resume) and waits for the answer: OK, the server's Error, kTimeout, or
  // kUnauthenticated when the CURVE handshake is refused.
  Status OpenOnce(int timeout_ms) {
    got_opened = false;
    open_error = Status();
    if (!SendEnvelope(OpenEnvelope()))
      return Make(Code::kUnavailable, "cannot send OpenSession to '" + endpoint + "'", true);
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (!got_opened && open_error.ok() && Clock::now() < deadline)
      Pump(static_cast<int>(std::max<int64_t>(
          1, std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count())));
    if (!open_error.ok()) return open_error;
    if (!got_opened)
      return Make(Code::kTimeout,
                  "no answer from '" + endpoint + "' within " + std::to_string(timeout_ms) +
                      " ms (is prism-server running there?)",
                  true);
    return Status();
  }

  // After SessionOpened of a resume: frames the server never got go again (as credit allows).
  void AfterResume() {
    while (!unanswered.empty() && unanswered.front().envelope.frame().sequence_number() < resume_next_frame)
      unanswered.pop_front();
    if (read_only) {
      unanswered.clear();
      return;
    }
    for (SentFrame& f : unanswered) {
      if (frame_credits <= 0) break;
      if (!SendEnvelope(f.envelope, &f.bytes)) break;
      --frame_credits;
    }
    if (close_sent) {
      v1::Envelope env = NewEnvelope();
      env.mutable_close()->set_session_id(session_id);
      SendEnvelope(env);
    }
  }

  // The connection dropped: resume on a new socket with backoff until reconnect_timeout_ms.
  void Reconnect() {
    need_reconnect = false;
    if (closed || reconnecting) return;
    reconnecting = true;
    Status last = Make(Code::kUnavailable, "reconnection disabled (reconnect_timeout_ms = 0)");
    const auto deadline = Clock::now() + std::chrono::milliseconds(options.reconnect_timeout_ms);
    int wait_ms = 250;
    bool resumed = false;
    while (Clock::now() < deadline) {
      last = Connect();
      if (!last.ok()) break;
      last = OpenOnce(wait_ms);
      if (last.ok()) {
        resumed = true;
        break;
      }
      // Final answers: the session is gone or the key/token is refused.
      if (last.code == Code::kNotFound || last.code == Code::kUnauthenticated || last.code == Code::kInvalidArgument)
        break;
      wait_ms = std::min(wait_ms * 2, 4000);
    }
    reconnecting = false;
    if (resumed) {
      ++reconnects;
      AfterResume();
      return;
    }
    closed = true;
    Event e;
    e.kind = Event::Kind::kError;
    e.error = Make(last.code == Code::kTimeout ? Code::kUnavailable : last.code,
                   "connection to '" + endpoint + "' lost and session '" + session_id +
                       "' could not be resumed: " + last.ToString());
    Emit(std::move(e));
  }

  void HandleMonitor() {
    for (;;) {
      zmq::message_t event, address;
      if (!monitor->recv(event, zmq::recv_flags::dontwait)) return;
      if (event.more()) (void)monitor->recv(address, zmq::recv_flags::none);
      if (event.size() < 6) continue;
      uint16_t id = 0;
      std::memcpy(&id, event.data(), sizeof(id));
      if (id == ZMQ_EVENT_DISCONNECTED) {
        if (opened && !closed) need_reconnect = true;
      } else if (id == ZMQ_EVENT_HANDSHAKE_FAILED_AUTH) {
        open_error = Make(Code::kUnauthenticated, "the server refused this client's CURVE key (not on its allow-list)");
      } else if (id == ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL && reconnecting) {
        // A server that is going down or starting up drops connections mid-handshake: keep trying (the
        // fault test's restart hit this); only an explicit refusal or a protocol mismatch is final.
        continue;
      } else if (id == ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL || id == ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL) {
        open_error = Make(Code::kUnauthenticated,
                          options.server_public_key.empty()
                              ? "connection handshake failed (does the server require CURVE keys?)"
                              : "CURVE handshake failed (wrong server public key, or the server does not use CURVE)");
      }
    }
  }

  void Handle(std::vector<zmq::message_t>& parts) {
    v1::Envelope env;
    if (parts.empty() || !env.ParseFromArray(parts[0].data(), static_cast<int>(parts[0].size()))) return;
    switch (env.body_case()) {
      case v1::Envelope::kSessionOpened:
        return OnSessionOpened(env.session_opened());
      case v1::Envelope::kFrameCredits:
        frame_credits += env.frame_credits().frames();
        return;
      case v1::Envelope::kPoseUpdate:
        return OnPoseUpdate(env.pose_update());
      case v1::Envelope::kMapChunk:
        return OnMapChunk(env.map_chunk(), parts);
      case v1::Envelope::kSessionSummary:
        return OnSessionSummary(env.session_summary());
      case v1::Envelope::kError:
        return OnError(env.error());
      default:
        return;
    }
  }

  void OnSessionOpened(const v1::SessionOpened& o) {
    session_id = o.session_id();
    if (!o.resume_token().empty()) resume_token = o.resume_token();
    frame_credits = o.initial_frame_credits();
    if (o.map_voxel_m() > 0) voxel_m = o.map_voxel_m();
    read_only = o.read_only();
    max_frame_rate_hz = o.max_frame_rate_hz();
    max_frame_bytes = o.max_frame_bytes();
    rate_burst = std::max<double>(1.0, o.initial_frame_credits());
    rate_tokens = std::min(rate_tokens, rate_burst);
    if (!o.resumed()) rate_tokens = rate_burst;
    rate_refilled = Clock::now();
    resume_next_frame = o.next_frame_sequence();
    got_opened = true;
    opened = true;
  }

  void OnPoseUpdate(const v1::PoseUpdate& p) {
    if (!p.refined()) {
      if (p.frame_sequence_number() < next_pose) return;  // resent after a resume, already seen
      next_pose = p.frame_sequence_number() + 1;
      while (!unanswered.empty() && unanswered.front().envelope.frame().sequence_number() <= p.frame_sequence_number())
        unanswered.pop_front();
    }
    Event e;
    e.kind = Event::Kind::kPose;
    e.pose.frame_sequence_number = p.frame_sequence_number();
    e.pose.timestamp_ns = p.timestamp_ns();
    const v1::Pose& w = p.world_from_camera();
    e.pose.rotation_xyzw = {w.rotation().x(), w.rotation().y(), w.rotation().z(), w.rotation().w()};
    e.pose.translation = {w.translation().x(), w.translation().y(), w.translation().z()};
    e.pose.state = p.state() == v1::PoseUpdate::TRACKING_STATE_TRACKING       ? TrackingState::kTracking
                   : p.state() == v1::PoseUpdate::TRACKING_STATE_INITIALISING ? TrackingState::kInitialising
                   : p.state() == v1::PoseUpdate::TRACKING_STATE_LOST         ? TrackingState::kLost
                                                                              : TrackingState::kUnknown;
    e.pose.is_keyframe = p.is_keyframe();
    e.pose.keyframe_id = p.keyframe_id();
    e.pose.refined = p.refined();
    e.pose.metres_per_unit = p.metres_per_unit();
    e.pose.has_tracking = p.has_tracking();
    if (p.has_tracking()) {
      const v1::TrackingQuality& t = p.tracking();
      e.pose.tracking = {t.residual_rms(), t.visible_fraction(), t.inlier_fraction(), t.iterations(), t.retried(),
                         t.step(),         t.rotation_deg(),     t.guess_correction()};
    }
    Emit(std::move(e));
  }

  // A chunk: [envelope][Draco bytes]; its credit goes back at once.
  void OnMapChunk(const v1::MapChunk& c, const std::vector<zmq::message_t>& parts) {
    // Grant the credit back: this chunk is consumed.
    v1::Envelope credit = NewEnvelope();
    credit.mutable_chunk_credits()->set_session_id(session_id);
    credit.mutable_chunk_credits()->set_chunks(1);
    SendEnvelope(credit);
    const uint64_t seq = c.chunk_sequence_number();
    if (!chunks_seen.insert(seq).second) return;  // resent after a resume, already seen
    last_chunk = std::max(last_chunk, static_cast<int64_t>(seq));
    Event e;
    e.kind = Event::Kind::kChunk;
    e.chunk.keyframe_id = c.keyframe_id();
    e.chunk.sequence_number = seq;
    if (parts.size() >= 2) {
      const auto* d = static_cast<const uint8_t*>(parts[1].data());
      e.chunk.draco.assign(d, d + parts[1].size());
    }
    const Status s = DecodeChunk(e.chunk.draco.data(), e.chunk.draco.size(), &e.chunk.points);
    if (!s.ok()) {
      Event err;
      err.kind = Event::Kind::kError;
      err.error = Make(Code::kDataLoss, "map chunk " + std::to_string(e.chunk.sequence_number) + ": " + s.message);
      Emit(std::move(err));
      return;
    }
    e.chunk.replaces_map = c.replaces_map();
    if (e.chunk.replaces_map && static_cast<int64_t>(seq) > map_replaced_at) {
      map.clear();
      map_replaced_at = static_cast<int64_t>(seq);
    }
    // A chunk older than the latest rebuilt map is void (its voxels are in the rebuilt map).
    if (static_cast<int64_t>(seq) >= map_replaced_at)
      for (const Point& p : e.chunk.points) map[VoxelKey(p, voxel_m)] = p;
    Emit(std::move(e));
  }

  void OnSessionSummary(const v1::SessionSummary& s) {
    summary.frames_received = s.frames_received();
    summary.frames_dropped = s.frames_dropped();
    summary.frames_rejected = s.frames_rejected();
    summary.keyframes = s.keyframes();
    summary.keyframes_dropped = s.keyframes_dropped();
    summary.keyframes_failed = s.keyframes_failed();
    summary.frames_depth_update_skipped = s.frames_depth_update_skipped();
    summary.chunks_sent = s.chunks_sent();
    summary.map_points = s.map_points();
    summary.metres_per_unit = s.metres_per_unit();
    summary.reason = s.reason();
    summary.shading_check = s.shading_check() == v1::SHADING_CHECK_CONSISTENT  ? Summary::ShadingCheck::kConsistent
                            : s.shading_check() == v1::SHADING_CHECK_DISTORTED ? Summary::ShadingCheck::kDistorted
                                                                               : Summary::ShadingCheck::kNotRun;
    summary.shading_pair_spread = s.shading_pair_spread();
    summary.start_check = s.start_check() == v1::START_CHECK_PASSED         ? Summary::StartCheck::kPassed
                          : s.start_check() == v1::START_CHECK_SECOND_START ? Summary::StartCheck::kSecondStart
                          : s.start_check() == v1::START_CHECK_FIRST_KEPT   ? Summary::StartCheck::kFirstKept
                                                                            : Summary::StartCheck::kNotRun;
    summary.start_pair_spread = s.start_pair_spread();
    summary_received = true;
    closed = true;
    Event e;
    e.kind = Event::Kind::kSummary;
    e.summary = summary;
    Emit(std::move(e));
  }

  void OnError(const v1::Error& w) {
    Status s = Make(FromWire(w.code()), w.message(), w.retryable());
    if (!opened || reconnecting) {
      open_error = s;
      return;
    }
    // The session is gone once its summary is here: a NOT_FOUND for it answers a message sent before
    // the summary arrived (the credit for its last chunks), and changes nothing.
    if (summary_received && w.code() == v1::ERROR_CODE_NOT_FOUND && w.session_id() == session_id) return;
    if (w.has_frame()) {
      for (auto it = unanswered.begin(); it != unanswered.end(); ++it)
        if (it->envelope.frame().sequence_number() == w.frame_sequence_number()) {
          unanswered.erase(it);
          break;
        }
    }
    // A server that restarted does not know this session on this connection: resume it.
    if (w.session_closed() && w.code() == v1::ERROR_CODE_NOT_FOUND && w.session_id() == session_id &&
        options.reconnect_timeout_ms > 0) {
      need_reconnect = true;
      return;
    }
    if (w.session_closed()) closed = true;
    Event e;
    e.kind = Event::Kind::kError;
    e.error = s;
    Emit(std::move(e));
  }

  // Handles incoming messages, waiting up to timeout_ms for the first; resumes after a lost connection.
  void Pump(int timeout_ms) {
    zmq::pollitem_t items[2] = {{socket->handle(), 0, ZMQ_POLLIN, 0}, {monitor->handle(), 0, ZMQ_POLLIN, 0}};
    try {
      zmq::poll(items, 2, std::chrono::milliseconds(timeout_ms));
      HandleMonitor();
      for (;;) {
        std::vector<zmq::message_t> parts;
        zmq::message_t part;
        if (!socket->recv(part, zmq::recv_flags::dontwait)) break;
        parts.push_back(std::move(part));
        while (parts.back().more()) {
          zmq::message_t next;
          (void)socket->recv(next, zmq::recv_flags::none);
          parts.push_back(std::move(next));
        }
        Handle(parts);
      }
    } catch (const zmq::error_t&) {
    }
    if (need_reconnect && !reconnecting) Reconnect();
  }
};

Session::Session(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Session::~Session() = default;

namespace {

Status CheckOptions(const SessionOptions& options) {
  if (options.jpeg_quality < 1 || options.jpeg_quality > 100)
    return Make(Code::kInvalidArgument, "SessionOptions.jpeg_quality must be in [1, 100]");
  if (options.chunk_credits < 1) return Make(Code::kInvalidArgument, "SessionOptions.chunk_credits must be >= 1");
  if (options.timeout_ms < 1) return Make(Code::kInvalidArgument, "SessionOptions.timeout_ms must be >= 1");
  if (options.reconnect_timeout_ms < 0)
    return Make(Code::kInvalidArgument, "SessionOptions.reconnect_timeout_ms must be >= 0");
  return Status();
}

}  // namespace

Status Session::Open(const std::string& endpoint, const Rig& rig, const SessionOptions& options,
                     std::unique_ptr<Session>* session) {
  if (Status s = CheckOptions(options); !s.ok()) return s;
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  impl->rig = rig;
  impl->endpoint = endpoint;
  if (Status s = impl->Connect(); !s.ok()) return s;
  if (Status s = impl->OpenOnce(options.timeout_ms); !s.ok()) return s;
  session->reset(new Session(std::move(impl)));
  return Status();
}

Status Session::Resume(const std::string& endpoint, const std::string& session_id, const std::string& resume_token,
                       const SessionOptions& options, std::unique_ptr<Session>* session) {
  if (Status s = CheckOptions(options); !s.ok()) return s;
  if (session_id.empty() || resume_token.empty())
    return Make(Code::kInvalidArgument, "Resume needs a session id and its resume token");
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  impl->endpoint = endpoint;
  impl->session_id = session_id;
  impl->resume_token = resume_token;
  if (Status s = impl->Connect(); !s.ok()) return s;
  if (Status s = impl->OpenOnce(options.timeout_ms); !s.ok()) return s;
  session->reset(new Session(std::move(impl)));
  return Status();
}

Status Session::PushFrame(int64_t timestamp_ns, const uint8_t* rgb, int width, int height, int stride_bytes) {
  if (rgb == nullptr || width <= 0 || height <= 0 || stride_bytes < width * 3)
    return Make(Code::kInvalidArgument, "PushFrame: bad image buffer or size");
  FrameEncodeOptions eo;
  eo.codec = ToCore(impl_->options.codec);
  eo.jpeg_quality = impl_->options.jpeg_quality;
  const prism::Status s =
      EncodeRgbFrame(rgb, width, height, static_cast<size_t>(stride_bytes), eo, &impl_->encode_buffer);
  if (!s.ok()) return Make(Code::kInvalidArgument, s.message());
  return PushEncoded(timestamp_ns, impl_->options.codec, impl_->encode_buffer, width, height);
}

Status Session::PushEncoded(int64_t timestamp_ns, Codec codec, const std::vector<uint8_t>& bytes, int width,
                            int height) {
  Impl& m = *impl_;
  m.Pump(0);
  auto ended = [&] {
    return Make(Code::kFailedPrecondition,
                m.read_only ? "the session has ended on the server (" +
                                  (m.summary_received ? m.summary.reason : std::string("read-only")) + ")"
                            : std::string("the session is closed"));
  };
  if (m.closed || m.read_only) return ended();
  // A larger frame would be refused (or, past the message limit, cost the connection).
  if (m.max_frame_bytes > 0 && bytes.size() > m.max_frame_bytes)
    return Make(Code::kInvalidArgument, "frame of " + std::to_string(bytes.size()) +
                                            " bytes exceeds the server's max_frame_bytes " +
                                            std::to_string(m.max_frame_bytes));
  const auto deadline = Clock::now() + std::chrono::milliseconds(m.options.timeout_ms);
  while (m.frame_credits <= 0 && !m.closed && !m.read_only && Clock::now() < deadline) m.Pump(5);
  if (m.closed || m.read_only) return ended();
  if (m.frame_credits <= 0)
    return Make(Code::kResourceExhausted,
                "no frame credit from the server within " + std::to_string(m.options.timeout_ms) + " ms", true);
  if (m.max_frame_rate_hz > 0) {
    // Pace to the server's limit (slightly under it, so clock jitter never trips the server's bucket).
    const double rate = 0.95 * m.max_frame_rate_hz;
    for (;;) {
      const auto now = Clock::now();
      m.rate_tokens =
          std::min(m.rate_burst, m.rate_tokens + std::chrono::duration<double>(now - m.rate_refilled).count() * rate);
      m.rate_refilled = now;
      if (m.rate_tokens >= 1.0) break;
      m.Pump(std::max(1, static_cast<int>(1000.0 * (1.0 - m.rate_tokens) / rate)));
      if (m.closed || m.read_only) return ended();
    }
    m.rate_tokens -= 1.0;
  }
  Impl::SentFrame sent;
  sent.envelope = m.NewEnvelope();
  v1::Frame* f = sent.envelope.mutable_frame();
  f->set_session_id(m.session_id);
  f->set_sequence_number(m.next_sequence++);
  f->set_timestamp_ns(timestamp_ns);
  f->set_codec(ToWire(codec));
  f->set_width(static_cast<uint32_t>(width));
  f->set_height(static_cast<uint32_t>(height));
  if (!m.SendEnvelope(sent.envelope, &bytes)) return Make(Code::kUnavailable, "cannot send the frame", true);
  --m.frame_credits;
  m.bytes_sent += bytes.size();
  // Kept until its pose arrives, to be sent again if the connection drops first.
  if (m.options.reconnect_timeout_ms > 0) {
    sent.bytes = bytes;
    m.unanswered.push_back(std::move(sent));
    if (m.unanswered.size() > Impl::kMaxUnanswered) m.unanswered.pop_front();
  }
  return Status();
}

int Session::frame_credits() const { return static_cast<int>(impl_->frame_credits); }

bool Session::Poll(Event* event, int timeout_ms) {
  Impl& m = *impl_;
  if (m.events.empty()) m.Pump(timeout_ms);
  else m.Pump(0);
  if (m.events.empty()) return false;
  *event = std::move(m.events.front());
  m.events.pop_front();
  return true;
}

void Session::SetEventCallback(std::function<void(const Event&)> callback) { impl_->callback = std::move(callback); }

Status Session::Close(int timeout_ms, Summary* summary) {
  Impl& m = *impl_;
  if (!m.summary_received) {
    if (!m.read_only && !m.close_sent) {
      v1::Envelope env = m.NewEnvelope();
      env.mutable_close()->set_session_id(m.session_id);
      if (!m.SendEnvelope(env)) return Make(Code::kUnavailable, "cannot send Close");
      m.close_sent = true;
    }
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (!m.summary_received && Clock::now() < deadline) {
      m.Pump(20);
      if (m.closed && !m.summary_received) break;  // ended without a summary (error event says why)
    }
  }
  if (!m.summary_received) {
    if (m.closed) return Make(Code::kUnavailable, "the session ended without a summary (see the error events)");
    return Make(Code::kTimeout, "no session summary within " + std::to_string(timeout_ms) + " ms", true);
  }
  if (summary) *summary = m.summary;
  return Status();
}

std::vector<Point> Session::Map() const {
  std::vector<Point> points;
  points.reserve(impl_->map.size());
  for (const auto& [key, p] : impl_->map) points.push_back(p);
  return points;
}

const std::string& Session::session_id() const { return impl_->session_id; }
const std::string& Session::resume_token() const { return impl_->resume_token; }
bool Session::read_only() const { return impl_->read_only; }
int Session::reconnects() const { return impl_->reconnects; }
uint64_t Session::bytes_sent() const { return impl_->bytes_sent; }

Status GenerateKeyPair(std::string* public_key, std::string* secret_key) {
  if (!zmq_has("curve")) return Make(Code::kUnavailable, "this libzmq has no CURVE support");
  char pub[41], sec[41];
  if (zmq_curve_keypair(pub, sec) != 0) return Make(Code::kInternal, "zmq_curve_keypair failed");
  *public_key = pub;
  *secret_key = sec;
  return Status();
}

}  // namespace prism::client
