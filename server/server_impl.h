// Server::Impl, prism-server's state on the transport thread, shared by its source files:
// server.cc (creation), server_transport.cc (poll loop, dispatch, sending, HTTP snapshot),
// server_sessions.cc (open, resume, frames, chunk credits), server_events.cc (pipeline events,
// summaries, housekeeping). Internal to server/.
#pragma once

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include <zmq.hpp>

#include "core/pipeline/dense_workers.h"
#include "core/pipeline/session_pipeline.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"
#include "prism/v1/session.pb.h"
#include "server/http_endpoint.h"
#include "server/memory_trimmer.h"
#include "server/metrics.h"
#include "server/server.h"
#include "server/server_options.h"
#include "server/session_store.h"

namespace prism::server {

using Clock = std::chrono::steady_clock;

// The last frame a session accepted into its queue: later frames' sequence numbers must be above its,
// their timestamps not before its.
struct AcceptedFrame {
  uint64_t sequence_number = 0;
  int64_t timestamp_ns = 0;
};

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
    bool deprioritised = false;  // over the limit once: its SLAM thread runs at the lowest priority
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

  Impl();
  ~Impl();

  // server_transport.cc
  void Wake();
  Status StartHttp();
  void PublishSnapshot(bool force = true);
  void StartMonitor();
  void ReadMonitor();
  void UpdateGauges();
  bool Send(const std::string& peer, const v1::Envelope& env, const std::vector<uint8_t>* payload = nullptr);
  void SendError(const std::string& peer, const Status& status, const std::string& session_id, bool retryable,
                 bool session_closed, const uint64_t* frame = nullptr);
  void SendVersionMismatch(const std::string& peer, int version);
  void HandleMessage(std::vector<zmq::message_t>& parts);
  Status Run();

  // server_sessions.cc
  Session* FindSession(const std::string& peer, const std::string& id);
  void ResumeSession(const std::string& peer, const v1::OpenSession& open);
  void FillSessionOpened(const Session* s, v1::SessionOpened* o) const;
  void OpenSession(const std::string& peer, const v1::OpenSession& open);
  void HandleFrame(const std::string& peer, const v1::Frame& frame, const zmq::message_t* payload);
  void QueueChunk(Session* s, Session::PendingChunk&& c);
  void FlushChunks(Session* s);

  // server_events.cc
  void HandleEvent(Outgoing& out);
  void PersistAndSummarise(Session* s);
  void Housekeeping();
  void TrimMemory();
};

}  // namespace prism::server
