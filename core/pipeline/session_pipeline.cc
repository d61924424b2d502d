#include "core/pipeline/session_pipeline.h"

#include <sys/syscall.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <exception>
#include <string>
#include <utility>

#include "core/util/logging.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

double MsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t).count();
}

}  // namespace

Status SessionPipelineOptions::Check() const {
  PRISM_RETURN_IF_ERROR(slam.Check());
  PRISM_RETURN_IF_ERROR(dense.Check());
  MapChunkCodecOptions c = chunk;
  c.voxel_m = dense.map.voxel_m;
  PRISM_RETURN_IF_ERROR(c.Check());
  if (frame_queue_capacity < 1 || frame_queue_capacity > 1024)
    return InvalidArgumentError("SessionPipelineOptions.frame_queue_capacity = " +
                                std::to_string(frame_queue_capacity) + "; violated: in [1, 1024]");
  if (skip_depth_update_backlog < 0 || skip_depth_update_backlog > 1024)
    return InvalidArgumentError("SessionPipelineOptions.skip_depth_update_backlog = " +
                                std::to_string(skip_depth_update_backlog) + "; violated: in [0, 1024]");
  if (keyframe_queue_capacity < 1 || keyframe_queue_capacity > 256)
    return InvalidArgumentError("SessionPipelineOptions.keyframe_queue_capacity = " +
                                std::to_string(keyframe_queue_capacity) + "; violated: in [1, 256]");
  if (!(covered_keyframe_fraction > 0 && covered_keyframe_fraction <= 1))
    return InvalidArgumentError("SessionPipelineOptions.covered_keyframe_fraction = " +
                                std::to_string(covered_keyframe_fraction) + "; violated: in (0, 1]");
  return Status::Ok();
}

StatusOr<std::unique_ptr<SessionPipeline>> SessionPipeline::Create(const RigCalibration& rig,
                                                                   const SessionPipelineOptions& options,
                                                                   DenseWorkers* workers, PipelineEventSink sink) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.Check());
  if (workers == nullptr || !sink) return InvalidArgumentError("SessionPipeline needs dense workers and an event sink");
  std::unique_ptr<SessionPipeline> p(new SessionPipeline(rig, options, workers, std::move(sink)));
  // A camera with lens distortion: the SLAM and the dense stage run on the undistorted pinhole camera
  // every decoded frame is remapped into (core/slam/undistort.h); poses and the map are unaffected.
  PRISM_ASSIGN_OR_RETURN(ImageUndistorter undistorter, ImageUndistorter::Create(rig.camera));
  RigCalibration pinhole_rig = rig;
  pinhole_rig.camera = undistorter.camera();
  p->undistorter_ = std::make_unique<ImageUndistorter>(std::move(undistorter));
  // The final adjustment runs after the last keyframes are handed to the dense stage (SlamLoop), so the
  // map does not wait for it.
  SlamOptions slam_options = options.slam;
  slam_options.final_adjustment = false;
  PRISM_ASSIGN_OR_RETURN(p->slam_, SlamSystem::Create(pinhole_rig, slam_options));
  PRISM_ASSIGN_OR_RETURN(p->dense_, DenseStage::Create(pinhole_rig, options.dense, workers->pool()));
  p->slam_thread_ = std::thread([raw = p.get()] {
    SetCurrentThreadName("prism-slam");
    raw->slam_thread_id_ = static_cast<int>(::syscall(SYS_gettid));
    raw->SlamLoop();
  });
  return p;
}

SessionPipeline::SessionPipeline(const RigCalibration& rig, const SessionPipelineOptions& options,
                                 DenseWorkers* workers, PipelineEventSink sink)
    : rig_(rig),
      options_(options),
      workers_(workers),
      strand_(workers->NewStrand()),
      sink_(std::move(sink)),
      frames_(static_cast<size_t>(options.frame_queue_capacity), options.input_policy) {}

