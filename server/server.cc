#include "server/server.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <sstream>
#include <unordered_map>
#include <vector>

#include <zmq.hpp>

#include "core/io/ply_io.h"
#include "core/pipeline/dense_workers.h"
#include "core/pipeline/session_pipeline.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"
#include "prism/v1/session.pb.h"
#include "server/curve.h"
#include "server/http_endpoint.h"
#include "server/memory_trimmer.h"
#include "server/metrics.h"
#include "server/rig_wire.h"
#include "server/session_store.h"

namespace prism::server {
namespace {

using Clock = std::chrono::steady_clock;

v1::ErrorCode ToWireCode(StatusCode code) {
  switch (code) {
    case StatusCode::kInvalidArgument:
    case StatusCode::kOutOfRange:
      return v1::ERROR_CODE_INVALID_ARGUMENT;
    case StatusCode::kNotFound:
      return v1::ERROR_CODE_NOT_FOUND;
    case StatusCode::kResourceExhausted:
      return v1::ERROR_CODE_RESOURCE_EXHAUSTED;
    case StatusCode::kFailedPrecondition:
      return v1::ERROR_CODE_FAILED_PRECONDITION;
    case StatusCode::kUnauthenticated:
      return v1::ERROR_CODE_UNAUTHENTICATED;
    case StatusCode::kDataLoss:
      return v1::ERROR_CODE_DATA_LOSS;
    case StatusCode::kUnavailable:
      return v1::ERROR_CODE_UNAVAILABLE;
    default:
      return v1::ERROR_CODE_INTERNAL;
  }
}

StatusOr<FrameCodec> FromWireCodec(v1::FrameCodec c) {
  switch (c) {
    case v1::FRAME_CODEC_PNG:
      return FrameCodec::kPng;
    case v1::FRAME_CODEC_JPEG:
      return FrameCodec::kJpeg;
    case v1::FRAME_CODEC_RAW:
      return FrameCodec::kRaw;
    default:
      return InvalidArgumentError("frame codec " + std::to_string(static_cast<int>(c)) + " is not png, jpeg or raw");
  }
}

void ToWire(const Rigid3d& pose, v1::Pose* out) {
  out->mutable_rotation()->set_x(pose.rotation.x());
  out->mutable_rotation()->set_y(pose.rotation.y());
  out->mutable_rotation()->set_z(pose.rotation.z());
  out->mutable_rotation()->set_w(pose.rotation.w());
  out->mutable_translation()->set_x(pose.translation.x());
  out->mutable_translation()->set_y(pose.translation.y());
  out->mutable_translation()->set_z(pose.translation.z());
}

// The last frame a session accepted into its queue: later frames' sequence numbers must be above its,
// their timestamps not before its.
struct AcceptedFrame {
  uint64_t sequence_number = 0;
  int64_t timestamp_ns = 0;
};

// The Frame fields the contract constrains (session.proto, Frame): a stated size equal to the camera's,
// sequence numbers that increase (gaps allowed), timestamps that do not go back.
Status CheckFrameFields(const v1::Frame& frame, int camera_width, int camera_height,
                        const std::optional<AcceptedFrame>& last) {
  if ((frame.width() != 0 && frame.width() != static_cast<uint32_t>(camera_width)) ||
      (frame.height() != 0 && frame.height() != static_cast<uint32_t>(camera_height)))
    return InvalidArgumentError("Frame.width x Frame.height = " + std::to_string(frame.width()) + "x" +
                                std::to_string(frame.height()) + " differ from the session's camera " +
                                std::to_string(camera_width) + "x" + std::to_string(camera_height) +
                                " (0 = not stated)");
  if (!last) return Status::Ok();
  if (frame.sequence_number() <= last->sequence_number)
    return InvalidArgumentError("Frame.sequence_number " + std::to_string(frame.sequence_number()) +
                                " is not above the last accepted frame's " + std::to_string(last->sequence_number) +
                                " (sequence numbers must increase; gaps are allowed)");
  if (frame.timestamp_ns() < last->timestamp_ns)
    return InvalidArgumentError("Frame.timestamp_ns " + std::to_string(frame.timestamp_ns()) +
                                " is before the last accepted frame's " + std::to_string(last->timestamp_ns) +
                                " (timestamps must not go back)");
  return Status::Ok();
}

std::string RandomHex(int bytes) {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  static const char* kHex = "0123456789abcdef";
  std::string s;
  for (int i = 0; i < bytes; ++i) {
    const auto b = static_cast<unsigned>(rng() & 0xFF);
    s += kHex[b >> 4];
    s += kHex[b & 15];
  }
  return s;
}

}  // namespace

// Approximate bytes per voxel of a session's map (position, normal, colour, confidence, hash entry).
constexpr double kMapBytesPerPoint = 96;
// A point of a keyframe cloud kept for the map's rebuild (DenseStage::Remap).
constexpr double kKeptBytesPerPoint = DenseStage::kKeptBytesPerPoint;

struct Server::Impl {
  // Per session, transport thread only (except pipeline, which is thread-safe).
  struct Session {
    std::string id;
    std::string peer;  // ZeroMQ routing id of the client's DEALER
    std::string client_name;
    int camera_width = 0, camera_height = 0;                      // the calibration's
    v1::InputPolicy input_policy = v1::INPUT_POLICY_UNSPECIFIED;  // in force (for a resumed SessionOpened)
    std::optional<AcceptedFrame> last_accepted;
    std::unique_ptr<SessionPipeline> pipeline;
    int64_t chunk_credits = 0;
    // Chunks waiting for credits, in order. Persisted ones beyond the first
    // options.max_pending_chunks_in_memory wait on disk only (read back when sent), so a client that
    // grants no credits costs no memory.
    struct PendingChunk {
      uint64_t sequence = 0;
      bool on_disk = false;  // envelope and bytes not loaded
      v1::Envelope envelope;
      std::vector<uint8_t> bytes;
    };
    std::deque<PendingChunk> pending_chunks;
    size_t pending_in_memory = 0, pending_bytes_in_memory = 0;
    // Frame-rate limit: a token bucket of frames (capacity = the frame queue), refilled at
    // options.max_frame_rate_hz.
    double rate_tokens = 0;
    Clock::time_point rate_refilled;
    bool memory_limit_hit = false;
    uint32_t frame_credits_to_grant = 0;
    Clock::time_point last_activity;
    bool closing = false;   // Close received, idle timeout or shutdown: no more frames
    bool finished = false;  // the pipeline's kFinished arrived
    std::string reason;     // why it ends
    PipelineStats stats;    // at kFinished
    uint64_t poses_sent = 0, chunks_sent = 0, frames_refused = 0;
    std::string resume_token;
    // Replay of an ended session (resume after it finished or after a server restart): no pipeline;
    // its persisted chunks go out, then `replay_summary`.
    bool replay = false;
    v1::SessionSummary replay_summary;
    std::vector<uint64_t> chunk_sequences;  // persisted, ascending
    PoseLog pose_log;
    uint64_t next_frame_sequence = 0;  // 1 + the highest frame sequence number received
    // Frames in the pipeline and when they arrived (for prism_frame_to_pose_seconds), oldest first.
    std::deque<std::pair<uint64_t, Clock::time_point>> frame_arrivals;
    uint64_t frames_dropped = 0;  // dropped or refused, for prism_session_frames_dropped
    bool credits_exhausted_logged = false;
  };
  struct Outgoing {
    std::string session_id;
    PipelineEvent event;
  };

