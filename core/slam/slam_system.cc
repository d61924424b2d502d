#include "core/slam/slam_system.h"

#include <algorithm>
#include <chrono>
#include <sstream>

#include "core/slam/shading_scale.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace slam_internal {

SlamTrackingQuality QualityOf(const TrackingResult& tr, bool retried, const Rigid3d& guess,
                              const Rigid3d& previous_from_keyframe, double mean_idepth) {
  SlamTrackingQuality q;
  q.tracked = true;
  q.residual_rms = tr.residual_rms;
  q.visible_fraction = tr.visible_fraction;
  q.inlier_fraction = tr.inlier_fraction;
  for (int n : tr.iterations) q.iterations += n;
  q.retried = retried;
  const Rigid3d frame_from_previous = tr.frame_from_keyframe * previous_from_keyframe.Inverse();
  q.step = frame_from_previous.translation.norm() * mean_idepth;
  q.rotation_deg = RotationAngle(frame_from_previous.rotation) * kRadToDeg;
  q.guess_correction = (tr.frame_from_keyframe.translation - guess.translation).norm() * mean_idepth;
  return q;
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

bool AllPointLights(const RigCalibration& rig) {
  for (const Light& l : rig.lights)
    if (l.type != LightType::kPoint || !(l.intensity > 0)) return false;
  return true;
}

double PairSpread(std::vector<double> estimates) {
  if (estimates.empty()) return 0;
  std::sort(estimates.begin(), estimates.end());
  const size_t n = estimates.size();
  const double median = estimates[n / 2];
  return (estimates[std::min((3 * n) / 4, n - 1)] - estimates[n / 4]) / median;
}

std::vector<std::pair<int, double>> PairScales(const RigCalibration& rig, const std::vector<ShadingPair>& pairs,
                                               ThreadPool* pool) {
  const ShadingScaleOptions so;
  std::vector<double> scales(pairs.size(), 0.0);
  std::vector<char> found(pairs.size(), 0);
  const auto one = [&](std::ptrdiff_t i) {
    const ShadingPair& p = pairs[static_cast<size_t>(i)];
    const std::vector<ShadingScaleFrame> frames = {
        {p.newer_rgb, BFromAInUnitsOfA(p.world_from_older, p.world_from_newer)}};
    StatusOr<ShadingScaleResult> r = EstimateShadingScale(rig, p.older_rgb, p.older_inverse_depth, frames, so);
    if (!r.ok()) return;
    scales[static_cast<size_t>(i)] = r->metres_per_unit / p.world_from_older.scale;
    found[static_cast<size_t>(i)] = 1;
  };
  if (pool && pool->num_threads() > 1 && pairs.size() > 1) {
    pool->ParallelFor(0, static_cast<std::ptrdiff_t>(pairs.size()), one);
  } else {
    for (size_t i = 0; i < pairs.size(); ++i) one(static_cast<std::ptrdiff_t>(i));
  }
  std::vector<std::pair<int, double>> estimates;
  for (size_t i = 0; i < pairs.size(); ++i)
    if (found[i]) estimates.emplace_back(pairs[i].older, scales[i]);
  return estimates;
}

}  // namespace slam_internal

using slam_internal::AllPointLights;
using slam_internal::ScopedSeconds;

namespace {

// The rig has a light with an intensity (it moves with the camera).
bool AnyLight(const RigCalibration& rig) {
  for (const Light& l : rig.lights)
    if (l.intensity > 0) return true;
  return false;
}

}  // namespace