bool SessionPipeline::Deprioritise() {
  const int tid = slam_thread_id_;
  if (tid == 0 || !SetThreadNice(tid, 19)) return false;
  strand_->MoveToBackground();
  return true;
}

void SessionPipeline::SkipDenseUntil(std::chrono::steady_clock::time_point until) {
  skip_dense_until_.store(until.time_since_epoch().count());
}

SessionPipeline::~SessionPipeline() {
  Abort();
  if (slam_thread_.joinable()) slam_thread_.join();
  // The SLAM thread posted the final job last: once the strand is idle nothing refers to this.
  while (strand_->pending() > 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
}

Status SessionPipeline::Push(EncodedFrame frame, bool* dropped_oldest) {
  if (dropped_oldest) *dropped_oldest = false;
  if (!accepting_) {
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.frames_rejected;
    return FailedPreconditionError(failed_ ? "the session has failed" : "the session is closing");
  }
  switch (frames_.Push(std::move(frame))) {
    case PushResult::kPushed: {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_received;
      return Status::Ok();
    }
    case PushResult::kDroppedOldest: {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_received;
      ++stats_.frames_dropped;
      if (dropped_oldest) *dropped_oldest = true;
      return Status::Ok();
    }
    case PushResult::kRejected: {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_rejected;
      return ResourceExhaustedError("frame queue full (" + std::to_string(frames_.capacity()) +
                                    " frames); wait for frame credits and retry");
    }
    case PushResult::kClosed:
      break;
  }
  std::lock_guard<std::mutex> lock(mutex_);
  ++stats_.frames_rejected;
  return FailedPreconditionError("the session is closing");
}

void SessionPipeline::Finish() {
  accepting_ = false;
  frames_.Close();
}

void SessionPipeline::Abort() {
  accepting_ = false;
  aborted_ = true;
  const size_t dropped = frames_.Clear();
  frames_.Close();
  std::lock_guard<std::mutex> lock(mutex_);
  stats_.frames_dropped += dropped;
  stats_.keyframes_dropped += keyframes_.size();
  keyframes_.clear();
  keyframe_room_.notify_all();
}

PipelineStats SessionPipeline::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  PipelineStats s = stats_;
  s.metres_per_unit = metres_per_unit_;
  return s;
}

PointCloud SessionPipeline::MapSnapshot() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  return dense_->map().ToPointCloud();
}

void SessionPipeline::Fail(const Status& status) {
  if (failed_.exchange(true)) return;
  accepting_ = false;
  PRISM_LOG(ERROR) << "session pipeline failed: " << status;
  PipelineEvent e;
  e.kind = PipelineEvent::Kind::kError;
  e.status = status;
  e.fatal = true;
  sink_(std::move(e));
  const size_t dropped = frames_.Clear();
  frames_.Close();
  std::lock_guard<std::mutex> lock(mutex_);
  stats_.frames_dropped += dropped;
  keyframe_room_.notify_all();
}

void SessionPipeline::SlamLoop() {
  cv::Mat rgb;
  while (std::optional<EncodedFrame> frame = frames_.Pop()) {
    if (aborted_ || failed_) {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_dropped;
      continue;
    }
    TrackFrame(*frame, &rgb);
  }
  std::vector<Sim3d> final_keyframe_poses;
  std::vector<PipelineEvent> refined;  // sent with the session's final scale, by the strand's last job
  if (!aborted_ && !failed_) FinishSlam(&final_keyframe_poses, &refined);
  // Last job of the strand: after every keyframe queued above.
  strand_->Post([this, final_keyframe_poses = std::move(final_keyframe_poses), refined = std::move(refined)]() mutable {
    FinishMap(final_keyframe_poses, &refined);
  });
}

