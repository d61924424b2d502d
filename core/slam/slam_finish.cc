// SlamSystem's end of the sequence: the last keyframes, the final adjustment, the metric scale and scale
// drift from the lights, and the keyframes' depth refinement.
#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "core/slam/slam_system.h"
#include "core/slam/slam_system_impl.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"

namespace prism {

using slam_internal::AllPointLights;
using slam_internal::kRadToDeg;
using slam_internal::PairSpread;
using slam_internal::ScopedSeconds;

std::vector<SlamKeyframe> SlamSystem::TakeFinishedKeyframes() {
  std::vector<SlamKeyframe> out;
  if (start_check_) return out;  // held until the start check is done
  // With keyframe_adjustment_async, the keyframe finished when the running adjustment was started (the
  // one before its newest) is held until that adjustment has been applied: handed out inline, it would
  // have had it.
  const int held_from = impl_->pending_adjustment ? impl_->pending_adjustment->num_keyframes - 2
                                                  : static_cast<int>(impl_->keyframes.size());
  for (Impl::Keyframe& k : impl_->keyframes) {
    if (!k.finished || k.handed_out || k.id >= held_from) continue;
    SlamKeyframe s;
    s.id = k.id;
    s.frame_id = k.frame_id;
    s.timestamp = k.timestamp;
    s.world_from_keyframe = k.world_from_keyframe;
    s.rgb = k.rgb;
    s.depth = k.final_depth;
    out.push_back(std::move(s));
    k.handed_out = true;
  }
  return out;
}

std::vector<SlamKeyframe> SlamSystem::Finish() {
  std::vector<SlamKeyframe> last = FinishTracking();
  if (impl_->options.final_adjustment) AdjustAllKeyframes();
  return last;
}

std::vector<SlamKeyframe> SlamSystem::FinishTracking() {
  if (start_check_ && impl_->pending_start_check) {
    // The pair scales still on their thread (start_check_async): reported; no second start can run now.
    const ScopedSeconds timer(&start_check_report_.seconds);
    const std::vector<double> first = TakeStartCheckScales();
    if (first.size() >= 3) {
      start_check_report_.checked = true;
      start_check_report_.first_spread = PairSpread(first);
      start_check_report_.passed = start_check_report_.first_spread <= impl_->options.start_check_max_pair_spread;
    }
    PRISM_LOG(INFO) << "slam: start check at Finish: " << first.size() << " keyframe pairs gave a shading scale"
                    << (start_check_report_.checked ? ", spread " + std::to_string(start_check_report_.first_spread)
                                                    : std::string());
  }
  if (start_check_ && start_check_->second_start.valid()) {
    CloseSecondStart(nullptr);  // the frames so far; the second start may still be kept
    impl_->start_check_running = false;
  }
  if (start_check_) {
    PRISM_LOG(INFO) << "slam: start check not done at Finish; the " << (start_check_->retry ? "first " : "")
                    << "start is kept";
    start_check_.reset();
    impl_->start_check_running = false;  // the last keyframe's adjustments as after the check
  }
  impl_->ApplyPendingAdjustment();
  if (impl_->adjustment_owed) {  // keyframe_adjustment_max_wait_ms: the newest keyframe's window adjustment
    impl_->StartOwedAdjustment();
    impl_->ApplyPendingAdjustment();
  }
  if (impl_->current_depth && !impl_->keyframes.empty() && !impl_->keyframes.back().finished) {
    impl_->current_depth->Regularise();
    impl_->FinishCurrent();
    // The last keyframe may close a loop too.
    if (impl_->options.loop_closure) impl_->CloseLoops(static_cast<int>(impl_->keyframes.size()) - 1);
  }
  return TakeFinishedKeyframes();
}

void SlamSystem::AdjustAllKeyframes() {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  if (m.final_adjustment_done) return;
  if (m.CanAdjustAllKeyframes()) {
    m.final_adjustment_done = true;
    m.AdjustKeyframes(0, m.options.final_adjustment_ba, /*at_finish=*/true);
    m.AdjustByFeatures();
  } else if (m.CanAdjustByFeaturesAlone()) {
    m.final_adjustment_done = true;
    m.AdjustByFeatures();
  }
}

SlamStreamEnd SlamSystem::FinishStream(bool metric_scale, std::vector<SlamKeyframe>* refine) {
  SlamStreamEnd end;
  const SlamOptions& o = impl_->options;
  if (o.final_adjustment) {
    const ScopedSeconds timer(&end.adjustment_seconds);
    AdjustAllKeyframes();
  }
  if (refine != nullptr) {
    const ScopedSeconds timer(&end.refinement_seconds);
    RefineKeyframeDepths(o.final_refinement_neighbours, o.final_refinement_relative_sigma, o.final_refinement_rounds,
                         refine);
  }
  if (metric_scale) {
    const ScopedSeconds timer(&end.metric_seconds);
    StatusOr<MetricScaleEstimate> metric = EstimateMetricScale();
    if (metric.ok()) end.metric = *metric;
    else end.metric_error = std::string(metric.status().message());
  }
  return end;
}

StatusOr<MetricScaleEstimate> SlamSystem::EstimateMetricScale() {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  const int n = static_cast<int>(m.keyframes.size());
  if (n < 3 || !m.current_depth || !m.keyframes.back().finished)
    return FailedPreconditionError("EstimateMetricScale: needs at least 3 finished keyframes (call Finish first)");
  if (!AllPointLights(m.rig))
    return FailedPreconditionError("EstimateMetricScale: needs three point lights on the rig");
  const double start = m.RelitMetresPerWorldUnit();
  if (!(start > 0)) return FailedPreconditionError("EstimateMetricScale: no keyframe pair gave a shading scale");
  // At most final_adjustment_max_keyframes, the newest.
  const int first = std::max(0, n - m.options.final_adjustment_max_keyframes);
  MetricScaleEstimate e;
  e.start_metres_per_world_unit = start;
  {
    const size_t np = m.relit_pair_estimates.size();
    e.pairs = static_cast<int>(np);
    e.pair_spread = PairSpread(m.relit_pair_estimates);
    e.consistent = e.pair_spread <= m.options.metric_scale_max_pair_spread;
    if (!e.consistent) {
      PRISM_LOG(WARNING) << "slam: the reconstruction disagrees with the co-moving lights' shading: the " << np
                         << " keyframe pairs' shading scales spread by " << e.pair_spread
                         << " of their median (interquartile range; limit " << m.options.metric_scale_max_pair_spread
                         << "); the trajectory and depth are probably distorted (e.g. an initialisation in the "
                            "bas-relief ambiguity of a sideways start)";
    }
  }
  double k = start;
  for (int pass = 0; pass < 4; ++pass) {
    DirectBaProblem problem;
    if (!m.BuildAdjustmentProblem(first, /*relit=*/true, /*mixed=*/false, k, m.options.metric_scale_min_band_fraction,
                                  &problem))
      return FailedPreconditionError("EstimateMetricScale: too few adjustment points");
    StatusOr<DirectBaSummary> summary =
        AdjustKeyframeWindowDirect(m.options.final_adjustment_relit_ba, &problem, m.pool);
    if (!summary.ok()) return summary.status();
    const double next = problem.relit.metres_per_world_unit;
    e.passes = pass + 1;
    e.residuals = summary->residuals;
    e.final_rms = summary->final_rms;
    const bool settled = std::abs(std::log(next / k)) < 0.005;
    k = next;
    if (settled) break;
  }
  for (Impl::Keyframe& kf : m.keyframes) kf.grey_j.release();
  e.metres_per_world_unit = k;
  e.keyframes = n - first;
  return e;
}

void SlamSystem::RefineKeyframeDepths(int neighbours, double relative_sigma, int rounds,
                                      std::vector<SlamKeyframe>* keyframes) {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  const int span = neighbours;
  if (span <= 0 || !(relative_sigma > 0) || keyframes == nullptr) return;
  const int n = static_cast<int>(m.keyframes.size());
  std::vector<cv::Mat> grey_j(static_cast<size_t>(n));  // each keyframe's J, computed once
  std::vector<InverseDepthMap> handed_out;              // each round starts from these
  for (const SlamKeyframe& out : *keyframes) handed_out.push_back(out.depth);
  const bool readjust = m.options.final_adjustment && m.CanAdjustAllKeyframes() && n >= 3;
  const bool features_alone = m.options.final_adjustment && m.CanAdjustByFeaturesAlone() && n >= 3;
  for (int round = 0; round < std::max(1, rounds); ++round) {
    if (round > 0) {
      if (!readjust && !features_alone) break;
      // The adjustment's points come from the keyframes' (refined) final depths; it uses the same J.
      for (int k = 0; k < n; ++k)
        if (!grey_j[static_cast<size_t>(k)].empty())
          m.keyframes[static_cast<size_t>(k)].grey_j = grey_j[static_cast<size_t>(k)];
      // The features first: they set the turn the direct cost leaves nearly flat, the direct adjustment
      // then refines the poses locally from there.
      m.AdjustByFeatures();
      if (readjust) m.AdjustKeyframes(0, m.options.final_adjustment_ba, /*at_finish=*/true);
      for (size_t i = 0; i < keyframes->size(); ++i) (*keyframes)[i].depth = handed_out[i];
    }
    // Each keyframe apart: with a pool of more than one thread the keyframes are refined in parallel,
    // each on one thread (the depth update gives the same bits with or without a pool), every neighbour's
    // J made first. Keyframe 0's seed reads keyframe 1's depth as handed out (the one-thread order
    // refines keyframe 0 first).
    const bool by_keyframe = m.pool != nullptr && m.pool->num_threads() > 1 && keyframes->size() > 1;
    if (by_keyframe) {
      m.pool->ParallelFor(0, n, [&](std::ptrdiff_t j) {
        cv::Mat& jj = grey_j[static_cast<size_t>(j)];
        if (jj.empty()) {
          cv::Mat mean;
          KeyframeDepth::NormalisedGrey(m.keyframes[static_cast<size_t>(j)].rgb, m.options.depth, &jj, &mean);
        }
      });
    }
    std::vector<InverseDepthMap> round_start;  // by_keyframe: the depths this round starts from
    if (by_keyframe)
      for (const SlamKeyframe& o : *keyframes) round_start.push_back(o.depth);
    auto refine = [&](SlamKeyframe& out, ThreadPool* update_pool) {
      const int id = out.id;
      if (id < 0 || id >= n || out.depth.inverse_depth.empty()) return;
      const Impl::Keyframe& k = m.keyframes[static_cast<size_t>(id)];
      // Every search made: this runs once, after the last frame (skip_information_ratio is for the
      // online mapping's time).
      DepthFilterOptions refine_options = m.options.depth;
      refine_options.skip_information_ratio = 0;
      StatusOr<KeyframeDepth> kd = KeyframeDepth::Create(k.rgb, m.rig.camera, refine_options, m.rig.crosstalk);
      if (!kd.ok()) return;
      cv::Mat seed = out.depth.inverse_depth;
      if (id == 0 && n >= 2 && m.options.final_refinement_first_from_second) {
        const cv::Mat* second = nullptr;
        for (size_t i = 0; i < keyframes->size(); ++i) {
          const SlamKeyframe& o = (*keyframes)[i];
          const cv::Mat& second_depth = by_keyframe ? round_start[i].inverse_depth : o.depth.inverse_depth;
          if (o.id == 1 && !second_depth.empty()) second = &second_depth;
        }
        if (second != nullptr) seed = m.SeedFromSecondKeyframe(*kd, out.depth.inverse_depth, *second);
      }
      kd->Seed(seed, relative_sigma, 2);
      const double mean_idepth = kd->MeanInverseDepth();
      for (int j = std::max(0, id - span); j <= std::min(n - 1, id + span); ++j) {
        if (j == id) continue;
        // A point X of keyframe id (its units) in j's camera, in id's units.
        const Rigid3d j_from_id =
            BFromAInUnitsOfA(k.world_from_keyframe, m.keyframes[static_cast<size_t>(j)].world_from_keyframe);
        // Only neighbours that see about the same scene (not across a relocalisation): within twice the
        // keyframe distance and rotation limits.
        if (j_from_id.translation.norm() * mean_idepth > 2 * m.options.keyframe_distance_fraction + 0.2 ||
            RotationAngle(j_from_id.rotation) * kRadToDeg > 2 * m.options.keyframe_max_rotation_deg)
          continue;
        cv::Mat& jj = grey_j[static_cast<size_t>(j)];
        if (jj.empty()) {
          cv::Mat mean;
          KeyframeDepth::NormalisedGrey(m.keyframes[static_cast<size_t>(j)].rgb, m.options.depth, &jj, &mean);
        }
        kd->Update(jj, j_from_id, update_pool);
      }
      kd->Regularise();
      out.depth = kd->ToInverseDepthMap();
      // Only a neighbour's image is used above, not its depth: the order does not matter.
      Impl::Keyframe& refined = m.keyframes[static_cast<size_t>(id)];
      if (refined.finished) {
        refined.final_depth = out.depth;
        refined.DropWindowPoints();
      }
    };
    if (by_keyframe) {
      m.pool->ParallelFor(0, static_cast<std::ptrdiff_t>(keyframes->size()),
                          [&](std::ptrdiff_t i) { refine((*keyframes)[static_cast<size_t>(i)], nullptr); });
    } else {
      for (SlamKeyframe& out : *keyframes) refine(out, m.pool);
    }
  }
}

cv::Mat SlamSystem::Impl::SeedFromSecondKeyframe(const KeyframeDepth& first, const cv::Mat& first_inverse_depth,
                                                 const cv::Mat& second_inverse_depth) {
  const Keyframe& k0 = keyframes[0];
  const Keyframe& k1 = keyframes[1];
  StatusOr<KeyframeDepth> source = KeyframeDepth::Create(k1.rgb, rig.camera, options.depth, rig.crosstalk);
  if (!source.ok()) return first_inverse_depth;
  KeyframeDepth target = first.Blank();  // keyframe 0's image parts, no estimates
  source->Seed(second_inverse_depth, options.final_refinement_relative_sigma, 2);
  // Keyframe 1's points in keyframe 0's camera, in keyframe 1's units; then in keyframe 0's.
  target.PropagateFrom(*source, BFromAInUnitsOfA(k1.world_from_keyframe, k0.world_from_keyframe), 0.0);
  const cv::Mat propagated = target.ToInverseDepthMap(1, 1.0).inverse_depth;
  const float to_first_units = static_cast<float>(k0.world_from_keyframe.scale / k1.world_from_keyframe.scale);
  std::vector<double> ratios;
  for (int y = 0; y < propagated.rows; ++y)
    for (int x = 0; x < propagated.cols; ++x) {
      const float p = propagated.at<float>(y, x), o = first_inverse_depth.at<float>(y, x);
      if (p > 0 && o > 0) ratios.push_back(p * to_first_units / o);
    }
  if (ratios.size() < 100) return first_inverse_depth;
  std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
  const float own_scale = static_cast<float>(ratios[ratios.size() / 2]);
  cv::Mat seed(first_inverse_depth.size(), CV_32F, cv::Scalar(0));
  for (int y = 0; y < seed.rows; ++y)
    for (int x = 0; x < seed.cols; ++x) {
      const float p = propagated.at<float>(y, x), o = first_inverse_depth.at<float>(y, x);
      seed.at<float>(y, x) = p > 0 ? p * to_first_units : o > 0 ? o * own_scale : 0.0f;
    }
  return seed;
}

}  // namespace prism
