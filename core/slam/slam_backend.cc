// SlamSystem's back end: the keyframe pairs' shading scales and the keyframe adjustments (direct and by
// features).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <future>
#include <string>

#include "core/slam/slam_system.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"

namespace prism {

using slam_internal::AllPointLights;
using slam_internal::PairScales;
using slam_internal::ScopedSeconds;
using slam_internal::SecondsSince;
using slam_internal::ShadingPair;

std::vector<ShadingPair> SlamSystem::Impl::ShadingPairs(size_t num_keyframes, bool own_depth) const {
  std::vector<ShadingPair> pairs;
  for (size_t k = 0; k + 1 < std::min(num_keyframes, keyframes.size()); ++k) {
    const Keyframe& a = keyframes[k];
    const Keyframe& b = keyframes[k + 1];
    if (!a.finished || a.final_depth.inverse_depth.empty()) continue;
    ShadingPair p;
    p.older = static_cast<int>(k);
    p.older_rgb = a.rgb;
    p.older_inverse_depth = own_depth ? a.final_depth.inverse_depth.clone() : a.final_depth.inverse_depth;
    p.newer_rgb = b.rgb;
    p.world_from_older = a.world_from_keyframe;
    p.world_from_newer = b.world_from_keyframe;
    pairs.push_back(std::move(p));
  }
  return pairs;
}

std::vector<double> SlamSystem::Impl::PairShadingScales(size_t num_keyframes) const {
  std::vector<double> estimates;
  if (!AllPointLights(rig)) return estimates;
  for (const auto& [k, scale] : PairScales(rig, ShadingPairs(num_keyframes, /*own_depth=*/false), pool))
    estimates.push_back(scale);
  return estimates;
}

double SlamSystem::Impl::RelitMetresPerWorldUnit() {
  if (relit_metres_per_world_unit != 0) return relit_metres_per_world_unit;
  relit_metres_per_world_unit = -1;
  if (!AllPointLights(rig)) return -1;
  std::vector<double> estimates = PairShadingScales(keyframes.size());
  if (estimates.size() < 3) {
    PRISM_LOG(INFO) << "slam: relit adjustment off: " << estimates.size() << " keyframe pairs gave a shading scale";
    return -1;
  }
  relit_pair_estimates = estimates;
  std::nth_element(estimates.begin(), estimates.begin() + estimates.size() / 2, estimates.end());
  relit_metres_per_world_unit = estimates[estimates.size() / 2];
  PRISM_LOG(INFO) << "slam: relit adjustment at " << relit_metres_per_world_unit << " metres per world unit ("
                  << estimates.size() << " keyframe pairs)";
  return relit_metres_per_world_unit;
}

bool SlamSystem::Impl::BuildAdjustmentProblem(int first, bool relit, bool mixed, double metres_per_world_unit,
                                              double min_band_fraction, DirectBaProblem* problem) {
  const int n = static_cast<int>(keyframes.size());
  problem->camera = rig.camera;
  std::vector<InverseDepthMap> maps;
  for (int k = first; k < n; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    problem->world_from_keyframe.push_back(kf.world_from_keyframe);
    if (kf.grey_j.empty()) {
      cv::Mat mean;
      KeyframeDepth::NormalisedGrey(kf.rgb, options.depth, &kf.grey_j, &mean);
    }
    problem->grey_j.push_back(kf.grey_j);
    // The newest keyframe's depth is the one propagated into it.
    maps.push_back(kf.finished ? kf.final_depth : current_depth->ToInverseDepthMap());
  }
  // Points: per cell, the strongest gradient with a converged inverse depth.
  const int cell_px = WindowCellPx();
  for (int k = 0; k < n - first; ++k) {
    const cv::Mat& d = maps[static_cast<size_t>(k)].inverse_depth;
    const cv::Mat& var = maps[static_cast<size_t>(k)].variance;
    if (d.empty()) continue;
    Keyframe& kf = keyframes[static_cast<size_t>(first + k)];
    if (kf.finished && kf.window_points_cell_px == cell_px) {
      for (DirectBaPoint p : kf.window_points) {
        p.host = k;
        problem->points.push_back(p);
      }
      continue;
    }
    const size_t begin = problem->points.size();
    const double max_sigma = options.tracking_max_relative_sigma;
    SelectCellPoints(
        problem->grey_j[static_cast<size_t>(k)], d, k, cell_px, 0.0f,
        [&](int x, int y) { return var.empty() || std::sqrt(var.at<float>(y, x)) <= max_sigma * d.at<float>(y, x); },
        &problem->points);
    if (kf.finished) {
      kf.window_points.assign(problem->points.begin() + static_cast<std::ptrdiff_t>(begin), problem->points.end());
      for (DirectBaPoint& p : kf.window_points) p.host = 0;
      kf.window_points_cell_px = cell_px;
    }
  }
  if (static_cast<int>(problem->points.size()) < options.keyframe_window_min_points) return false;
  if (relit && mixed) {
    // J stays; every point is also a relit point (the adjustment computes the raw grey levels).
    const size_t num_j = problem->points.size();
    for (size_t i = 0; i < num_j; ++i) {
      DirectBaPoint p = problem->points[i];
      p.relit = true;
      problem->points.push_back(p);
    }
    for (int k = first; k < n; ++k) problem->relit.rgb.push_back(keyframes[static_cast<size_t>(k)].rgb);
    problem->relit.mixed = true;
    problem->relit.relit_residual_scale = options.final_adjustment_mixed_relit_scale;
  } else if (relit) {
    // The raw grey level of every keyframe and the hosts' colours (the points stay those J selected).
    for (int k = first; k < n; ++k) {
      const cv::Mat& rgb = keyframes[static_cast<size_t>(k)].rgb;
      problem->grey_j[static_cast<size_t>(k - first)] = MeanOfChannels(rgb);
      problem->relit.rgb.push_back(rgb);
    }
  }
  if (relit) {
    problem->relit.rig = &rig;
    problem->relit.metres_per_world_unit = metres_per_world_unit;
    problem->relit.estimate_metres_per_world_unit = true;
    problem->relit.min_band_fraction = min_band_fraction;
  }
  return true;
}

void SlamSystem::Impl::AdjustKeyframes(int first, const DirectBaOptions& ba_options, bool at_finish) {
  ApplyPendingAdjustment();
  const int n = static_cast<int>(keyframes.size());
  if (n - first < 3 || !current_depth) return;
  // Keyframes that left the window are not adjusted again until the final adjustment (which recomputes
  // them): drop their normalised images (1 MB each at 512x512, which would otherwise grow with the
  // session).
  for (int k = 0; k < first; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    kf.grey_j.release();
    kf.DropWindowPoints();
  }
  const bool mixed = at_finish && options.final_adjustment_mixed && RelitMetresPerWorldUnit() > 0;
  const bool relit = mixed || (at_finish && options.final_adjustment_relit && RelitMetresPerWorldUnit() > 0);
  auto job = std::make_unique<PendingAdjustment>();
  job->first = first;
  job->num_keyframes = n;
  job->at_finish = at_finish;
  job->relit = relit;
  job->mixed = mixed;
  DirectBaProblem& problem = job->problem;
  if (!BuildAdjustmentProblem(first, relit, mixed, relit_metres_per_world_unit,
                              mixed ? options.metric_scale_min_band_fraction : DirectBaRelit().min_band_fraction,
                              &problem))
    return;
  const DirectBaOptions used_options = relit && !mixed ? options.final_adjustment_relit_ba : ba_options;
  job->initial_inverse_depth.reserve(problem.points.size());
  for (const DirectBaPoint& p : problem.points) job->initial_inverse_depth.push_back(p.inverse_depth);
  if (AdjustAsync() && !at_finish) {
    // The problem holds its own copies (the images are shared, read-only): the thread touches nothing
    // else. One thread, no pool: the result is the same to the bit as with the pool (keyframe_ba.h).
    PendingAdjustment* p = job.get();
    job->done = std::async(std::launch::async, [p, used_options] {
      SetCurrentThreadName("slam-adjust");
      const auto start = std::chrono::steady_clock::now();
      p->summary = AdjustKeyframeWindowDirect(used_options, &p->problem, nullptr);
      p->seconds = SecondsSince(start);
    });
    pending_adjustment = std::move(job);
    return;
  }
  job->summary = AdjustKeyframeWindowDirect(used_options, &problem, pool);
  ApplyAdjustment(job.get());
}

bool SlamSystem::Impl::ApplyPendingAdjustment(double max_wait_ms) {
  if (!pending_adjustment) return true;
  if (max_wait_ms >= 0) {
    const ScopedSeconds wait(&timings.keyframe_adjustment_wait);
    const auto bound = std::chrono::duration<double, std::milli>(max_wait_ms);
    if (pending_adjustment->done.wait_for(bound) != std::future_status::ready) return false;
  }
  std::unique_ptr<PendingAdjustment> job = std::move(pending_adjustment);
  {
    const ScopedSeconds wait(&timings.keyframe_adjustment_wait);
    job->done.get();  // rethrows what the thread threw
  }
  timings.keyframe_adjustment_thread += job->seconds;
  ApplyAdjustment(job.get());
  return true;
}

void SlamSystem::Impl::PollPendingAdjustment() {
  if (pending_adjustment && pending_adjustment->done.wait_for(std::chrono::seconds(0)) == std::future_status::ready)
    ApplyPendingAdjustment();
  if (adjustment_owed && !pending_adjustment) {
    const ScopedSeconds adjustment_timer(&timings.keyframe_adjustment);
    StartOwedAdjustment();
  }
}

void SlamSystem::Impl::ApplyAdjustment(PendingAdjustment* job) {
  const int first = job->first;
  const int n = job->num_keyframes;
  const bool at_finish = job->at_finish, relit = job->relit, mixed = job->mixed;
  const DirectBaProblem& problem = job->problem;
  const std::vector<float>& initial_inverse_depth = job->initial_inverse_depth;
  // Keyframes made while the adjustment ran (keyframe_adjustment_max_wait_ms) follow its newest keyframe.
  if (static_cast<int>(keyframes.size()) < n) {
    PRISM_LOG(WARNING) << "slam: keyframe adjustment over " << n << " keyframes dropped: there are now "
                       << keyframes.size();
    return;
  }
  const Sim3d newest_before = keyframes[static_cast<size_t>(n - 1)].world_from_keyframe;
  if (at_finish)
    for (Keyframe& kf : keyframes) kf.grey_j.release();
  const StatusOr<DirectBaSummary>& summary = job->summary;
  if (relit && summary.ok()) {
    PRISM_LOG(INFO) << "slam: relit adjustment: " << relit_metres_per_world_unit << " -> "
                    << problem.relit.metres_per_world_unit << " metres per world unit";
    relit_metres_per_world_unit = problem.relit.metres_per_world_unit;
  }
  if (!summary.ok()) {
    PRISM_LOG(WARNING) << "slam: keyframe adjustment: " << summary.status();
    return;
  }
  // Each adjusted keyframe keeps its depth map; its depth unit follows the adjusted inverse depths of the
  // points it hosts (median ratio).
  // The oldest keeps its pose (the gauge) and with refit_oldest_keyframe_scale has its unit re-fitted too.
  const int first_refitted = options.refit_oldest_keyframe_scale ? first : first + 1;
  for (int k = first_refitted; k < n; ++k) {
    Sim3d pose = problem.world_from_keyframe[static_cast<size_t>(k - first)];
    std::vector<double> ratios;
    for (size_t i = 0; i < problem.points.size(); ++i) {
      const DirectBaPoint& p = problem.points[i];
      // (Mixed: the J points alone; the keyframe's depth map is J's.)
      if (p.host == k - first && p.ok && !(mixed && p.relit))
        ratios.push_back(initial_inverse_depth[i] / p.inverse_depth);
    }
    if (ratios.size() >= 20) {
      std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
      pose.scale *= ratios[ratios.size() / 2];
    }
    keyframes[static_cast<size_t>(k)].world_from_keyframe = pose;
  }
  // Made at the newest one's pose before the adjustment: moved as it moved.
  const Sim3d newest_move = keyframes[static_cast<size_t>(n - 1)].world_from_keyframe * newest_before.Inverse();
  for (size_t k = static_cast<size_t>(n); k < keyframes.size(); ++k)
    keyframes[k].world_from_keyframe = newest_move * keyframes[k].world_from_keyframe;
  if (options.repropagate_after_adjustment && !at_finish) {
    FollowKeyframes(first_refitted, static_cast<int>(keyframes.size()));  // the edges, before the re-propagation
    RepropagateNewestKeyframe();
  }
  // The frames of the oldest keyframe move too when its next keyframe moved (distribute_keyframe_corrections).
  FollowKeyframes(first_refitted, options.distribute_keyframe_corrections ? first : first_refitted);
  ++keyframe_adjustments;
  PRISM_LOG(DEBUG) << "slam: " << (at_finish ? "final" : "keyframe") << " adjustment " << first << ".." << n - 1 << ": "
                   << problem.points.size() << " points, " << summary->residuals << " residuals, RMS "
                   << summary->initial_rms << " -> " << summary->final_rms << " in " << summary->iterations
                   << " iterations";
}

void SlamSystem::Impl::FollowKeyframes(int first_edge, int first_moved) {
  // The odometry edges follow (a later loop closure starts from the adjusted chain), as do the frames.
  for (PoseGraphEdge& e : graph_edges) {
    if (e.to - e.from != 1 || e.to < first_edge) continue;
    e.from_from_to = keyframes[static_cast<size_t>(e.from)].world_from_keyframe.Inverse() *
                     keyframes[static_cast<size_t>(e.to)].world_from_keyframe;
  }
  for (FrameRecord& f : frames)
    if (f.result.state == SlamState::kTracking && f.result.keyframe_id >= first_moved)
      f.result.world_from_camera = WorldFromFrame(f);
}

void SlamSystem::Impl::AdjustByFeatures() {
  ApplyPendingAdjustment();
  const int n = static_cast<int>(keyframes.size());
  if (!options.final_feature_adjustment || !(CanAdjustAllKeyframes() || CanAdjustByFeaturesAlone()) || n < 3) return;
  if (feature_tracks_failed_for == n) return;  // the same keyframes' images gave no tracks: not again
  const auto start = std::chrono::steady_clock::now();
  feature_report.ran = true;
  ++feature_report.runs;
  // The tracks depend on the images alone: built once for these keyframes (RefineKeyframeDepths' rounds
  // adjust the same keyframes again).
  if (!feature_tracks || feature_tracks->num_keyframes != n) {
    std::vector<FeatureImage> images(static_cast<size_t>(n));
    std::vector<Sim3d> poses;
    for (const Keyframe& kf : keyframes) poses.push_back(kf.world_from_keyframe);
    auto prepare = [&](std::ptrdiff_t k) {
      FeatureImage& in = images[static_cast<size_t>(k)];
      KeyframeDepth::NormalisedGrey(keyframes[static_cast<size_t>(k)].rgb, options.depth, &in.grey_j, &in.local_mean);
    };
    if (pool) pool->ParallelFor(0, n, prepare);
    else
      for (int k = 0; k < n; ++k) prepare(k);
    const double min_overlap = options.feature_adjustment_min_overlap;
    StatusOr<FeatureTracks> tracks = BuildFeatureTracks(
        rig.camera, options.feature_adjustment, images, poses, pool,
        [&](int a, int b) { return DepthOverlap(a, b) >= min_overlap || DepthOverlap(b, a) >= min_overlap; });
    feature_report.tracks_seconds = SecondsSince(start);
    if (!tracks.ok()) {
      feature_report.seconds += SecondsSince(start);
      feature_report.applied = false;
      feature_report.error = std::string(tracks.status().message());
      feature_tracks_failed_for = n;
      PRISM_LOG(WARNING) << "slam: feature adjustment not applied: " << tracks.status();
      return;
    }
    feature_tracks = std::make_unique<FeatureTracks>(std::move(tracks).value());
    feature_report.pairs_tried = feature_tracks->pairs_tried;
  }
  std::vector<Sim3d> adjusted;
  for (const Keyframe& kf : keyframes) adjusted.push_back(kf.world_from_keyframe);
  StatusOr<FeatureAdjustmentSummary> summary =
      AdjustKeyframesByFeatures(rig.camera, options.feature_adjustment, *feature_tracks, &adjusted);
  feature_report.seconds += SecondsSince(start);
  if (!summary.ok()) {
    feature_report.applied = false;
    feature_report.error = std::string(summary.status().message());
    PRISM_LOG(WARNING) << "slam: feature adjustment not applied: " << summary.status();
    return;
  }
  // Each keyframe's depth unit follows the tracks' depths where its depth map has them: a point at depth
  // z_map (the keyframe's units) is at depth scale * z_map in world units.
  int rescaled = 0;
  for (int k = 0; k < n; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    Sim3d pose = adjusted[static_cast<size_t>(k)];
    const cv::Mat& d = kf.final_depth.inverse_depth;
    std::vector<double> ratios;
    if (!d.empty()) {
      for (const FeatureObservation& o : summary->observations_by_keyframe[static_cast<size_t>(k)]) {
        const int x = static_cast<int>(std::lround(o.u)), y = static_cast<int>(std::lround(o.v));
        if (x < 0 || y < 0 || x >= d.cols || y >= d.rows) continue;
        const float rho = d.at<float>(y, x);
        if (rho > 0 && o.depth > 0) ratios.push_back(o.depth * rho);
      }
    }
    if (ratios.size() >= 20) {
      std::nth_element(ratios.begin(), ratios.begin() + static_cast<std::ptrdiff_t>(ratios.size() / 2), ratios.end());
      pose.scale = ratios[ratios.size() / 2];
      ++rescaled;
    }
    kf.world_from_keyframe = pose;
  }
  FollowKeyframes(0, 0);
  feature_report.applied = true;
  feature_report.error.clear();
  feature_report.keyframes_rescaled = rescaled;
  feature_report.summary = std::move(summary).value();
  feature_report.summary.observations_by_keyframe.clear();
  const FeatureAdjustmentSummary& r = feature_report.summary;
  PRISM_LOG(INFO) << "slam: feature adjustment: " << r.features << " features, " << r.pairs_matched << " of "
                  << feature_report.pairs_tried << " pairs matched, " << r.tracks << " tracks (" << r.mean_track_length
                  << " keyframes each), reprojection RMS " << r.initial_rms_px << " -> " << r.final_rms_px
                  << " px (median " << r.initial_median_px << " -> " << r.final_median_px << "), " << r.iterations
                  << " iterations, " << rescaled << " depth units refitted";
}

}  // namespace prism