  ServerOptions options;
  SessionStore store{""};
  zmq::context_t context{1};
  // ZAP handler (CURVE only), created before the ROUTER binds so no handshake goes unchecked.
  std::unique_ptr<zmq::socket_t> zap;
  std::set<std::string> allowed_clients;
  zmq::socket_t router{context, zmq::socket_type::router};
  std::string endpoint, metrics_endpoint;
  std::unique_ptr<HttpEndpoint> http;  // its own thread; reads what PublishSnapshot hands it
  Clock::time_point last_publish, last_trim;
  MemoryTrimmer trimmer;
  size_t published_sessions = 0;
  bool published_draining = false;
  // The ROUTER's connection events (zmq_socket_monitor), read on the transport thread.
  zmq::socket_t monitor{context, zmq::socket_type::pair};
  bool monitoring = false;
  struct ConnectionWindow {
    uint64_t accepted = 0, handshake_failures = 0;
    Clock::time_point start;
  } window;
  int wake_fd = -1;  // eventfd: pipeline events and stop requests
  std::atomic<bool> stop_requested{false};
  std::unique_ptr<ThreadPool> pool;
  std::unique_ptr<DenseWorkers> workers;
  std::unordered_map<std::string, std::unique_ptr<Session>> sessions;  // transport thread only
  std::mutex outbox_mutex;
  std::deque<Outgoing> outbox;  // Guarded by outbox_mutex.
  Metrics metrics;
  OncePerPeer once;  // abusive peers are logged once, counted always
  bool draining = false;
  Clock::time_point drain_deadline;
  uint64_t session_counter = 0;

  Impl() { DeclareServerMetrics(&metrics); }
  ~Impl() {
    http.reset();      // no handler runs past here
    sessions.clear();  // pipelines stop before the workers and pool go
    workers.reset();
    if (wake_fd >= 0) ::close(wake_fd);
  }

  void Wake() {
    const uint64_t one = 1;
    (void)!::write(wake_fd, &one, sizeof(one));
  }

  Status StartHttp() {
    if (options.metrics_bind == "off") return Status::Ok();
    HttpOptions ho;
    ho.bind = options.metrics_bind;
    ho.max_connections = options.http_max_connections;
    ho.idle_timeout_s = options.http_idle_timeout_s;
    ho.max_request_bytes = options.http_max_request_bytes;
    PRISM_ASSIGN_OR_RETURN(http, HttpEndpoint::Start(ho));
    metrics_endpoint = http->url();
    PublishSnapshot();
    return Status::Ok();
  }

  // Hands the HTTP thread what /metrics, /healthz, /readyz and /allocate read: at most every 100 ms,
  // and at once when the session count or draining changed.
  void PublishSnapshot(bool force = true) {
    if (!http) return;
    const auto now = Clock::now();
    const bool changed = sessions.size() != published_sessions || draining != published_draining;
    if (!force && !changed && now - last_publish < std::chrono::milliseconds(100)) return;
    last_publish = now;
    published_sessions = sessions.size();
    published_draining = draining;
    UpdateGauges();
    auto snap = std::make_shared<HttpSnapshot>();
    snap->metrics_text = metrics.Render();
    snap->endpoint = options.advertise.empty() ? endpoint : options.advertise;
    snap->sessions_active = static_cast<int>(sessions.size());
    snap->sessions_capacity = options.max_sessions;
    snap->draining = draining;
    http->Publish(std::move(snap));
  }

  // Starts reading the ROUTER's connection events (accepts, disconnects, failed handshakes).
  void StartMonitor() {
    const char* address = "inproc://prism-router-monitor";
    const int events = ZMQ_EVENT_ACCEPTED | ZMQ_EVENT_DISCONNECTED | ZMQ_EVENT_HANDSHAKE_FAILED_NO_DETAIL |
                       ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL | ZMQ_EVENT_HANDSHAKE_FAILED_AUTH;
    if (zmq_socket_monitor(router.handle(), address, events) != 0) {
      PRISM_LOG(WARNING) << "event=monitor_unavailable error=\"" << zmq_strerror(zmq_errno()) << "\"";
      return;
    }
    monitor.set(zmq::sockopt::linger, 0);
    monitor.connect(address);
    monitoring = true;
    window.start = Clock::now();
  }

  void ReadMonitor() {
    for (int n = 0; n < 4096; ++n) {
      zmq::message_t event, address;
      if (!monitor.recv(event, zmq::recv_flags::dontwait)) break;
      if (event.more()) (void)monitor.recv(address, zmq::recv_flags::none);
      if (event.size() < 6) continue;
      uint16_t id = 0;
      std::memcpy(&id, event.data(), sizeof(id));
      switch (id) {
        case ZMQ_EVENT_ACCEPTED:
          metrics.Add("prism_zmq_connections_accepted_total");
          metrics.Set("prism_zmq_connections_open", metrics.Value("prism_zmq_connections_open") + 1);
          ++window.accepted;
          break;
        case ZMQ_EVENT_DISCONNECTED:
          metrics.Add("prism_zmq_disconnects_total");
          metrics.Set("prism_zmq_connections_open", std::max(0.0, metrics.Value("prism_zmq_connections_open") - 1));
          break;
        case ZMQ_EVENT_HANDSHAKE_FAILED_PROTOCOL:
          metrics.Add("prism_zmq_handshake_failures_total{reason=\"protocol\"}");
          ++window.handshake_failures;
          break;
        case ZMQ_EVENT_HANDSHAKE_FAILED_AUTH:
          metrics.Add("prism_zmq_handshake_failures_total{reason=\"auth\"}");
          ++window.handshake_failures;
          break;
        default:
          metrics.Add("prism_zmq_handshake_failures_total{reason=\"no_detail\"}");
          ++window.handshake_failures;
          break;
      }
    }
    // Connection events carry no peer identity worth logging one by one: one line per 10 s window when
    // handshakes failed or connections churned (over 10 a second).
    const auto now = Clock::now();
    if (now - window.start < std::chrono::seconds(10)) return;
    if (window.handshake_failures > 0 || window.accepted > 100) {
      PRISM_LOG(WARNING) << "event=zmq_connection_churn accepted=" << window.accepted
                         << " handshake_failures=" << window.handshake_failures
                         << " window_s=" << std::chrono::duration<double>(now - window.start).count();
    }
    window = ConnectionWindow{0, 0, now};
  }

  void UpdateGauges() {
    metrics.Set("prism_sessions_active", static_cast<double>(sessions.size()));
    metrics.Set("prism_sessions_capacity", options.max_sessions);
    metrics.Set("prism_dense_jobs_pending", static_cast<double>(workers->pending_jobs()));
    size_t pending_chunks = 0, in_memory = 0;
    for (const auto& [id, s] : sessions) {
      pending_chunks += s->pending_chunks.size();
      in_memory += s->pending_bytes_in_memory;
      const std::string label = "{session=\"" + MetricLabel(id) + "\"}";
      metrics.Set("prism_session_chunks_waiting" + label, static_cast<double>(s->pending_chunks.size()));
      metrics.Set("prism_session_frames_dropped" + label, static_cast<double>(s->frames_dropped));
      if (s->pipeline) {
        metrics.Set("prism_session_frame_queue_depth" + label, static_cast<double>(s->pipeline->queued_frames()));
        metrics.Set("prism_session_keyframe_queue_depth" + label, static_cast<double>(s->pipeline->queued_keyframes()));
      }
    }
    metrics.Set("prism_chunks_waiting_for_credit", static_cast<double>(pending_chunks));
    metrics.Set("prism_chunk_bytes_waiting_in_memory", static_cast<double>(in_memory));
  }

