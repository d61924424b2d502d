// The pipelines' events on the transport thread: poses, map chunks (persisted, then queued for
// credits), errors and the end of a session; the summary and persisted map of a finished session;
// the periodic housekeeping that grants credits, reaps idle sessions and retires finished ones.
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <string>
#include <system_error>
#include <utility>

#include "core/io/ply_io.h"
#include "core/util/logging.h"
#include "server/server_impl.h"

namespace prism::server {
namespace {

void ToWire(const Rigid3d& pose, v1::Pose* out) {
  out->mutable_rotation()->set_x(pose.rotation.x());
  out->mutable_rotation()->set_y(pose.rotation.y());
  out->mutable_rotation()->set_z(pose.rotation.z());
  out->mutable_rotation()->set_w(pose.rotation.w());
  out->mutable_translation()->set_x(pose.translation.x());
  out->mutable_translation()->set_y(pose.translation.y());
  out->mutable_translation()->set_z(pose.translation.z());
}

}  // namespace

void Server::Impl::HandleEvent(Outgoing& out) {
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
      if (const DenseTiming& t = e.timing; t.queued_at != Clock::time_point()) {
        metrics.Observe("prism_keyframe_to_chunk_seconds",
                        std::chrono::duration<double>(Clock::now() - t.queued_at).count());
        metrics.Observe("prism_keyframe_wait_seconds",
                        std::chrono::duration<double>(t.started_at - t.queued_at).count());
        metrics.Observe("prism_dense_keyframe_seconds", t.total_ms / 1000.0);
        metrics.Observe("prism_dense_part_seconds{part=\"photometric\"}", t.photometric_ms / 1000.0);
        metrics.Observe("prism_dense_part_seconds{part=\"fusion\"}", t.fusion_ms / 1000.0);
        metrics.Observe("prism_dense_part_seconds{part=\"map\"}", t.map_ms / 1000.0);
        metrics.Observe("prism_dense_part_seconds{part=\"encode\"}", t.encode_ms / 1000.0);
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
      const double session_mb =
          (static_cast<double>(e.map_voxels) * kMapBytesPerPoint +
           static_cast<double>(e.kept_points) * kKeptBytesPerPoint + static_cast<double>(s->pending_bytes_in_memory)) /
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

void Server::Impl::PersistAndSummarise(Session* s) {
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
void Server::Impl::Housekeeping() {
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
      SendError(
          s->peer,
          UnavailableError("session closed after " + std::to_string(options.idle_timeout_ms) + " ms without a message"),
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
void Server::Impl::TrimMemory() {
  last_trim = Clock::now();
  trimmer.Request();
}

}  // namespace prism::server
