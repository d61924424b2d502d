// SlamSystem's frame tracking: the tracker's keyframe, each frame's alignment, frame poses, relocalisation.
#include <algorithm>
#include <chrono>
#include <sstream>
#include <string>

#include "core/slam/slam_system.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/logging.h"

namespace prism {

using slam_internal::kRadToDeg;
using slam_internal::QualityOf;
using slam_internal::ScopedSeconds;
using slam_internal::SecondsSince;

Status SlamSystem::Impl::RefreshTracker() { return SetTrackerKeyframe(keyframes.back().rgb, *current_depth); }

void SlamSystem::Impl::RefreshTrackerOrKeep(int64_t frame_id) {
  const Status refreshed = RefreshTracker();
  if (refreshed.ok()) return;
  PRISM_LOG(WARNING) << "slam: frame " << frame_id << ": the tracker keeps its earlier copy of keyframe "
                     << keyframes.back().id << " (" << refreshed.message() << ")";
}

Status SlamSystem::Impl::SetTrackerKeyframe(const cv::Mat& rgb, const KeyframeDepth& depth) {
  return tracker->SetKeyframe(
      rgb, depth.ToInverseDepthMap(options.tracking_min_observations, options.tracking_max_relative_sigma));
}

StatusOr<KeyframeDepth> SlamSystem::Impl::PropagateForTracking(const cv::Mat& rgb, const KeyframeDepth& source,
                                                               const Rigid3d& this_from_source,
                                                               const KeyframeDepth* blank) {
  StatusOr<KeyframeDepth> created = blank ? StatusOr<KeyframeDepth>(blank->Blank())
                                          : KeyframeDepth::Create(rgb, rig.camera, options.depth, rig.crosstalk);
  PRISM_ASSIGN_OR_RETURN(KeyframeDepth kd, std::move(created));
  kd.PropagateFrom(source, this_from_source, options.new_pixel_relative_sigma);
  if (!SetTrackerKeyframe(rgb, kd).ok())
    return FailedPreconditionError("too few points with depth in the new keyframe");
  return kd;
}

Rigid3d SlamSystem::Impl::WorldFromFrame(const FrameRecord& f, bool corrected) const {
  const Keyframe& k = keyframes[static_cast<size_t>(f.result.keyframe_id)];
  Rigid3d keyframe_from_frame = f.frame_from_keyframe.Inverse();
  if (corrected && options.distribute_keyframe_corrections && k.next >= 0) {
    const Keyframe& n = keyframes[static_cast<size_t>(k.next)];
    const FrameRecord& made = frames[static_cast<size_t>(n.frame_id)];
    if (f.result.frame_id > k.frame_id && f.result.frame_id <= n.frame_id && made.result.keyframe_id == k.id &&
        made.result.state == SlamState::kTracking) {
      // The next keyframe's camera in this keyframe (this keyframe's unit): now, and as tracked.
      const Rigid3d keyframe_from_next = BFromAInUnitsOfA(k.world_from_keyframe, n.world_from_keyframe).Inverse();
      const Rigid3d correction = keyframe_from_next * made.frame_from_keyframe;
      const double fraction =
          static_cast<double>(f.result.frame_id - k.frame_id) / static_cast<double>(n.frame_id - k.frame_id);
      const Eigen::AngleAxisd angle_axis(correction.rotation);
      const Rigid3d part(ExpSo3(fraction * angle_axis.angle() * angle_axis.axis()), fraction * correction.translation);
      keyframe_from_frame = part * keyframe_from_frame;
    }
  }
  return k.world_from_keyframe.TransformPose(keyframe_from_frame);
}

Rigid3d SlamSystem::Impl::LastGoodWorldFromCamera() const {
  // As tracked (the frames' corrections are for their output: the estimation never depends on them).
  for (auto it = frames.rbegin(); it != frames.rend(); ++it)
    if (it->result.state == SlamState::kTracking)
      return it->result.keyframe_id >= 0 ? WorldFromFrame(*it, /*corrected=*/false) : it->result.world_from_camera;
  return Rigid3d();
}

StatusOr<SlamFrameResult> SlamSystem::Impl::TrackFrame(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  FrameRecord rec;
  rec.result.frame_id = frame_id;
  rec.result.timestamp = timestamp;
  Rigid3d guess = has_last ? last_frame_from_kf : Rigid3d();
  if (has_last && has_prev) guess = (last_frame_from_kf * prev_frame_from_kf.Inverse()) * last_frame_from_kf;
  ++timings.tracked_frames;
  const auto tracking_start = std::chrono::steady_clock::now();
  PRISM_ASSIGN_OR_RETURN(TrackingResult tr, tracker->Track(rgb, guess));
  const double mean_idepth_now = current_depth->MeanInverseDepth();
  const bool implausible = tr.ok && has_last && !PlausibleStep(tr.frame_from_keyframe, guess, mean_idepth_now);
  bool retried = false;
  if ((!tr.ok || implausible) && has_last) {
    PRISM_ASSIGN_OR_RETURN(TrackingResult retry, tracker->Track(rgb, last_frame_from_kf));
    if (retry.ok && PlausibleStep(retry.frame_from_keyframe, guess, mean_idepth_now)) {
      tr = retry;
      retried = true;
    } else if (implausible) {
      std::ostringstream m;
      m << "implausible jump from the predicted pose ("
        << RotationAngle(tr.frame_from_keyframe.rotation * guess.rotation.inverse()) * kRadToDeg << " deg, "
        << (tr.frame_from_keyframe.translation - guess.translation).norm() * mean_idepth_now << " of the mean depth)";
      tr.ok = false;
      tr.lost_reason = m.str();
    }
  }
  timings.tracking += SecondsSince(tracking_start);
  int kf_index = static_cast<int>(keyframes.size()) - 1;
  if (!tr.ok) {
    const ScopedSeconds timer(&timings.relocalisation);
    ++lost_count;
    Rigid3d reloc_pose;
    int reloc_kf = -1;
    std::string reloc_failure;
    if (lost_count >= options.relocalise_after_lost_frames && Relocalise(rgb, &reloc_pose, &reloc_kf)) {
      // Resume from the keyframe found: a new keyframe at this frame, seeded from its depth. The frame
      // is recorded first (MakeKeyframe marks it), and taken back if the new keyframe is unusable.
      PRISM_ASSIGN_OR_RETURN(KeyframeDepth source, KeyframeDepth::Create(keyframes[static_cast<size_t>(reloc_kf)].rgb,
                                                                         rig.camera, options.depth, rig.crosstalk));
      source.Seed(keyframes[static_cast<size_t>(reloc_kf)].final_depth.inverse_depth, 0.05, 2);
      rec.frame_from_keyframe = reloc_pose;
      rec.result.keyframe_id = reloc_kf;
      rec.result.state = SlamState::kTracking;
      rec.result.message = "relocalised against keyframe " + std::to_string(reloc_kf) + " after " + tr.lost_reason;
      rec.result.world_from_camera = WorldFromFrame(rec);
      frames.push_back(rec);
      const Status made = MakeKeyframe(frame_id, timestamp, rgb, reloc_kf, reloc_pose, source);
      if (made.ok()) {
        frames.back().result.new_keyframe = true;
        lost_count = 0;
        PRISM_LOG(INFO) << "slam: frame " << frame_id << " " << frames.back().result.message;
        return frames.back().result;
      }
      frames.pop_back();
      // The current keyframe stays; restore the tracker's copy of it (MakeKeyframe replaced it).
      RefreshTrackerOrKeep(frame_id);
      reloc_failure =
          " (relocalised against keyframe " + std::to_string(reloc_kf) + " but " + std::string(made.message()) + ")";
      rec = FrameRecord();
      rec.result.frame_id = frame_id;
      rec.result.timestamp = timestamp;
    }
    rec.result.state = SlamState::kLost;
    rec.result.message = "tracking lost: " + tr.lost_reason + reloc_failure;
    // Keep the last good pose.
    rec.result.world_from_camera = LastGoodWorldFromCamera();
    rec.result.keyframe_id = -1;
    frames.push_back(rec);
    return rec.result;
  }
  lost_count = 0;
  rec.frame_from_keyframe = tr.frame_from_keyframe;
  rec.result.keyframe_id = keyframes[static_cast<size_t>(kf_index)].id;
  rec.result.state = SlamState::kTracking;
  // The previous frame's pose on this keyframe (the keyframe's own pose when it was made from it).
  rec.result.tracking = QualityOf(tr, retried, guess, has_last ? last_frame_from_kf : Rigid3d(), mean_idepth_now);
  rec.result.world_from_camera = WorldFromFrame(rec);
  frames.push_back(rec);
  prev_frame_from_kf = last_frame_from_kf;
  has_prev = has_last;
  last_frame_from_kf = tr.frame_from_keyframe;
  has_last = true;

  // Stereo update of the keyframe's depth (every depth_update_interval frames, and on a frame that
  // makes a keyframe).
  ++frames_since_keyframe;
  const double rotation_deg = RotationAngle(tr.frame_from_keyframe.rotation) * kRadToDeg;
  const auto needs_keyframe = [&](double mean_idepth) {
    const double distance = tr.frame_from_keyframe.translation.norm() * mean_idepth;
    return distance > options.keyframe_distance_fraction ||
           tr.visible_fraction < options.keyframe_min_visible_fraction ||
           rotation_deg > options.keyframe_max_rotation_deg;
  };
  // Over the mapping budget: the time spent so far on mapping, with this update's expected time (the
  // mean of the updates so far), against the budget of the frames tracked.
  const double expected_update = timings.depth_updates > 0 ? timings.depth_update / timings.depth_updates : 0.0;
  const bool over_budget =
      options.mapping_budget_ms > 0 && 1000.0 * (timings.depth_update + timings.keyframes + expected_update) >
                                           options.mapping_budget_ms * static_cast<double>(timings.tracked_frames);
  const bool interval_update = !skip_depth_update && frames_since_keyframe % options.depth_update_interval == 0;
  const bool makes_keyframe = needs_keyframe(current_depth->MeanInverseDepth());
  if (interval_update && over_budget && !makes_keyframe) ++timings.depth_updates_over_budget;
  if ((interval_update && !over_budget) || makes_keyframe) {
    const ScopedSeconds timer(&timings.depth_update);
    ++timings.depth_updates;
    frames.back().result.depth_updated = true;
    // The tracker's J of this frame when its normalisation is the depth filter's (the defaults: the
    // same image, not computed twice).
    const TrackerOptions& to = tracker->options();
    cv::Mat j, mean;
    if (to.shading_model != ShadingModel::kNone && to.local_mean_radius_px == options.depth.local_mean_radius_px &&
        to.local_mean_floor == options.depth.local_mean_floor && !tracker->last_frame_grey().empty()) {
      j = tracker->last_frame_grey();
    } else {
      KeyframeDepth::NormalisedGrey(rgb, options.depth, &j, &mean);
    }
    const DepthUpdateStats stats = current_depth->Update(j, tr.frame_from_keyframe, pool);
    timings.depth_pixels_searched += stats.searched;
    timings.depth_pixels_skipped += stats.skipped;
  }

  // New keyframe?
  const ScopedSeconds keyframe_timer(&timings.keyframes);
  PollPendingAdjustment();
  if (needs_keyframe(current_depth->MeanInverseDepth())) {
    current_depth->Regularise();
    const Status made = MakeKeyframe(frame_id, timestamp, rgb, kf_index, tr.frame_from_keyframe, *current_depth);
    if (made.ok()) {
      frames.back().result.new_keyframe = true;
      const ScopedSeconds adjustment_timer(&timings.keyframe_adjustment);
      if (options.keyframe_adjustment && (keyframes.size() - 1) % options.keyframe_adjustment_interval == 0) {
        if (pending_adjustment) {
          adjustment_owed = true;  // MakeKeyframe went on without the running one
        } else {
          AdjustWindow();
        }
      }
    } else {
      // Keep tracking against the current keyframe; restore the tracker's copy.
      frames.back().result.message = "no new keyframe: " + std::string(made.message());
      RefreshTrackerOrKeep(frame_id);
    }
  } else if (frames_since_keyframe % options.tracker_refresh_frames == 0) {
    current_depth->Regularise();
    RefreshTrackerOrKeep(frame_id);
  }
  return frames.back().result;
}

bool SlamSystem::Impl::Relocalise(const cv::Mat& rgb, Rigid3d* frame_from_kf, int* keyframe_index) {
  ApplyPendingAdjustment();  // the keyframes' current poses
  // The last good pose, and the keyframes nearest to it (finished ones have their final depth).
  const Rigid3d last_world_from_camera = LastGoodWorldFromCamera();
  std::vector<std::pair<double, int>> candidates;
  for (const Keyframe& k : keyframes) {
    if (!k.finished) continue;
    const double d = (k.world_from_keyframe.translation - last_world_from_camera.translation).norm();
    candidates.push_back({d, k.id});
  }
  std::sort(candidates.begin(), candidates.end());
  if (static_cast<int>(candidates.size()) > options.relocalise_max_keyframes)
    candidates.resize(options.relocalise_max_keyframes);
  for (const auto& [d, id] : candidates) {
    const Keyframe& k = keyframes[static_cast<size_t>(id)];
    if (!reloc_tracker->SetKeyframe(k.rgb, k.final_depth).ok()) continue;
    const Sim3d kf_from_world = k.world_from_keyframe.Inverse();
    const Rigid3d kf_from_camera = kf_from_world.TransformPose(last_world_from_camera);
    for (const Rigid3d& guess : {kf_from_camera.Inverse(), Rigid3d()}) {
      StatusOr<TrackingResult> tr = reloc_tracker->Track(rgb, guess);
      if (tr.ok() && tr->ok) {
        *frame_from_kf = tr->frame_from_keyframe;
        *keyframe_index = id;
        return true;
      }
    }
  }
  return false;
}

}  // namespace prism