  // Sends [peer][envelope][payload?] without blocking. false when the peer is gone (ROUTER_MANDATORY:
  // EHOSTUNREACH) or its queue is full (EAGAIN); counted either way.
  bool Send(const std::string& peer, const v1::Envelope& env, const std::vector<uint8_t>* payload = nullptr) {
    const std::string header = env.SerializeAsString();
    try {
      if (!router.send(zmq::buffer(peer), zmq::send_flags::dontwait | zmq::send_flags::sndmore)) {
        metrics.Add("prism_send_failures_total{reason=\"hwm\"}");
        return false;
      }
      if (payload) {
        router.send(zmq::buffer(header), zmq::send_flags::dontwait | zmq::send_flags::sndmore);
        router.send(zmq::buffer(*payload), zmq::send_flags::dontwait);
      } else {
        router.send(zmq::buffer(header), zmq::send_flags::dontwait);
      }
      return true;
    } catch (const zmq::error_t& e) {
      metrics.Add(std::string("prism_send_failures_total{reason=\"") +
                  (e.num() == EHOSTUNREACH ? "unreachable" : "other") + "\"}");
      return false;
    }
  }

  void SendError(const std::string& peer, const Status& status, const std::string& session_id, bool retryable,
                 bool session_closed, const uint64_t* frame = nullptr) {
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::Error* e = env.mutable_error();
    e->set_code(ToWireCode(status.code()));
    e->set_message(status.message());
    e->set_retryable(retryable);
    e->set_session_id(session_id);
    e->set_session_closed(session_closed);
    if (frame) {
      e->set_has_frame(true);
      e->set_frame_sequence_number(*frame);
    }
    metrics.Add(std::string("prism_errors_sent_total{code=\"") + v1::ErrorCode_Name(e->code()) + "\"}");
    // A flood of bad messages from one peer is one line; prism_errors_sent_total counts them all.
    if (once.First(peer, v1::ErrorCode_Name(e->code()))) {
      PRISM_LOG(INFO) << "event=error_sent peer=" << PeerName(peer)
                      << " session=" << (session_id.empty() ? "-" : session_id)
                      << " code=" << v1::ErrorCode_Name(e->code()) << " message=\"" << status.message()
                      << "\" (logged once per peer and code)";
    }
    Send(peer, env);
  }

  void SendVersionMismatch(const std::string& peer, int version) {
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::Error* e = env.mutable_error();
    e->set_code(v1::ERROR_CODE_VERSION_MISMATCH);
    e->set_message("protocol version " + std::to_string(version) + " is not supported; this server speaks version 1");
    metrics.Add("prism_errors_sent_total{code=\"ERROR_CODE_VERSION_MISMATCH\"}");
    if (once.First(peer, "version")) {
      PRISM_LOG(INFO) << "event=error_sent peer=" << PeerName(peer)
                      << " code=ERROR_CODE_VERSION_MISMATCH version=" << version << " (logged once per peer)";
    }
    Send(peer, env);
  }

  void HandleMessage(std::vector<zmq::message_t>& parts) {
    metrics.Add("prism_messages_received_total");
    const std::string peer = parts[0].to_string();
    if (parts.size() < 2 || parts.size() > 3) {
      metrics.Add("prism_malformed_messages_total");
      SendError(peer,
                InvalidArgumentError("malformed message: expected [Envelope] or [Envelope][payload], got " +
                                     std::to_string(parts.size() - 1) + " parts"),
                "", false, false);
      return;
    }
    v1::Envelope env;
    if (!env.ParseFromArray(parts[1].data(), static_cast<int>(parts[1].size()))) {
      metrics.Add("prism_malformed_messages_total");
      SendError(peer,
                InvalidArgumentError("malformed envelope: " + std::to_string(parts[1].size()) +
                                     " bytes that do not parse as a prism.v1.Envelope"),
                "", false, false);
      return;
    }
    if (env.protocol_version() != v1::PROTOCOL_VERSION_1) {
      metrics.Add("prism_malformed_messages_total");
      SendVersionMismatch(peer, env.protocol_version());
      return;
    }
    const zmq::message_t* payload = parts.size() == 3 ? &parts[2] : nullptr;
    const bool wants_payload = env.body_case() == v1::Envelope::kFrame;
    if (payload && !wants_payload) {
      metrics.Add("prism_malformed_messages_total");
      SendError(peer, InvalidArgumentError("this message type carries no payload part"), "", false, false);
      return;
    }
    switch (env.body_case()) {
      case v1::Envelope::kOpenSession:
        return OpenSession(peer, env.open_session());
      case v1::Envelope::kFrame:
        return HandleFrame(peer, env.frame(), payload);
      case v1::Envelope::kChunkCredits: {
        // NOT_FOUND like Frame and Close; credits for a session that has just ended (granted for its
        // last chunks) are common, and clients that have its summary ignore the error.
        auto it = sessions.find(env.chunk_credits().session_id());
        if (it == sessions.end() || it->second->peer != peer) metrics.Add("prism_stale_credits_total");
        Session* s = FindSession(peer, env.chunk_credits().session_id());
        if (!s) return;
        s->last_activity = Clock::now();
        s->chunk_credits = std::min<int64_t>(s->chunk_credits + env.chunk_credits().chunks(), 1 << 20);
        FlushChunks(s);
        return;
      }
      case v1::Envelope::kClose: {
        Session* s = FindSession(peer, env.close().session_id());
        if (!s) return;
        s->last_activity = Clock::now();
        if (!s->closing) {
          s->closing = true;
          s->reason = env.close().abort() ? "aborted by client" : "closed by client";
          if (env.close().abort()) s->pipeline->Abort();
          else s->pipeline->Finish();
          PRISM_LOG(INFO) << "event=session_closing session=" << s->id << " reason=\"" << s->reason << "\"";
        }
        return;
      }
      case v1::Envelope::BODY_NOT_SET:
        metrics.Add("prism_malformed_messages_total");
        SendError(peer, InvalidArgumentError("envelope has no body"), "", false, false);
        return;
      default:
        metrics.Add("prism_malformed_messages_total");
        SendError(peer,
                  InvalidArgumentError("a client may not send this message type (body " +
                                       std::to_string(static_cast<int>(env.body_case())) + ")"),
                  "", false, false);
        return;
    }
  }

  Session* FindSession(const std::string& peer, const std::string& id) {
    auto it = sessions.find(id);
    if (it == sessions.end() || it->second->peer != peer) {
      metrics.Add("prism_unknown_session_total");
      SendError(peer, NotFoundError("unknown session '" + id + "'"), id, false, true);
      return nullptr;
    }
    return it->second.get();
  }