Status SlamOptions::Check() const {
  PRISM_RETURN_IF_ERROR(tracker.Check());
  PRISM_RETURN_IF_ERROR(wide_baseline_tracker.Check());
  PRISM_RETURN_IF_ERROR(depth.Check());
  if (!(keyframe_distance_fraction > 0))
    return InvalidArgumentError("SlamOptions: keyframe_distance_fraction must be > 0");
  if (!(keyframe_min_visible_fraction >= 0 && keyframe_min_visible_fraction <= 1))
    return InvalidArgumentError("SlamOptions: keyframe_min_visible_fraction must be in [0, 1]");
  if (!(keyframe_max_rotation_deg > 0))
    return InvalidArgumentError("SlamOptions: keyframe_max_rotation_deg must be > 0");
  if (init_min_frames < 2) return InvalidArgumentError("SlamOptions: init_min_frames must be >= 2");
  if (init_rounds < 1 || init_rounds > 10) return InvalidArgumentError("SlamOptions: init_rounds must be in [1, 10]");
  if (init_threads < 1 || init_threads > 64)
    return InvalidArgumentError("SlamOptions: init_threads must be in [1, 64]");
  if (!(init_min_parallax_fraction > 0))
    return InvalidArgumentError("SlamOptions: init_min_parallax_fraction must be > 0");
  if (init_max_frames < init_min_frames)
    return InvalidArgumentError("SlamOptions: init_max_frames must be >= init_min_frames");
  if (!(init_min_feature_local_mean >= 0 && init_min_feature_local_mean <= 255))
    return InvalidArgumentError("SlamOptions: init_min_feature_local_mean must be in [0, 255]");
  if (relocalise_max_keyframes < 1) return InvalidArgumentError("SlamOptions: relocalise_max_keyframes must be >= 1");
  if (!(new_pixel_relative_sigma > 0)) return InvalidArgumentError("SlamOptions: new_pixel_relative_sigma must be > 0");
  if (tracker_refresh_frames < 1) return InvalidArgumentError("SlamOptions: tracker_refresh_frames must be >= 1");
  if (depth_update_interval < 1) return InvalidArgumentError("SlamOptions: depth_update_interval must be >= 1");
  if (!(mapping_budget_ms >= 0)) return InvalidArgumentError("SlamOptions: mapping_budget_ms must be >= 0");
  if (loop_min_keyframe_gap < 2) return InvalidArgumentError("SlamOptions: loop_min_keyframe_gap must be >= 2");
  if (!(loop_max_distance_fraction > 0))
    return InvalidArgumentError("SlamOptions: loop_max_distance_fraction must be > 0");
  if (!(loop_max_angle_deg > 0 && loop_max_angle_deg <= 180))
    return InvalidArgumentError("SlamOptions: loop_max_angle_deg must be in (0, 180]");
  if (loop_max_candidates < 1) return InvalidArgumentError("SlamOptions: loop_max_candidates must be >= 1");
  if (!(loop_max_rotation_inconsistency_deg > 0))
    return InvalidArgumentError("SlamOptions: loop_max_rotation_inconsistency_deg must be > 0");
  if (loop_min_depth_matches < 10) return InvalidArgumentError("SlamOptions: loop_min_depth_matches must be >= 10");
  for (double sigma : {odometry_rotation_sigma, odometry_translation_sigma, odometry_log_scale_sigma,
                       loop_rotation_sigma, loop_translation_sigma, loop_log_scale_sigma})
    if (!(sigma > 0)) return InvalidArgumentError("SlamOptions: pose-graph sigmas must be > 0");
  if (!(max_step_rotation_deg > 0) || !(max_step_translation_fraction > 0))
    return InvalidArgumentError("SlamOptions: max_step_rotation_deg and max_step_translation_fraction must be > 0");
  if (keyframe_window < 3) return InvalidArgumentError("SlamOptions: keyframe_window must be >= 3");
  if (keyframe_window_cell_px < 4) return InvalidArgumentError("SlamOptions: keyframe_window_cell_px must be >= 4");
  if (!(keyframe_window_min_overlap >= 0 && keyframe_window_min_overlap <= 1))
    return InvalidArgumentError("SlamOptions: keyframe_window_min_overlap must be in [0, 1]");
  if (keyframe_window_min_points < 10)
    return InvalidArgumentError("SlamOptions: keyframe_window_min_points must be >= 10");
  if (keyframe_adjustment_interval < 1)
    return InvalidArgumentError("SlamOptions: keyframe_adjustment_interval must be >= 1");
  PRISM_RETURN_IF_ERROR(keyframe_window_ba.Check());
  if (final_adjustment_max_keyframes < 3)
    return InvalidArgumentError("SlamOptions: final_adjustment_max_keyframes must be >= 3");
  if (feature_adjustment_max_keyframes < 3)
    return InvalidArgumentError("SlamOptions: feature_adjustment_max_keyframes must be >= 3");
  if (final_refinement_neighbours < 0 || final_refinement_neighbours > 5)
    return InvalidArgumentError("SlamOptions: final_refinement_neighbours must be in [0, 5]");
  if (!(final_refinement_relative_sigma > 0))
    return InvalidArgumentError("SlamOptions: final_refinement_relative_sigma must be > 0");
  if (final_refinement_rounds < 1 || final_refinement_rounds > 10)
    return InvalidArgumentError("SlamOptions: final_refinement_rounds must be in [1, 10]");
  PRISM_RETURN_IF_ERROR(final_adjustment_ba.Check());
  PRISM_RETURN_IF_ERROR(feature_adjustment.Check());
  if (!(feature_adjustment_min_overlap >= 0 && feature_adjustment_min_overlap <= 1))
    return InvalidArgumentError("SlamOptions: feature_adjustment_min_overlap must be in [0, 1]");
  PRISM_RETURN_IF_ERROR(final_adjustment_relit_ba.Check());
  if (!(metric_scale_max_pair_spread > 0))
    return InvalidArgumentError("SlamOptions: metric_scale_max_pair_spread must be > 0");
  if (start_check_keyframes != 0 && start_check_keyframes < 4)
    return InvalidArgumentError("SlamOptions: start_check_keyframes must be 0 (off) or >= 4");
  if (!(start_check_max_pair_spread > 0) || !(start_check_retry_parallax_fraction > 0))
    return InvalidArgumentError(
        "SlamOptions: start_check_max_pair_spread and start_check_retry_parallax_fraction must be > 0");
  if (start_check_max_frames < 1) return InvalidArgumentError("SlamOptions: start_check_max_frames must be >= 1");
  if (start_check_window_cell_px < 4)
    return InvalidArgumentError("SlamOptions: start_check_window_cell_px must be >= 4");
  if (!(metric_scale_min_band_fraction >= 0 && metric_scale_min_band_fraction < 1))
    return InvalidArgumentError("SlamOptions: metric_scale_min_band_fraction must be in [0, 1)");
  if (!(final_adjustment_mixed_relit_scale > 0))
    return InvalidArgumentError("SlamOptions: final_adjustment_mixed_relit_scale must be > 0");
  if (final_adjustment_mixed && final_adjustment_ba.pyramid_levels != 1)
    return InvalidArgumentError("SlamOptions: final_adjustment_mixed needs final_adjustment_ba.pyramid_levels = 1");
  if (final_adjustment_relit && final_adjustment_relit_ba.pyramid_levels != 1)
    return InvalidArgumentError("SlamOptions: final_adjustment_relit_ba.pyramid_levels must be 1");
  return Status::Ok();
}