void SessionPipeline::TrackFrame(const EncodedFrame& frame, cv::Mat* rgb) {
  const auto t0 = std::chrono::steady_clock::now();
  // Behind the input: this frame's pose only (the frames still waiting, not counting this one).
  const bool skip_depth_update = options_.skip_depth_update_backlog > 0 &&
                                 frames_.size() >= static_cast<size_t>(options_.skip_depth_update_backlog);
  Status decoded =
      DecodeFrame(frame.bytes.data(), frame.bytes.size(), frame.codec, rig_.camera.width, rig_.camera.height, rgb);
  if (decoded.ok() && !undistorter_->identity()) {
    StatusOr<cv::Mat> undistorted = undistorter_->Undistort(*rgb);
    if (undistorted.ok()) *rgb = std::move(undistorted).value();
    else decoded = undistorted.status();
  }
  if (!decoded.ok()) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_bad;
    }
    SendFrameError(frame.sequence_number, decoded);
    return;
  }
  try {
    StatusOr<SlamFrameResult> r =
        slam_->ProcessFrame(static_cast<double>(frame.timestamp_ns) * 1e-9, *rgb, skip_depth_update);
    if (!r.ok()) {
      SendFrameError(frame.sequence_number, r.status());
      return;
    }
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.frames_processed;
      // Asked to skip and did (a frame that made a keyframe, or was tracked while initialising, did not).
      stats_.frames_depth_update_skipped += skip_depth_update && r->state == SlamState::kTracking && !r->depth_updated;
      stats_.slam_ms_total += MsSince(t0);
    }
    PipelineEvent e;
    e.kind = PipelineEvent::Kind::kPose;
    e.frame_sequence_number = frame.sequence_number;
    e.timestamp_ns = frame.timestamp_ns;
    e.slam = *r;
    e.metres_per_unit = metres_per_unit_;
    // By SLAM frame id (a frame the SLAM recorded before failing leaves a gap).
    if (r->frame_id >= 0) {
      if (reported_.size() <= static_cast<size_t>(r->frame_id)) reported_.resize(static_cast<size_t>(r->frame_id) + 1);
      reported_[static_cast<size_t>(r->frame_id)] = {true, frame.sequence_number, frame.timestamp_ns, r->state,
                                                     r->world_from_camera};
    }
    sink_(std::move(e));
    if (UpdateStartCheck()) {
      for (PipelineEvent& refined : RefinedPoses(/*untracked_too=*/true)) {
        refined.metres_per_unit = metres_per_unit_;
        sink_(std::move(refined));
      }
    }
    for (SlamKeyframe& kf : slam_->TakeFinishedKeyframes()) QueueKeyframe(std::move(kf));
  } catch (const std::exception& ex) {
    Fail(InternalError(std::string("SLAM failed: ") + ex.what()));
  }
}

void SessionPipeline::SendFrameError(uint64_t sequence_number, const Status& status) {
  PipelineEvent e;
  e.kind = PipelineEvent::Kind::kError;
  e.status = Status(status.code(), "frame " + std::to_string(sequence_number) + ": " + status.message());
  e.has_frame = true;
  e.frame_sequence_number = sequence_number;
  sink_(std::move(e));
}

void SessionPipeline::FinishSlam(std::vector<Sim3d>* final_keyframe_poses, std::vector<PipelineEvent>* refined) {
  try {
    // The last keyframes go to the dense stage before the final adjustment: the map is complete while
    // the poses are refined (the map rebuilt at the final poses follows, FinishMap).
    for (SlamKeyframe& kf : slam_->FinishTracking()) QueueKeyframe(std::move(kf));
    const bool second_start_at_finish = UpdateStartCheck();
    const SlamStreamEnd end = slam_->FinishStream(options_.remap_at_end && options_.metric_scale_at_end);
    if (options_.remap_at_end && options_.metric_scale_at_end) TakeFinalMetricScale(end);
    *refined = RefinedPoses(/*untracked_too=*/second_start_at_finish);
    if (options_.remap_at_end) *final_keyframe_poses = slam_->KeyframePoses();
  } catch (const std::exception& ex) {
    Fail(InternalError(std::string("SLAM failed at the end: ") + ex.what()));
  }
}