  // Re-attaches a client to a running session, or replays an ended one from the data dir.
  void ResumeSession(const std::string& peer, const v1::OpenSession& open) {
    const std::string& id = open.resume_session_id();
    if (!IsValidSessionId(id)) {
      metrics.Add("prism_resumes_rejected_total{reason=\"invalid\"}");
      return SendError(peer, InvalidArgumentError("malformed resume_session_id '" + id.substr(0, 64) + "'"), "", false,
                       false);
    }
    auto token_ok = [&](const std::string& token) {
      // Constant time in the token length: no early exit on the first differing byte.
      if (token.size() != open.resume_token().size() || token.empty()) return false;
      unsigned diff = 0;
      for (size_t i = 0; i < token.size(); ++i) diff |= static_cast<unsigned>(token[i] ^ open.resume_token()[i]);
      return diff == 0;
    };
    Session* s = nullptr;
    auto it = sessions.find(id);
    if (it != sessions.end()) {
      s = it->second.get();
      if (!token_ok(s->resume_token)) {
        metrics.Add("prism_resumes_rejected_total{reason=\"token\"}");
        return SendError(peer, Status(StatusCode::kUnauthenticated, "resume token does not match session '" + id + "'"),
                         id, false, false);
      }
    } else {
      StatusOr<StoredSession> stored = store.Load(id);
      if (!stored.ok()) {
        metrics.Add("prism_resumes_rejected_total{reason=\"unknown\"}");
        return SendError(peer, stored.status(), id, false, true);
      }
      if (!token_ok(stored->resume_token)) {
        metrics.Add("prism_resumes_rejected_total{reason=\"token\"}");
        return SendError(peer, Status(StatusCode::kUnauthenticated, "resume token does not match session '" + id + "'"),
                         id, false, false);
      }
      if (static_cast<int>(sessions.size()) >= options.max_sessions)
        return SendError(peer,
                         ResourceExhaustedError("server at capacity: " + std::to_string(sessions.size()) +
                                                " sessions; retry the resume later"),
                         id, true, false);
      if (!stored->has_summary) {
        // Interrupted by a server stop: finish it from what was persisted.
        StatusOr<size_t> points = store.RebuildMap(id, stored->voxel_m);
        v1::SessionSummary& sum = stored->summary;
        sum.set_session_id(id);
        sum.set_chunks_sent(stored->chunk_sequences.size());
        sum.set_map_points(points.ok() ? *points : 0);
        sum.set_reason("interrupted: the server stopped before the session finished; " +
                       std::to_string(stored->chunk_sequences.size()) + " persisted chunks");
        if (Status w = store.WriteSummary(id, sum); !w.ok()) {
          PRISM_LOG(WARNING) << "event=persist_failed session=" << id << " error=\"" << w << "\"";
        }
        PRISM_LOG(INFO) << "event=session_recovered session=" << id << " chunks=" << stored->chunk_sequences.size()
                        << " map_points=" << sum.map_points();
      }
      auto session = std::make_unique<Session>();
      session->id = id;
      session->resume_token = stored->resume_token;
      session->client_name = stored->client_name;
      session->replay = true;
      session->closing = true;
      session->finished = true;
      session->replay_summary = stored->summary;
      session->reason = stored->summary.reason();
      session->chunk_sequences = stored->chunk_sequences;
      s = session.get();
      sessions[id] = std::move(session);
    }
    s->peer = peer;
    s->last_activity = Clock::now();
    s->chunk_credits = open.initial_chunk_credits() > 0 ? open.initial_chunk_credits() : options.default_chunk_credits;
    s->frame_credits_to_grant = 0;
    // Every persisted chunk from resume_next_chunk on goes out again, in order (the pending ones are
    // among them: chunks are persisted before they are queued).
    // Chunks that failed to persist stay as they are (in memory); the rest are re-read from disk.
    std::deque<Session::PendingChunk> unpersisted;
    for (Session::PendingChunk& c : s->pending_chunks)
      if (!c.on_disk && !std::binary_search(s->chunk_sequences.begin(), s->chunk_sequences.end(), c.sequence))
        unpersisted.push_back(std::move(c));
    s->pending_chunks.clear();
    s->pending_in_memory = s->pending_bytes_in_memory = 0;
    for (uint64_t seq : s->chunk_sequences) {
      if (seq < open.resume_next_chunk()) continue;
      Session::PendingChunk c;
      c.sequence = seq;
      c.on_disk = true;
      s->pending_chunks.push_back(std::move(c));
    }
    for (Session::PendingChunk& c : unpersisted) QueueChunk(s, std::move(c));
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::SessionOpened* o = env.mutable_session_opened();
    FillSessionOpened(s, o);
    o->set_resumed(true);
    o->set_read_only(s->replay);
    if (!s->replay) {
      o->set_input_policy(s->input_policy);
      o->set_max_frame_rate_hz(options.max_frame_rate_hz);
    }
    o->set_next_frame_sequence(s->next_frame_sequence);
    o->set_initial_frame_credits(
        s->replay || s->closing
            ? 0u
            : static_cast<uint32_t>(std::max<int64_t>(0, static_cast<int64_t>(options.pipeline.frame_queue_capacity) -
                                                             static_cast<int64_t>(s->pipeline->queued_frames()))));
    metrics.Add("prism_sessions_resumed_total");
    PRISM_LOG(INFO) << "event=session_resumed session=" << id << " read_only=" << s->replay
                    << " chunks_to_resend=" << s->pending_chunks.size() << " next_pose=" << open.resume_next_pose();
    Send(peer, env);
    for (v1::PoseUpdate& p : store.ReadPoses(id, open.resume_next_pose())) {
      v1::Envelope pe;
      pe.set_protocol_version(v1::PROTOCOL_VERSION_1);
      *pe.mutable_pose_update() = std::move(p);
      Send(peer, pe);
    }
    FlushChunks(s);
  }

  void FillSessionOpened(const Session* s, v1::SessionOpened* o) const {
    const SessionPipelineOptions& po = options.pipeline;
    o->set_session_id(s->id);
    o->set_resume_token(s->resume_token);
    o->set_initial_frame_credits(static_cast<uint32_t>(po.frame_queue_capacity));
    o->set_max_frame_bytes(options.max_frame_bytes);
    o->set_map_voxel_m(po.dense.map.voxel_m);
    o->set_map_grid_subdivisions(static_cast<uint32_t>(po.chunk.subdivisions));
    o->set_map_quantisation_m(po.dense.map.voxel_m / po.chunk.subdivisions);
    o->set_idle_timeout_ms(static_cast<uint32_t>(options.idle_timeout_ms));
    o->set_max_message_bytes(static_cast<uint64_t>(options.MessageLimit()));
  }