const char* SlamStateName(SlamState state) {
  switch (state) {
    case SlamState::kInitializing:
      return "initializing";
    case SlamState::kTracking:
      return "tracking";
    case SlamState::kLost:
      return "lost";
  }
  return "unknown";
}

StatusOr<std::unique_ptr<SlamSystem::Impl>> SlamSystem::NewImpl(const RigCalibration& rig, const SlamOptions& options,
                                                                ThreadPool* pool) {
  auto impl = std::make_unique<Impl>();
  impl->rig = rig;
  impl->options = options;
  impl->pool = pool;
  // Without lights on the rig (KITTI: daylight) the settings that target the co-moving lights' effects are
  // off: the camera-attached tests (only false alarms there), the initialisation's KLT on J (raw grey tracks
  // better), the final adjustment's gradient weight and the local mean's edge test (the pattern moves with
  // the scene).
  if (!AnyLight(rig)) {
    impl->options.tracker.camera_attached_min_votes = 0;
    impl->options.depth.camera_attached_min_votes = 0;
    impl->options.depth.max_local_mean_log_gradient = 0;
    impl->options.init_track_normalised = false;
    impl->options.init_min_feature_local_mean = 0;
    impl->options.final_adjustment_ba.gradient_weight_c = 0;
  }
  PRISM_ASSIGN_OR_RETURN(Tracker t, Tracker::Create(rig, impl->options.tracker));
  impl->tracker = std::make_unique<Tracker>(std::move(t));
  // The wide-baseline tracker's extra level is dropped on images too small for it (coarsest side >= 8).
  TrackerOptions wide = options.wide_baseline_tracker;
  while (wide.pyramid_levels > options.tracker.pyramid_levels &&
         std::min(rig.camera.width, rig.camera.height) >> (wide.pyramid_levels - 1) < 8)
    --wide.pyramid_levels;
  PRISM_ASSIGN_OR_RETURN(Tracker r, Tracker::Create(rig, wide));
  impl->reloc_tracker = std::make_unique<Tracker>(std::move(r));
  PRISM_ASSIGN_OR_RETURN(Tracker l, Tracker::Create(rig, wide));
  impl->loop_tracker = std::make_unique<Tracker>(std::move(l));
  TrackerOptions init_options = impl->options.tracker;
  init_options.max_residual_rms *= options.init_residual_factor;
  PRISM_ASSIGN_OR_RETURN(Tracker it, Tracker::Create(rig, init_options));
  impl->init_tracker = std::make_unique<Tracker>(std::move(it));
  return impl;
}