void SessionPipeline::TakeFinalMetricScale(const SlamStreamEnd& end) {
  if (!end.metric) {
    PRISM_LOG(INFO) << "pipeline: no metric scale from the co-moving lights: " << end.metric_error;
    return;
  }
  const MetricScaleEstimate* metric = &*end.metric;
  PRISM_LOG(INFO) << "pipeline: metric scale from the co-moving lights " << metric->metres_per_world_unit
                  << " m per unit (dense stage " << metres_per_unit_ << ") in " << 1000 * end.metric_seconds
                  << " ms (final adjustment " << 1000 * end.adjustment_seconds << " ms)";
  final_metres_per_unit_ = metric->metres_per_world_unit;
  final_shading_consistent_ = metric->consistent;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stats_.shading_check = metric->consistent ? 1 : 2;
    stats_.shading_pair_spread = metric->pair_spread;
  }
  if (!metric->consistent) {
    PRISM_LOG(WARNING) << "pipeline: the session's reconstruction disagrees with the co-moving lights' "
                          "shading (keyframe pairs' shading scales spread by "
                       << metric->pair_spread << " of their median): its trajectory and map are probably "
                       << "distorted";
  }
}

void SessionPipeline::FinishMap(const std::vector<Sim3d>& final_keyframe_poses, std::vector<PipelineEvent>* refined) {
  if (!aborted_ && !failed_) {
    try {
      StatusOr<MapChunk> rest = InternalError("not run");
      size_t map_points = 0;
      {
        std::lock_guard<std::mutex> lock(map_mutex_);
        rest = dense_->Flush();
        map_points = dense_->map().output_size();
      }
      if (rest.ok() && !rest->empty()) EmitChunk(*rest, 0, Rigid3d(), map_points);
      StatusOr<MapChunk> rebuilt = InternalError("not run");
      if (options_.remap_at_end && !final_keyframe_poses.empty() && dense_->kept_clouds() > 0) {
        const auto t0 = std::chrono::steady_clock::now();
        {
          std::lock_guard<std::mutex> lock(map_mutex_);
          const double dense_scale = dense_->session_metres_per_unit();
          const MetresPerUnit chosen =
              ChooseMetresPerUnit(dense_scale, final_metres_per_unit_, final_shading_consistent_);
          PRISM_LOG(INFO) << "pipeline: the session's scale " << chosen.value << " m per unit from the "
                          << (chosen.from_shading ? "co-moving lights" : "dense stage") << " (dense stage "
                          << dense_scale << ", lights " << final_metres_per_unit_ << ")";
          rebuilt = dense_->Remap(final_keyframe_poses, 1e-6, chosen.value);
          map_points = dense_->map().output_size();
        }
        if (!rebuilt.ok()) {
          PRISM_LOG(WARNING) << "pipeline: map not rebuilt at the final keyframe poses: " << rebuilt.status();
        } else if (rebuilt->replaces_map) {
          PRISM_LOG(INFO) << "pipeline: map rebuilt at the final keyframe poses, " << map_points << " voxels from "
                          << dense_->kept_clouds() << " keyframe clouds in " << MsSince(t0) << " ms";
          metres_per_unit_ = dense_->map_metres_per_unit();
        }
      }
      SendRefined(refined);
      if (rebuilt.ok() && !rebuilt->empty()) EmitChunk(*rebuilt, 0, Rigid3d(), map_points);
    } catch (const std::exception& ex) {
      Fail(InternalError(std::string("dense stage failed at the end: ") + ex.what()));
    }
  }
  // The SLAM's refined poses do not depend on the map: they go out even when its end failed.
  if (!aborted_) SendRefined(refined);
  PipelineEvent e;
  e.kind = PipelineEvent::Kind::kFinished;
  e.stats = stats();
  sink_(std::move(e));
}

void SessionPipeline::SendRefined(std::vector<PipelineEvent>* refined) {
  for (PipelineEvent& e : *refined) {
    e.metres_per_unit = metres_per_unit_;
    sink_(std::move(e));
  }
  refined->clear();
}