  void OpenSession(const std::string& peer, const v1::OpenSession& open) {
    if (open.protocol_version() != v1::PROTOCOL_VERSION_1) return SendVersionMismatch(peer, open.protocol_version());
    if (draining) {
      return SendError(peer, UnavailableError("server is shutting down"), "", true, false);
    }
    if (!open.resume_session_id().empty()) return ResumeSession(peer, open);
    if (static_cast<int>(sessions.size()) >= options.max_sessions) {
      metrics.Add("prism_sessions_rejected_total{reason=\"capacity\"}");
      return SendError(peer,
                       ResourceExhaustedError("server at capacity: " + std::to_string(sessions.size()) + " of " +
                                              std::to_string(options.max_sessions) +
                                              " sessions open; retry later or raise --max-sessions"),
                       "", true, false);
    }
    StatusOr<RigCalibration> rig = RigFromWire(open.calibration());
    if (!rig.ok()) {
      metrics.Add("prism_sessions_rejected_total{reason=\"invalid\"}");
      return SendError(peer, rig.status(), "", false, false);
    }
    SessionPipelineOptions po = options.pipeline;
    if (open.input_policy() == v1::INPUT_POLICY_LIVE) po.input_policy = OverflowPolicy::kDropOldest;
    if (open.input_policy() == v1::INPUT_POLICY_UPLOAD) po.input_policy = OverflowPolicy::kReject;
    // A live camera's SLAM behind its input skips depth updates (ServerOptions::skip_depth_update_backlog_live).
    // Nor does its new keyframe wait for the SLAM's window adjustment
    // (ServerOptions::slam_adjustment_max_wait_ms_live).
    if (po.input_policy == OverflowPolicy::kDropOldest) {
      po.skip_depth_update_backlog = options.skip_depth_update_backlog_live;
      if (options.slam_adjustment_max_wait_ms_live >= 0)
        po.slam.keyframe_adjustment_max_wait_ms = options.slam_adjustment_max_wait_ms_live;
    }
    // The keyframe clouds kept for the map's rebuild at the end take at most a quarter of the session's
    // memory limit (kKeptBytesPerPoint each); none without remap-at-end.
    po.dense.remap_max_points = po.remap_at_end
                                    ? static_cast<int64_t>(static_cast<double>(options.max_session_memory_mb) *
                                                           (1 << 20) / 4 / kKeptBytesPerPoint)
                                    : 0;
    auto session = std::make_unique<Session>();
    session->id = "s" + std::to_string(++session_counter) + "-" + RandomHex(6);
    session->peer = peer;
    session->client_name = open.client_name();
    session->camera_width = rig->camera.width;
    session->camera_height = rig->camera.height;
    session->input_policy =
        po.input_policy == OverflowPolicy::kReject ? v1::INPUT_POLICY_UPLOAD : v1::INPUT_POLICY_LIVE;
    session->chunk_credits =
        open.initial_chunk_credits() > 0 ? open.initial_chunk_credits() : options.default_chunk_credits;
    session->last_activity = Clock::now();
    session->rate_refilled = session->last_activity;
    session->rate_tokens = 2.0 * po.frame_queue_capacity;
    session->resume_token = RandomHex(16);
    const std::string id = session->id;
    StoredSession stored;
    stored.id = id;
    stored.resume_token = session->resume_token;
    stored.client_name = open.client_name();
    stored.voxel_m = po.dense.map.voxel_m;
    if (Status c = store.Create(stored); !c.ok()) {
      metrics.Add("prism_sessions_rejected_total{reason=\"storage\"}");
      return SendError(peer, c, "", true, false);
    }
    if (Status c = session->pose_log.Open(store.Dir(id)); !c.ok()) return SendError(peer, c, "", true, false);
    StatusOr<std::unique_ptr<SessionPipeline>> pipeline =
        SessionPipeline::Create(*rig, po, workers.get(), [this, id](PipelineEvent&& e) {
          {
            std::lock_guard<std::mutex> lock(outbox_mutex);
            outbox.push_back({id, std::move(e)});
          }
          Wake();
        });
    if (!pipeline.ok()) {
      metrics.Add("prism_sessions_rejected_total{reason=\"invalid\"}");
      return SendError(peer, pipeline.status(), "", false, false);
    }
    session->pipeline = std::move(*pipeline);
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    v1::SessionOpened* o = env.mutable_session_opened();
    FillSessionOpened(session.get(), o);
    o->set_input_policy(session->input_policy);
    o->set_max_frame_rate_hz(options.max_frame_rate_hz);
    sessions[id] = std::move(session);
    metrics.Add("prism_sessions_opened_total");
    PRISM_LOG(INFO) << "event=session_opened session=" << id << " client=\"" << open.client_name()
                    << "\" size=" << rig->camera.width << "x" << rig->camera.height << " sessions=" << sessions.size();
    Send(peer, env);
  }

  void HandleFrame(const std::string& peer, const v1::Frame& frame, const zmq::message_t* payload) {
    Session* s = FindSession(peer, frame.session_id());
    if (!s) return;
    s->last_activity = Clock::now();
    const uint64_t seq = frame.sequence_number();
    auto refuse = [&](const Status& st, bool retryable) {
      ++s->frames_refused;
      ++s->frames_dropped;
      ++s->frame_credits_to_grant;  // the frame never entered the queue: its credit comes back
      metrics.Add("prism_frames_refused_total");
      SendError(peer, Status(st.code(), "frame " + std::to_string(seq) + ": " + st.message()), s->id, retryable, false,
                &seq);
    };
    if (s->replay)
      return refuse(FailedPreconditionError("the session has ended (" + s->reason + "); it takes no frames"), false);
    if (s->closing) return refuse(FailedPreconditionError("the session is closing; no frames after Close"), false);
    s->next_frame_sequence = std::max(s->next_frame_sequence, seq + 1);
    if (options.max_frame_rate_hz > 0) {
      const auto now = Clock::now();
      // Twice the burst a client pacing itself uses (the frame queue), so network jitter never trips it.
      const double burst = 2.0 * options.pipeline.frame_queue_capacity;
      s->rate_tokens = std::min(burst, s->rate_tokens + std::chrono::duration<double>(now - s->rate_refilled).count() *
                                                            options.max_frame_rate_hz);
      s->rate_refilled = now;
      if (s->rate_tokens < 1.0) {
        metrics.Add("prism_frames_dropped_total{reason=\"rate\"}");
        return refuse(ResourceExhaustedError("over the session frame-rate limit of " +
                                             std::to_string(options.max_frame_rate_hz) + " Hz (max-frame-rate-hz)"),
                      true);
      }
      s->rate_tokens -= 1.0;
    }
    if (Status fields = CheckFrameFields(frame, s->camera_width, s->camera_height, s->last_accepted); !fields.ok())
      return refuse(fields, false);
    if (!payload || payload->size() == 0)
      return refuse(InvalidArgumentError("frame without image payload part"), false);
    if (payload->size() > options.max_frame_bytes)
      return refuse(InvalidArgumentError("frame payload of " + std::to_string(payload->size()) + " bytes exceeds " +
                                         std::to_string(options.max_frame_bytes)),
                    false);
    StatusOr<FrameCodec> codec = FromWireCodec(frame.codec());
    if (!codec.ok()) return refuse(codec.status(), false);
    EncodedFrame ef;
    ef.sequence_number = seq;
    ef.timestamp_ns = frame.timestamp_ns();
    ef.codec = *codec;
    const auto* bytes = static_cast<const uint8_t*>(payload->data());
    ef.bytes.assign(bytes, bytes + payload->size());
    bool dropped = false;
    const Status pushed = s->pipeline->Push(std::move(ef), &dropped);
    if (!pushed.ok()) return refuse(pushed, pushed.code() == StatusCode::kResourceExhausted);
    s->last_accepted = AcceptedFrame{seq, frame.timestamp_ns()};
    metrics.Add("prism_frames_received_total");
    metrics.Add("prism_frame_bytes_total", static_cast<double>(payload->size()));
    s->frame_arrivals.emplace_back(seq, Clock::now());
    if (s->frame_arrivals.size() > 4096) s->frame_arrivals.pop_front();
    if (dropped) {
      ++s->frames_dropped;
      ++s->frame_credits_to_grant;
      metrics.Add("prism_frames_dropped_total{reason=\"queue_full\"}");
    }
  }

