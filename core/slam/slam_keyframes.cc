// SlamSystem's keyframes: a new keyframe, loop closure, the adjustment window, the re-propagation.
#include <algorithm>
#include <cmath>
#include <string>

#include "core/slam/pose_graph.h"
#include "core/slam/slam_system.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/logging.h"

namespace prism {

using slam_internal::kRadToDeg;
using slam_internal::ScopedSeconds;

namespace {

Sim3d ToSim3(const Rigid3d& r) { return Sim3d(1.0, r.rotation, r.translation); }

}  // namespace

Status SlamSystem::Impl::MakeKeyframe(int64_t frame_id, double timestamp, const cv::Mat& rgb, int reference_kf,
                                      const Rigid3d& frame_from_reference, const KeyframeDepth& source) {
  // The start check's pair scales, on their thread (start_check_async), decide how this keyframe's window
  // adjustment runs (inline with 16 px cells while the check is open): as if they had been taken inline.
  if (pending_start_check) {
    WaitForStartCheck();
    if (StartCheckCloses(pending_start_check->scales)) start_check_running = false;
  }
  // The adjustment started at the previous keyframe moves the reference keyframe: first apply it (or,
  // with keyframe_adjustment_max_wait_ms, go on without it when it takes longer: ApplyAdjustment moves
  // this keyframe with the reference keyframe then).
  const bool adjusted = ApplyPendingAdjustment(options.keyframe_adjustment_max_wait_ms);
  // The tracker must accept it before it becomes the keyframe.
  PRISM_ASSIGN_OR_RETURN(KeyframeDepth kd, PropagateForTracking(rgb, source, frame_from_reference));
  // The last frame-to-frame motion (newest from previous tracked frame), for the next frame's guess.
  const bool had_velocity = has_last && has_prev;
  const Rigid3d velocity = had_velocity ? last_frame_from_kf * prev_frame_from_kf.Inverse() : Rigid3d();
  FinishCurrent();  // the keyframe being replaced (uses current_depth before it is replaced)
  Keyframe k;
  k.id = static_cast<int>(keyframes.size());
  k.frame_id = frame_id;
  k.timestamp = timestamp;
  k.rgb = rgb.clone();
  k.world_from_keyframe =
      keyframes[static_cast<size_t>(reference_kf)].world_from_keyframe * ToSim3(frame_from_reference.Inverse());
  PoseGraphEdge edge;
  edge.from = reference_kf;
  edge.to = k.id;
  edge.from_from_to = ToSim3(frame_from_reference.Inverse());
  edge.rotation_sigma = options.odometry_rotation_sigma;
  edge.translation_sigma = options.odometry_translation_sigma;
  edge.log_scale_sigma = options.odometry_log_scale_sigma;
  graph_edges.push_back(edge);
  keyframes.push_back(std::move(k));
  if (keyframes[static_cast<size_t>(reference_kf)].next < 0)
    keyframes[static_cast<size_t>(reference_kf)].next = keyframes.back().id;
  previous_depth.reset();
  previous_depth_kf = -1;
  if (options.keyframe_adjustment && options.repropagate_after_adjustment && !AdjustAsync() && current_depth &&
      &source == current_depth.get()) {
    previous_depth = std::move(current_depth);
    previous_depth_kf = reference_kf;
  }
  current_depth = std::make_unique<KeyframeDepth>(std::move(kd));
  frames_since_keyframe = 0;
  if (!adjusted) ++timings.keyframes_made_before_adjustment;
  if (options.loop_closure && keyframes.size() >= 2) {
    const ScopedSeconds loop_timer(&timings.loop_search);
    CloseLoops(static_cast<int>(keyframes.size()) - 2);
  }
  // The new keyframe is at this frame's pose; with the velocity kept, the previous frame sits one step
  // behind it, so the next frame's constant-velocity guess is one step ahead.
  has_last = true;
  last_frame_from_kf = Rigid3d();
  has_prev = options.keep_velocity_across_keyframes && had_velocity;
  prev_frame_from_kf = has_prev ? velocity.Inverse() : Rigid3d();
  return Status::Ok();
}

void SlamSystem::Impl::FinishCurrent() {
  if (!current_depth || keyframes.empty() || keyframes.back().finished) return;
  keyframes.back().final_depth = current_depth->ToInverseDepthMap();
  keyframes.back().finished = true;
}

bool SlamSystem::Impl::AlignKeyframes(int j, int k, Sim3d* j_from_k, std::string* why) {
  const Keyframe& kj = keyframes[static_cast<size_t>(j)];
  const Keyframe& kk = keyframes[static_cast<size_t>(k)];
  // Current estimate as a rigid guess in each keyframe's units.
  const Sim3d k_from_j_estimate = kk.world_from_keyframe.Inverse() * kj.world_from_keyframe;
  const Rigid3d guess_k_from_j(k_from_j_estimate.rotation, k_from_j_estimate.translation / k_from_j_estimate.scale);
  // A: image k against depth j -> k_from_j in j's units.
  if (!loop_tracker->SetKeyframe(kj.rgb, kj.final_depth).ok()) return (*why = "keyframe j has too little depth", false);
  StatusOr<TrackingResult> a = loop_tracker->Track(kk.rgb, guess_k_from_j);
  if (!a.ok() || !a->ok) return (*why = "k does not track on j", false);
  // B: image j against depth k -> j_from_k in k's units.
  if (!loop_tracker->SetKeyframe(kk.rgb, kk.final_depth).ok()) return (*why = "keyframe k has too little depth", false);
  const Rigid3d guess_j_from_k = a->frame_from_keyframe.Inverse();
  StatusOr<TrackingResult> b = loop_tracker->Track(kj.rgb, guess_j_from_k);
  if (!b.ok() || !b->ok) return (*why = "j does not track on k", false);
  const double inconsistency_deg =
      RotationAngle(a->frame_from_keyframe.rotation * b->frame_from_keyframe.rotation) * kRadToDeg;
  if (inconsistency_deg > options.loop_max_rotation_inconsistency_deg)
    return (*why = "alignments disagree by " + std::to_string(inconsistency_deg) + " deg", false);
  // Ratio of the depth units (k units per j unit): j's points moved into k's camera (in j's units)
  // against k's own depth at the pixels they land on.
  const PinholeCamera& cam = rig.camera;
  std::vector<double> ratios;
  for (int y = 0; y < cam.height; y += 2) {
    const float* d = kj.final_depth.inverse_depth.ptr<float>(y);
    for (int x = 0; x < cam.width; x += 2) {
      if (!(d[x] > 0)) continue;
      const Eigen::Vector3d p = a->frame_from_keyframe * (cam.Unproject(Eigen::Vector2d(x, y)) / d[x]);
      if (!(p.z() > 0)) continue;
      const Eigen::Vector2d uv = cam.Project(p);
      const int u = static_cast<int>(std::lround(uv.x())), v = static_cast<int>(std::lround(uv.y()));
      if (u < 0 || v < 0 || u >= cam.width || v >= cam.height) continue;
      const float idk = kk.final_depth.inverse_depth.at<float>(v, u);
      if (idk > 0) ratios.push_back((1.0 / idk) / p.z());
    }
  }
  // Every second pixel in x and y was tried: a quarter of the matches a full scan would find.
  if (static_cast<int>(ratios.size()) < options.loop_min_depth_matches / 4)
    return (*why = "depths overlap on " + std::to_string(ratios.size()) + " points", false);
  std::nth_element(ratios.begin(), ratios.begin() + static_cast<std::ptrdiff_t>(ratios.size() / 2), ratios.end());
  const double s_kj = ratios[ratios.size() / 2];
  if (!(s_kj > 0.5 && s_kj < 2.0)) return (*why = "implausible unit ratio " + std::to_string(s_kj), false);
  const Sim3d k_from_j(s_kj, a->frame_from_keyframe.rotation, s_kj * a->frame_from_keyframe.translation);
  *j_from_k = k_from_j.Inverse();
  return true;
}

void SlamSystem::Impl::CloseLoops(int index) {
  const Keyframe& kk = keyframes[static_cast<size_t>(index)];
  if (!kk.finished) return;
  // Mean depth of the keyframe in world units.
  double sum = 0;
  int count = 0;
  for (int y = 0; y < kk.final_depth.inverse_depth.rows; y += 4) {
    const float* d = kk.final_depth.inverse_depth.ptr<float>(y);
    for (int x = 0; x < kk.final_depth.inverse_depth.cols; x += 4)
      if (d[x] > 0) {
        sum += 1.0 / d[x];
        ++count;
      }
  }
  if (count == 0) return;
  const double mean_depth = kk.world_from_keyframe.scale * sum / count;
  const Eigen::Vector3d axis_k = kk.world_from_keyframe.rotation * Eigen::Vector3d::UnitZ();
  std::vector<std::pair<double, int>> candidates;
  for (int j = 0; j + options.loop_min_keyframe_gap <= index; ++j) {
    const Keyframe& kj = keyframes[static_cast<size_t>(j)];
    if (!kj.finished) continue;
    const double distance = (kj.world_from_keyframe.translation - kk.world_from_keyframe.translation).norm();
    const double angle =
        std::acos(std::clamp(axis_k.dot(kj.world_from_keyframe.rotation * Eigen::Vector3d::UnitZ()), -1.0, 1.0)) *
        kRadToDeg;
    if (distance < options.loop_max_distance_fraction * mean_depth && angle < options.loop_max_angle_deg)
      candidates.push_back({distance / mean_depth + angle / options.loop_max_angle_deg, j});
  }
  std::sort(candidates.begin(), candidates.end());
  if (static_cast<int>(candidates.size()) > options.loop_max_candidates) candidates.resize(options.loop_max_candidates);
  // A candidate waits for the adjustment still running (keyframe_adjustment_max_wait_ms): the alignment
  // and the pose graph start from the adjusted poses.
  if (!candidates.empty()) ApplyPendingAdjustment();
  bool added = false;
  for (const auto& [score, j] : candidates) {
    Sim3d j_from_k;
    std::string why;
    if (!AlignKeyframes(j, index, &j_from_k, &why)) {
      PRISM_LOG(INFO) << "slam: no loop edge " << j << " - " << index << ": " << why;
      continue;
    }
    PoseGraphEdge edge;
    edge.from = j;
    edge.to = index;
    edge.from_from_to = j_from_k;
    edge.rotation_sigma = options.loop_rotation_sigma;
    edge.translation_sigma = options.loop_translation_sigma;
    edge.log_scale_sigma = options.loop_log_scale_sigma;
    graph_edges.push_back(edge);
    ++loop_closures;
    added = true;
    PRISM_LOG(INFO) << "slam: loop edge keyframe " << j << " - " << index << ", unit ratio " << 1.0 / j_from_k.scale;
  }
  if (!added) return;
  std::vector<Sim3d> nodes;
  for (const Keyframe& k : keyframes) nodes.push_back(k.world_from_keyframe);
  StatusOr<PoseGraphSummary> summary = OptimisePoseGraph(graph_edges, PoseGraphOptions(), &nodes);
  if (!summary.ok()) {
    PRISM_LOG(WARNING) << "slam: pose graph: " << summary.status();
    return;
  }
  for (size_t i = 0; i < keyframes.size(); ++i) keyframes[i].world_from_keyframe = nodes[i];
  // Poses of tracked frames follow their keyframes.
  for (FrameRecord& f : frames)
    if (f.result.state == SlamState::kTracking && f.result.keyframe_id >= 0)
      f.result.world_from_camera = WorldFromFrame(f);
  PRISM_LOG(INFO) << "slam: pose graph " << keyframes.size() << " keyframes, " << graph_edges.size() << " edges, cost "
                  << summary->initial_cost << " -> " << summary->final_cost << " in " << summary->iterations
                  << " iterations";
}

double SlamSystem::Impl::DepthOverlap(int k, int j) const {
  const Keyframe& a = keyframes[static_cast<size_t>(k)];
  if (!a.finished) return 1.0;
  return DepthOverlapFraction(rig.camera, a.final_depth.inverse_depth, a.world_from_keyframe,
                              keyframes[static_cast<size_t>(j)].world_from_keyframe, 8);
}

int SlamSystem::Impl::WindowStart(int first) const {
  const int n = static_cast<int>(keyframes.size());
  if (options.keyframe_window_min_overlap <= 0) return first;
  while (n - first > 3 && DepthOverlap(first, n - 1) < options.keyframe_window_min_overlap) ++first;
  return first;
}

void SlamSystem::Impl::RepropagateNewestKeyframe() {
  const int n = static_cast<int>(keyframes.size());
  std::unique_ptr<KeyframeDepth> source = std::move(previous_depth);
  if (!source || previous_depth_kf != n - 2 || n < 2) return;
  Keyframe& reference = keyframes[static_cast<size_t>(n - 2)];
  Keyframe& newest = keyframes[static_cast<size_t>(n - 1)];
  // The adjusted relative pose, in the reference keyframe's depth units.
  const Sim3d& a = reference.world_from_keyframe;
  const Sim3d& b = newest.world_from_keyframe;
  const Eigen::Quaterniond a_inv = a.rotation.conjugate();
  const Rigid3d reference_from_newest(a_inv * b.rotation, a_inv * (b.translation - a.translation) / a.scale);
  // current_depth is the newest keyframe's (propagated into it along the tracked pose): its image parts
  // are reused.
  const KeyframeDepth* blank = current_depth && current_depth->HasImage(newest.rgb) ? current_depth.get() : nullptr;
  StatusOr<KeyframeDepth> kd = PropagateForTracking(newest.rgb, *source, reference_from_newest.Inverse(), blank);
  if (!kd.ok()) {
    // Keep the depth propagated along the tracked pose; restore the tracker's copy of it.
    if (!RefreshTracker().ok()) {
      PRISM_LOG(WARNING) << "slam: tracker refresh failed after re-propagation";
    }
    return;
  }
  current_depth = std::make_unique<KeyframeDepth>(std::move(kd).value());
  newest.world_from_keyframe.scale = a.scale;
  for (PoseGraphEdge& e : graph_edges) {
    if (e.from == n - 2 && e.to == n - 1) e.from_from_to = a.Inverse() * newest.world_from_keyframe;
  }
}

}  // namespace prism