std::vector<PipelineEvent> SessionPipeline::RefinedPoses(bool untracked_too) {
  const std::vector<SlamFrameResult> final_poses = slam_->Trajectory();
  std::vector<PipelineEvent> refined;
  for (size_t i = 0; i < final_poses.size() && i < reported_.size(); ++i) {
    const SlamFrameResult& f = final_poses[i];
    const ReportedPose& sent = reported_[i];
    if (!sent.valid) continue;
    // Provisional or lost: nothing better, unless the frame was sent as tracked by a start since replaced.
    if (f.state != SlamState::kTracking && !(untracked_too && sent.state == SlamState::kTracking)) continue;
    const bool moved = sent.state != f.state ||
                       (f.world_from_camera.translation - sent.world_from_camera.translation).norm() > 1e-6 ||
                       f.world_from_camera.rotation.angularDistance(sent.world_from_camera.rotation) > 1e-6;
    if (!moved) continue;
    PipelineEvent e;
    e.kind = PipelineEvent::Kind::kPose;
    e.frame_sequence_number = sent.sequence_number;
    e.timestamp_ns = sent.timestamp_ns;
    e.slam = f;
    e.refined = true;
    refined.push_back(std::move(e));
    reported_[i].state = f.state;
    reported_[i].world_from_camera = f.world_from_camera;
  }
  PRISM_LOG(INFO) << "pipeline: " << refined.size() << " of " << reported_.size() << " poses refined";
  return refined;
}

bool SessionPipeline::UpdateStartCheck() {
  if (start_check_done_) return false;
  const StartCheckReport r = slam_->start_check();
  if (!r.done) return false;
  start_check_done_ = true;
  const int state = !r.checked ? 0 : r.passed ? 1 : r.second_kept ? 2 : 3;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stats_.start_check = state;
    stats_.start_pair_spread = r.first_spread;
  }
  // The second start replaced the first: every pose sent so far was of the first.
  if (state != 2) return false;
  PRISM_LOG(WARNING) << "pipeline: the SLAM's first start disagreed with the shading (pair spread " << r.first_spread
                     << "); the second start replaced it, every pose is sent again";
  return true;
}

void SessionPipeline::QueueKeyframe(SlamKeyframe keyframe) {
  {
    std::unique_lock<std::mutex> lock(mutex_);
    ++stats_.keyframes;
    const size_t capacity = static_cast<size_t>(options_.keyframe_queue_capacity);
    if (keyframes_.size() >= capacity) {
      if (options_.input_policy == OverflowPolicy::kReject) {
        // Upload: hold SLAM (and so the frame credits) until the dense stage takes a keyframe.
        ++stats_.keyframe_waits;
        keyframe_room_.wait(lock, [&] { return keyframes_.size() < capacity || aborted_ || failed_; });
        if (aborted_ || failed_) {
          ++stats_.keyframes_dropped;
          return;
        }
      } else {
        keyframes_.pop_front();
        ++stats_.keyframes_dropped;
      }
    }
    keyframes_.push_back({std::move(keyframe), std::chrono::steady_clock::now()});
  }
  strand_->Post([this] { DenseJob(); });
}

size_t SessionPipeline::queued_keyframes() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return keyframes_.size();
}