  void QueueChunk(Session* s, Session::PendingChunk&& c) {
    const bool persisted = std::binary_search(s->chunk_sequences.begin(), s->chunk_sequences.end(), c.sequence);
    if (persisted && s->pending_in_memory >= static_cast<size_t>(options.max_pending_chunks_in_memory)) {
      c.on_disk = true;
      c.envelope.Clear();
      std::vector<uint8_t>().swap(c.bytes);
    } else {
      ++s->pending_in_memory;
      s->pending_bytes_in_memory += c.bytes.size();
    }
    s->pending_chunks.push_back(std::move(c));
  }

  void FlushChunks(Session* s) {
    if (s->chunk_credits <= 0 && s->pending_chunks.size() > static_cast<size_t>(options.default_chunk_credits) &&
        !s->credits_exhausted_logged) {
      s->credits_exhausted_logged = true;
      PRISM_LOG(WARNING) << "event=chunk_credits_exhausted session=" << s->id << " waiting=" << s->pending_chunks.size()
                         << " message=\"the client grants no chunk credits; chunks wait on disk (logged once per "
                            "session, prism_session_chunks_waiting counts them)\"";
    }
    while (s->chunk_credits > 0 && !s->pending_chunks.empty()) {
      Session::PendingChunk& c = s->pending_chunks.front();
      if (c.on_disk) {
        c.envelope.set_protocol_version(v1::PROTOCOL_VERSION_1);
        if (Status r = store.ReadChunk(s->id, c.sequence, c.envelope.mutable_map_chunk(), &c.bytes); !r.ok()) {
          PRISM_LOG(WARNING) << "event=chunk_unreadable session=" << s->id << " error=\"" << r << "\"";
          metrics.Add("prism_persist_failures_total");
          s->pending_chunks.pop_front();
          continue;
        }
        c.envelope.mutable_map_chunk()->set_session_id(s->id);
        c.on_disk = false;
        ++s->pending_in_memory;
        s->pending_bytes_in_memory += c.bytes.size();
      }
      if (!Send(s->peer, c.envelope, &c.bytes)) break;  // retried on the next loop
      --s->chunk_credits;
      ++s->chunks_sent;
      metrics.Add("prism_chunks_sent_total");
      metrics.Add("prism_chunk_bytes_total", static_cast<double>(c.bytes.size()));
      --s->pending_in_memory;
      s->pending_bytes_in_memory -= c.bytes.size();
      s->pending_chunks.pop_front();
    }
  }

  void HandleEvent(Outgoing& out) {
    auto it = sessions.find(out.session_id);
    if (it == sessions.end()) return;
    Session* s = it->second.get();
    PipelineEvent& e = out.event;
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    switch (e.kind) {
      case PipelineEvent::Kind::kPose: {
        if (!e.refined) ++s->frame_credits_to_grant;
        v1::PoseUpdate* p = env.mutable_pose_update();
        p->set_session_id(s->id);
        p->set_frame_sequence_number(e.frame_sequence_number);
        p->set_timestamp_ns(e.timestamp_ns);
        ToWire(e.slam.world_from_camera, p->mutable_world_from_camera());
        p->set_state(e.slam.state == SlamState::kTracking       ? v1::PoseUpdate::TRACKING_STATE_TRACKING
                     : e.slam.state == SlamState::kInitializing ? v1::PoseUpdate::TRACKING_STATE_INITIALISING
                                                                : v1::PoseUpdate::TRACKING_STATE_LOST);
        p->set_is_keyframe(e.slam.new_keyframe);
        p->set_keyframe_id(e.slam.keyframe_id);
        p->set_metres_per_unit(e.metres_per_unit);
        p->set_refined(e.refined);
        if (const SlamTrackingQuality& q = e.slam.tracking; q.tracked) {
          v1::TrackingQuality* t = p->mutable_tracking();
          t->set_residual_rms(q.residual_rms);
          t->set_visible_fraction(q.visible_fraction);
          t->set_inlier_fraction(q.inlier_fraction);
          t->set_iterations(static_cast<uint32_t>(std::max(0, q.iterations)));
          t->set_retried(q.retried);
          t->set_step(q.step);
          t->set_rotation_deg(q.rotation_deg);
          t->set_guess_correction(q.guess_correction);
        }
        s->pose_log.Append(*p);
        if (!e.refined) {
          // Frames before this one that got no pose were dropped or failed.
          while (!s->frame_arrivals.empty() && s->frame_arrivals.front().first < e.frame_sequence_number)
            s->frame_arrivals.pop_front();
          if (!s->frame_arrivals.empty() && s->frame_arrivals.front().first == e.frame_sequence_number) {
            metrics.Observe("prism_frame_to_pose_seconds",
                            std::chrono::duration<double>(Clock::now() - s->frame_arrivals.front().second).count());
            s->frame_arrivals.pop_front();
          }
          metrics.Set("prism_session_tracking_state{session=\"" + MetricLabel(s->id) + "\"}",
                      e.slam.state == SlamState::kInitializing ? 0
                      : e.slam.state == SlamState::kTracking   ? 1
                                                               : 2);
        }
        if (Send(s->peer, env)) {
          ++s->poses_sent;
          metrics.Add(e.refined ? "prism_poses_refined_total" : "prism_poses_sent_total");
        }
        return;
      }
      case PipelineEvent::Kind::kChunk: {
        v1::MapChunk* c = env.mutable_map_chunk();
        c->set_session_id(s->id);
        c->set_keyframe_id(e.keyframe_id);
        c->set_chunk_sequence_number(e.chunk_sequence);
        c->set_num_points(static_cast<uint32_t>(e.num_points));
        ToWire(e.world_from_keyframe, c->mutable_world_from_keyframe());
        c->set_payload_bytes(e.draco.size());
        c->set_map_points(e.map_points);
        c->set_replaces_map(e.replaces_map);
        metrics.Add("prism_keyframes_merged_total");
        if (e.keyframe_queued_at != Clock::time_point()) {
          metrics.Observe("prism_keyframe_to_chunk_seconds",
                          std::chrono::duration<double>(Clock::now() - e.keyframe_queued_at).count());
          metrics.Observe("prism_dense_keyframe_seconds", e.dense_ms / 1000.0);
        }
        // Persisted before it is queued: a chunk the client may have seen is always on disk.
        if (Status w = store.WriteChunk(s->id, *c, e.draco); !w.ok()) {
          metrics.Add("prism_persist_failures_total");
          PRISM_LOG(WARNING) << "event=persist_failed session=" << s->id << " error=\"" << w << "\"";
        } else {
          s->chunk_sequences.push_back(e.chunk_sequence);
        }
        Session::PendingChunk pc;
        pc.sequence = e.chunk_sequence;
        pc.envelope = std::move(env);
        pc.bytes = std::move(e.draco);
        QueueChunk(s, std::move(pc));
        FlushChunks(s);
        if (!s->pending_chunks.empty() && s->chunk_credits <= 0) metrics.Add("prism_chunk_credit_stalls_total");
        // Memory per session: the map (voxels) and the chunks held for the client.
        const double session_mb = (static_cast<double>(e.map_voxels) * kMapBytesPerPoint +
                                   static_cast<double>(e.kept_points) * kKeptBytesPerPoint +
                                   static_cast<double>(s->pending_bytes_in_memory)) /
                                  (1 << 20);
        if (!s->memory_limit_hit && !s->closing && session_mb > options.max_session_memory_mb) {
          s->memory_limit_hit = true;
          s->closing = true;
          s->reason = "memory limit";
          s->pipeline->Finish();
          metrics.Add("prism_sessions_limited_total{limit=\"memory\"}");
          SendError(s->peer,
                    ResourceExhaustedError(
                        "session memory ~" + std::to_string(static_cast<int>(session_mb)) +
                        " MiB exceeds max-session-memory-mb = " + std::to_string(options.max_session_memory_mb) +
                        "; the session is finished with the map so far (raise the limit or use a "
                        "coarser voxel-m)"),
                    s->id, false, false);
        }
        return;
      }
      case PipelineEvent::Kind::kError: {
        if (e.has_frame) ++s->frame_credits_to_grant;
        if (e.has_frame) metrics.Add("prism_frames_bad_total");
        SendError(s->peer, e.status, s->id, false, e.fatal, e.has_frame ? &e.frame_sequence_number : nullptr);
        if (e.fatal) {
          s->closing = true;
          s->reason = "failed: " + e.status.message();
          metrics.Add("prism_sessions_failed_total");
        }
        return;
      }
      case PipelineEvent::Kind::kFinished:
        if (Status w = s->pose_log.WriteFinalTrajectory(); !w.ok()) {
          PRISM_LOG(WARNING) << "session " << s->id << ": " << w;
        }
        s->finished = true;
        s->stats = e.stats;
        if (s->reason.empty()) s->reason = "finished";
        return;
    }
  }