StatusOr<std::unique_ptr<SlamSystem>> SlamSystem::Create(const RigCalibration& rig, const SlamOptions& options,
                                                         ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.camera.Check());
  if (rig.camera.HasDistortion())
    return InvalidArgumentError("SlamSystem: undistort the images first (camera has distortion)");
  PRISM_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, NewImpl(rig, options, pool));
  std::unique_ptr<SlamSystem> slam(new SlamSystem(std::move(impl)));
  if (options.start_check_keyframes > 0 && rig.lights.size() == 3 && AllPointLights(rig))
    slam->start_check_ = std::make_unique<StartCheck>();
  return slam;
}

SlamSystem::SlamSystem(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
SlamSystem::~SlamSystem() = default;

StatusOr<SlamFrameResult> SlamSystem::ProcessFrame(double timestamp, const cv::Mat& rgb, bool skip_depth_update) {
  const PinholeCamera& cam = impl_->rig.camera;
  if (rgb.type() != CV_8UC3 || rgb.cols != cam.width || rgb.rows != cam.height) {
    std::ostringstream m;
    m << "SlamSystem::ProcessFrame: expected a CV_8UC3 image of " << cam.width << "x" << cam.height << ", got "
      << rgb.cols << "x" << rgb.rows << " type " << rgb.type();
    return InvalidArgumentError(m.str());
  }
  impl_->skip_depth_update = skip_depth_update;
  impl_->start_check_running = start_check_ != nullptr;
  StatusOr<SlamFrameResult> r = impl_->Process(timestamp, rgb);
  impl_->skip_depth_update = false;
  if (start_check_) StepStartCheck(timestamp, rgb, &r);
  return r;
}

StatusOr<SlamFrameResult> SlamSystem::Impl::Process(double timestamp, const cv::Mat& rgb) {
  const int64_t frame_id = static_cast<int64_t>(frames.size());
  if (!initialized) {
    const ScopedSeconds timer(&timings.initialisation);
    return Initialise(frame_id, timestamp, rgb);
  }
  return TrackFrame(frame_id, timestamp, rgb);
}

std::vector<SlamFrameResult> SlamSystem::Trajectory() const {
  std::vector<SlamFrameResult> out;
  out.reserve(impl_->frames.size());
  for (const Impl::FrameRecord& f : impl_->frames) {
    SlamFrameResult r = f.result;
    if (r.state == SlamState::kTracking && r.keyframe_id >= 0) r.world_from_camera = impl_->WorldFromFrame(f);
    out.push_back(std::move(r));
  }
  return out;
}

PointCloud SlamSystem::SemiDenseCloud() const {
  PointCloud cloud;
  const PinholeCamera& cam = impl_->rig.camera;
  for (const Impl::Keyframe& k : impl_->keyframes) {
    InverseDepthMap depth =
        k.finished ? k.final_depth
                   : (impl_->current_depth ? impl_->current_depth->ToInverseDepthMap() : InverseDepthMap());
    if (depth.inverse_depth.empty()) continue;
    for (int y = 0; y < cam.height; ++y) {
      const float* d = depth.inverse_depth.ptr<float>(y);
      const uint8_t* c = k.rgb.ptr<uint8_t>(y);
      for (int x = 0; x < cam.width; ++x) {
        if (!(d[x] > 0)) continue;
        const Eigen::Vector3d p = cam.Unproject(Eigen::Vector2d(x, y)) / d[x];
        cloud.positions.push_back((k.world_from_keyframe * p).cast<float>());
        cloud.colors.push_back(Eigen::Matrix<uint8_t, 3, 1>(c[3 * x], c[3 * x + 1], c[3 * x + 2]));
      }
    }
  }
  return cloud;
}

int SlamSystem::num_keyframes() const { return static_cast<int>(impl_->keyframes.size()); }

int SlamSystem::num_loop_closures() const { return impl_->loop_closures; }

int SlamSystem::num_keyframe_adjustments() const {
  // The one running on its own thread counts (it is applied before anything reads its result).
  return impl_->keyframe_adjustments + (impl_->pending_adjustment ? 1 : 0) + (impl_->adjustment_owed ? 1 : 0);
}

SlamTimings SlamSystem::timings() const { return impl_->timings; }

FeatureAdjustmentReport SlamSystem::feature_adjustment() const { return impl_->feature_report; }

std::vector<Sim3d> SlamSystem::KeyframePoses() const {
  std::vector<Sim3d> out;
  for (const Impl::Keyframe& k : impl_->keyframes) out.push_back(k.world_from_keyframe);
  return out;
}

}  // namespace prism