void SessionPipeline::EmitChunk(const MapChunk& changes, uint64_t keyframe_id, const Rigid3d& world_from_keyframe,
                                size_t map_points, DenseTiming timing) {
  const auto encode_start = std::chrono::steady_clock::now();
  MapChunkCodecOptions chunk_options = options_.chunk;
  chunk_options.voxel_m = options_.dense.map.voxel_m;
  StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(changes.cloud, chunk_options);
  if (!encoded.ok()) {  // nothing encodable (every point off the grid)
    if (changes.replaces_map) {
      PRISM_LOG(WARNING) << "pipeline: the rebuilt map could not be encoded (" << encoded.status()
                         << "); clients keep the map as merged";
    }
    return;
  }
  PipelineEvent e;
  e.kind = PipelineEvent::Kind::kChunk;
  e.keyframe_id = keyframe_id;
  e.chunk_sequence = changes.sequence;
  e.num_points = encoded->num_points;
  e.draco = std::move(encoded->bytes);
  e.world_from_keyframe = world_from_keyframe;
  e.map_points = map_points;
  e.replaces_map = changes.replaces_map;
  e.map_voxels = dense_->map().size();
  e.kept_points = dense_->kept_points();
  e.timing = timing;
  if (timing.started_at != std::chrono::steady_clock::time_point()) {
    e.timing.encode_ms = MsSince(encode_start);
    e.timing.total_ms = MsSince(timing.started_at);
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.chunks;
    stats_.chunk_bytes += e.draco.size();
    stats_.chunk_points += e.num_points;
    stats_.map_points = map_points;
  }
  sink_(std::move(e));
}

void SessionPipeline::DenseJob() {
  SlamKeyframe kf;
  std::chrono::steady_clock::time_point queued_at;
  bool backlog = false;  // another of the session's keyframes waits behind this one
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (keyframes_.empty()) return;  // dropped by the overflow policy or Abort
    kf = std::move(keyframes_.front().keyframe);
    queued_at = keyframes_.front().queued_at;
    keyframes_.pop_front();
    keyframe_room_.notify_all();
    const bool skip = std::chrono::steady_clock::now().time_since_epoch().count() < skip_dense_until_.load();
    if (aborted_ || failed_ || skip) {
      ++stats_.keyframes_dropped;
      return;
    }
    backlog = !keyframes_.empty();
  }
  try {
    const auto t0 = std::chrono::steady_clock::now();
    DenseTiming timing;
    timing.queued_at = queued_at;
    timing.started_at = t0;
    DenseKeyframe dk;
    dk.id = static_cast<uint64_t>(kf.id);
    dk.rgb = kf.rgb;
    dk.world_from_keyframe = kf.world_from_keyframe;
    dk.depth = kf.depth;
    StatusOr<DenseKeyframeResult> r = InternalError("not run");
    size_t map_points = 0;
    {
      std::lock_guard<std::mutex> lock(map_mutex_);
      if (backlog && options_.covered_keyframe_fraction < 1) {
        const double coverage = dense_->MapCoverage(dk);
        if (coverage > options_.covered_keyframe_fraction) {
          PRISM_LOG(INFO) << "pipeline: keyframe " << kf.id << " skips the dense stage: the map covers " << coverage
                          << " of it and another keyframe waits";
          std::lock_guard<std::mutex> stats_lock(mutex_);
          ++stats_.keyframes_dropped;
          return;
        }
      }
      r = dense_->Process(dk);
      map_points = dense_->map().output_size();
    }
    if (!r.ok()) {
      {
        std::lock_guard<std::mutex> lock(mutex_);
        ++stats_.keyframes_failed;
      }
      PipelineEvent e;
      e.kind = PipelineEvent::Kind::kError;
      e.status = Status(r.status().code(),
                        "keyframe " + std::to_string(kf.id) + " skipped by the dense stage: " + r.status().message());
      sink_(std::move(e));
      return;
    }
    metres_per_unit_ = r->metres_per_unit;
    if (r->changes.empty()) return;
    const double s = r->metres_per_unit;
    timing.photometric_ms = r->photometric_ms;
    timing.fusion_ms = r->fusion_ms;
    timing.map_ms = r->map_ms;
    EmitChunk(r->changes, dk.id, Rigid3d(kf.world_from_keyframe.rotation, s * kf.world_from_keyframe.translation),
              map_points, timing);
    std::lock_guard<std::mutex> lock(mutex_);
    stats_.dense_ms_total += MsSince(t0);
  } catch (const std::exception& ex) {
    Fail(InternalError(std::string("dense stage failed: ") + ex.what()));
  }
}

}  // namespace prism