  void PersistAndSummarise(Session* s) {
    v1::Envelope env;
    env.set_protocol_version(v1::PROTOCOL_VERSION_1);
    if (s->replay) {
      *env.mutable_session_summary() = s->replay_summary;
      Send(s->peer, env);
      PRISM_LOG(INFO) << "event=session_replayed session=" << s->id << " chunks=" << s->chunks_sent;
      return;
    }
    const PipelineStats& st = s->stats;
    v1::SessionSummary* sum = env.mutable_session_summary();
    sum->set_session_id(s->id);
    sum->set_frames_received(st.frames_received);
    sum->set_frames_dropped(st.frames_dropped);
    sum->set_frames_rejected(st.frames_rejected + st.frames_bad + s->frames_refused);
    sum->set_keyframes(st.keyframes);
    sum->set_keyframes_dropped(st.keyframes_dropped);
    sum->set_keyframes_failed(st.keyframes_failed);
    sum->set_chunks_sent(s->chunks_sent);
    sum->set_map_points(st.map_points);
    sum->set_metres_per_unit(st.metres_per_unit);
    sum->set_shading_check(static_cast<v1::ShadingCheck>(st.shading_check));
    sum->set_shading_pair_spread(st.shading_pair_spread);
    sum->set_start_check(static_cast<v1::StartCheck>(st.start_check));
    sum->set_start_pair_spread(st.start_pair_spread);
    sum->set_frames_depth_update_skipped(st.frames_depth_update_skipped);
    sum->set_reason(s->reason);
    // Persist: the merged map and the summary.
    const std::string dir = store.Dir(s->id);
    std::error_code ec;
    std::filesystem::create_directories(dir, ec);
    if (st.map_points > 0) {
      const Status w = WritePointCloudPly(dir + "/map.ply", s->pipeline->MapSnapshot());
      if (!w.ok()) {
        PRISM_LOG(WARNING) << "event=persist_failed session=" << s->id << " error=\"" << w << "\"";
      }
    }
    if (Status w = store.WriteSummary(s->id, *sum); !w.ok()) {
      PRISM_LOG(WARNING) << "event=persist_failed session=" << s->id << " error=\"" << w << "\"";
    }
    Send(s->peer, env);
    metrics.Add("prism_sessions_closed_total");
    metrics.Add("prism_keyframes_dropped_total", static_cast<double>(st.keyframes_dropped));
    PRISM_LOG(INFO) << "event=session_closed session=" << s->id << " reason=\"" << s->reason
                    << "\" frames=" << st.frames_processed << " keyframes=" << st.keyframes
                    << " chunks=" << s->chunks_sent << " map_points=" << st.map_points;
  }

  // Credits, idle timeouts, finished sessions. Transport thread.
  void Housekeeping() {
    const auto now = Clock::now();
    for (auto it = sessions.begin(); it != sessions.end();) {
      Session* s = it->second.get();
      if (s->frame_credits_to_grant > 0 && !s->closing) {
        v1::Envelope env;
        env.set_protocol_version(v1::PROTOCOL_VERSION_1);
        env.mutable_frame_credits()->set_session_id(s->id);
        env.mutable_frame_credits()->set_frames(s->frame_credits_to_grant);
        if (Send(s->peer, env)) s->frame_credits_to_grant = 0;
      }
      FlushChunks(s);
      if (!s->closing && now - s->last_activity > std::chrono::milliseconds(options.idle_timeout_ms)) {
        s->closing = true;
        s->reason = "idle timeout";
        s->pipeline->Abort();
        metrics.Add("prism_sessions_reaped_total");
        SendError(s->peer,
                  UnavailableError("session closed after " + std::to_string(options.idle_timeout_ms) +
                                   " ms without a message"),
                  s->id, false, true);
      }
      if (draining && now > drain_deadline && !s->finished) s->pipeline->Abort();
      // Done: the pipeline finished and every chunk went out (or the client is not reading: give up at
      // the drain deadline or after the idle timeout).
      const bool stalled = now - s->last_activity > std::chrono::milliseconds(options.idle_timeout_ms) ||
                           (draining && now > drain_deadline);
      if (s->finished && (s->pending_chunks.empty() || stalled)) {
        PersistAndSummarise(s);
        for (const char* family :
             {"prism_session_tracking_state", "prism_session_frames_dropped", "prism_session_frame_queue_depth",
              "prism_session_keyframe_queue_depth", "prism_session_chunks_waiting"})
          metrics.Remove(family, "session=\"" + MetricLabel(s->id) + "\"");
        it = sessions.erase(it);
        TrimMemory();
      } else {
        ++it;
      }
    }
    if (now - last_trim > std::chrono::seconds(10)) TrimMemory();
  }

  // After a session ends, and every 10 s (the freed memory of peers that came and went).
  void TrimMemory() {
    last_trim = Clock::now();
    trimmer.Request();
  }

