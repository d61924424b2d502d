// Session handlers on the transport thread: open, resume (a running session or a persisted one),
// frames into the pipeline, and the chunk queue that waits for the client's credits.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include <zmq.hpp>

#include "core/util/logging.h"
#include "server/rig_wire.h"
#include "server/server_impl.h"

namespace prism::server {
namespace {

// A session over max-frame-rate-hz maps no keyframe until it has kept to the limit this long.
constexpr std::chrono::seconds kDenseSkipAfterRateRefusal(2);

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

Server::Impl::Session* Server::Impl::FindSession(const std::string& peer, const std::string& id) {
  auto it = sessions.find(id);
  if (it == sessions.end() || it->second->peer != peer) {
    metrics.Add("prism_unknown_session_total");
    SendError(peer, NotFoundError("unknown session '" + id + "'"), id, false, true);
    return nullptr;
  }
  return it->second.get();
}

// Re-attaches a client to a running session, or replays an ended one from the data dir.
void Server::Impl::ResumeSession(const std::string& peer, const v1::OpenSession& open) {
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

void Server::Impl::FillSessionOpened(const Session* s, v1::SessionOpened* o) const {
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

void Server::Impl::OpenSession(const std::string& peer, const v1::OpenSession& open) {
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
  session->input_policy = po.input_policy == OverflowPolicy::kReject ? v1::INPUT_POLICY_UPLOAD : v1::INPUT_POLICY_LIVE;
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

void Server::Impl::HandleFrame(const std::string& peer, const v1::Frame& frame, const zmq::message_t* payload) {
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
      s->pipeline->SkipDenseUntil(now + kDenseSkipAfterRateRefusal);
      if (!s->deprioritised && s->pipeline->Deprioritise()) {
        s->deprioritised = true;
        metrics.Add("prism_sessions_deprioritised_total");
        PRISM_LOG(WARNING) << "event=session_deprioritised session=" << s->id << " peer=" << PeerName(peer)
                           << " message=\"frames over max-frame-rate-hz; the session runs at the lowest CPU priority "
                              "(nice 19) from now on, and its keyframes skip the dense stage until it has kept to "
                              "the limit for 2 s\"";
      }
      return refuse(ResourceExhaustedError("over the session frame-rate limit of " +
                                           std::to_string(options.max_frame_rate_hz) + " Hz (max-frame-rate-hz)"),
                    true);
    }
    s->rate_tokens -= 1.0;
  }
  if (Status fields = CheckFrameFields(frame, s->camera_width, s->camera_height, s->last_accepted); !fields.ok())
    return refuse(fields, false);
  if (!payload || payload->size() == 0) return refuse(InvalidArgumentError("frame without image payload part"), false);
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

void Server::Impl::QueueChunk(Session* s, Session::PendingChunk&& c) {
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

void Server::Impl::FlushChunks(Session* s) {
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

}  // namespace prism::server