  Status Run() {
    PRISM_LOG(INFO) << "event=server_started endpoint=" << endpoint << " metrics=" << metrics_endpoint
                    << " max_sessions=" << options.max_sessions << " dense_workers=" << options.dense_workers
                    << " pool_threads=" << pool->num_threads();
    std::vector<zmq::pollitem_t> items;
    for (;;) {
      if (stop_requested && !draining) {
        draining = true;
        drain_deadline = Clock::now() + std::chrono::milliseconds(options.shutdown_deadline_ms);
        PRISM_LOG(INFO) << "event=draining sessions=" << sessions.size();
        for (auto& [id, s] : sessions)
          if (!s->closing) {
            s->closing = true;
            s->reason = "server shutdown";
            s->pipeline->Finish();
          }
      }
      if (draining && sessions.empty()) break;
      items.clear();
      items.push_back({router.handle(), 0, ZMQ_POLLIN, 0});
      items.push_back({nullptr, wake_fd, ZMQ_POLLIN, 0});
      const size_t monitor_item = items.size();
      if (monitoring) items.push_back({monitor.handle(), 0, ZMQ_POLLIN, 0});
      const size_t zap_item = items.size();
      if (zap) items.push_back({zap->handle(), 0, ZMQ_POLLIN, 0});
      try {
        zmq::poll(items.data(), items.size(), std::chrono::milliseconds(50));
      } catch (const zmq::error_t& e) {
        if (e.num() != EINTR) return InternalError(std::string("zmq::poll failed: ") + e.what());
        continue;  // a signal (SIGTERM sets stop_requested)
      }
      if (items[1].revents & ZMQ_POLLIN) {
        uint64_t v;
        (void)!::read(wake_fd, &v, sizeof(v));
      }
      // Incoming: at most a batch per loop so events and housekeeping keep flowing.
      for (int n = 0; n < 256; ++n) {
        std::vector<zmq::message_t> parts;
        zmq::message_t part;
        try {
          if (!router.recv(part, zmq::recv_flags::dontwait)) break;
          parts.push_back(std::move(part));
          while (parts.back().more() && parts.size() < 8) {
            zmq::message_t next;
            (void)router.recv(next, zmq::recv_flags::none);
            parts.push_back(std::move(next));
          }
          while (parts.back().more()) {  // more than 8 parts: drain the rest
            zmq::message_t rest;
            (void)router.recv(rest, zmq::recv_flags::none);
            parts.push_back(zmq::message_t());
            parts.back().swap(rest);
            if (parts.size() > 64) parts.erase(parts.begin() + 8, parts.end() - 1);
          }
        } catch (const zmq::error_t& e) {
          PRISM_LOG(WARNING) << "event=recv_failed error=\"" << e.what() << "\"";
          break;
        }
        try {
          HandleMessage(parts);
        } catch (const std::exception& e) {  // a bug in handling one message never takes the server down
          PRISM_LOG(ERROR) << "event=handler_failed error=\"" << e.what() << "\"";
          metrics.Add("prism_handler_failures_total");
        }
      }
      std::deque<Outgoing> events;
      {
        std::lock_guard<std::mutex> lock(outbox_mutex);
        events.swap(outbox);
      }
      metrics.Set("prism_transport_events_pending", static_cast<double>(events.size()));
      for (Outgoing& o : events) HandleEvent(o);
      if (monitoring && (items[monitor_item].revents & ZMQ_POLLIN)) ReadMonitor();
      if (zap && (items[zap_item].revents & ZMQ_POLLIN)) {
        std::string key;
        for (int n = 0; n < 64; ++n) {
          try {
            const bool admitted = HandleZapRequest(*zap, allowed_clients, &key);
            if (key.empty() && !admitted) break;  // nothing pending (or a non-CURVE request, refused)
            metrics.Add(admitted ? "prism_auth_accepted_total" : "prism_auth_refused_total");
            if (!admitted && once.First(key, "auth")) {
              PRISM_LOG(WARNING) << "event=auth_refused client_key=" << key << " (logged once per key)";
            }
          } catch (const zmq::error_t& e) {
            PRISM_LOG(WARNING) << "event=zap_failed error=\"" << e.what() << "\"";
            break;
          }
        }
      }
      Housekeeping();
      PublishSnapshot(/*force=*/false);
    }
    PublishSnapshot();
    PRISM_LOG(INFO) << "event=server_stopped";
    return Status::Ok();
  }
};

Server::Server(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Server::~Server() = default;

StatusOr<std::unique_ptr<Server>> Server::Create(const ServerOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  impl->store = SessionStore(options.data_dir);
  std::error_code ec;
  std::filesystem::create_directories(options.data_dir + "/sessions", ec);
  if (ec) return UnavailableError("cannot create data dir '" + options.data_dir + "': " + ec.message());
  impl->wake_fd = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (impl->wake_fd < 0) return InternalError("eventfd failed");
  try {
    zmq::socket_t& r = impl->router;
    if (!options.curve_keys.empty()) {
      if (!zmq_has("curve")) return UnavailableError("curve_keys is set but this libzmq was built without CURVE");
      PRISM_ASSIGN_OR_RETURN(CurveKeyPair keys, ReadCurveKeyFile(options.curve_keys));
      PRISM_ASSIGN_OR_RETURN(impl->allowed_clients, ReadAllowList(options.allowed_clients));
      impl->zap = std::make_unique<zmq::socket_t>(impl->context, zmq::socket_type::rep);
      impl->zap->set(zmq::sockopt::linger, 0);
      impl->zap->bind("inproc://zeromq.zap.01");
      r.set(zmq::sockopt::curve_server, 1);
      r.set(zmq::sockopt::curve_secretkey, keys.secret_key);
      r.set(zmq::sockopt::zap_domain, std::string("prism"));
      PRISM_LOG(INFO) << "event=curve_enabled server_key=" << keys.public_key
                      << " allowed_clients=" << impl->allowed_clients.size();
    }
    r.set(zmq::sockopt::router_mandatory, 1);
    r.set(zmq::sockopt::linger, 0);
    r.set(zmq::sockopt::maxmsgsize, options.MessageLimit());
    r.set(zmq::sockopt::handshake_ivl, options.handshake_timeout_ms);
    r.set(zmq::sockopt::heartbeat_ivl, options.heartbeat_ivl_ms);
    r.set(zmq::sockopt::heartbeat_timeout, options.heartbeat_timeout_ms);
    r.set(zmq::sockopt::heartbeat_ttl, options.heartbeat_timeout_ms);
    r.set(zmq::sockopt::sndhwm, options.send_hwm);
    r.set(zmq::sockopt::rcvhwm, options.send_hwm);
    r.bind(options.bind);
    impl->endpoint = r.get(zmq::sockopt::last_endpoint);
    if (options.curve_keys.empty() && !IsLoopbackEndpoint(impl->endpoint)) {
      PRISM_LOG(WARNING) << "event=unencrypted_listener endpoint=" << impl->endpoint
                         << " message=\"plain TCP on a non-loopback address: anyone who can reach it may open "
                            "sessions and read the traffic; use --curve-keys and --allowed-clients\"";
    }
  } catch (const zmq::error_t& e) {
    return UnavailableError("cannot bind " + options.bind + ": " + e.what());
  }
  impl->pool = std::make_unique<ThreadPool>(options.threads, options.dense_nice);
  impl->workers = std::make_unique<DenseWorkers>(options.dense_workers, impl->pool.get(), options.dense_nice);
  impl->StartMonitor();
  PRISM_RETURN_IF_ERROR(impl->StartHttp());
  return std::unique_ptr<Server>(new Server(std::move(impl)));
}

const std::string& Server::endpoint() const { return impl_->endpoint; }
const std::string& Server::metrics_endpoint() const { return impl_->metrics_endpoint; }
Status Server::Run() { return impl_->Run(); }
void Server::HandleMessageForFuzzing(const std::vector<std::string>& parts) {
  std::vector<zmq::message_t> messages;
  for (const std::string& p : parts) messages.emplace_back(p.data(), p.size());
  if (messages.empty()) return;
  impl_->HandleMessage(messages);  // Run catches what escapes; a fuzzer must see it
  std::deque<Impl::Outgoing> events;
  {
    std::lock_guard<std::mutex> lock(impl_->outbox_mutex);
    events.swap(impl_->outbox);
  }
  for (Impl::Outgoing& o : events) impl_->HandleEvent(o);
}

void Server::RequestStop() {
  impl_->stop_requested = true;
  impl_->Wake();
}

}  // namespace prism::server
