#include "core/slam/slam_system.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ostream>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <gtest/gtest.h>

#include "core/eval/trajectory_metrics.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/synthesize.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

struct Rendered {
  synth::SynthSetup setup;
  Trajectory trajectory;
  std::vector<synth::RenderedFrame> frames;
};

// As prism-synth --preset PRESET --frames FRAMES --seed SEED renders it (with supersampling).
bool Render(const std::string& preset, int frames, int supersampling, Rendered* out, std::string* why,
            uint32_t seed = 1) {
  synth::PresetOptions o;
  o.frames = frames;
  o.seed = seed;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    *why = setup.status().ToString();
    return false;
  }
  out->setup = std::move(setup).value();
  out->setup.render.supersampling = supersampling;
  out->trajectory = synth::MakeTrajectory(out->setup.trajectory);
  out->frames.resize(frames);
  ThreadPool pool;
  pool.ParallelFor(0, frames, [&](std::ptrdiff_t i) {
    out->frames[i] = synth::RenderFrame(out->setup.scene, out->setup.rig, out->trajectory[i].world_from_camera,
                                        out->setup.render, synth::FrameNoiseSeed(seed, i));
  });
  return true;
}

// Every frame of r, then Finish; the keyframes as handed out.
void RunAndFinish(const Rendered& r, SlamSystem* slam, std::vector<SlamKeyframe>* keyframes) {
  for (size_t i = 0; i < r.frames.size(); ++i) {
    StatusOr<SlamFrameResult> f = slam->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok()) << f.status();
    for (SlamKeyframe& k : slam->TakeFinishedKeyframes()) keyframes->push_back(std::move(k));
  }
  for (SlamKeyframe& k : slam->Finish()) keyframes->push_back(std::move(k));
}

// RunAndFinish, then prism-slam's refinement rounds (options' final_refinement_*), as prism-slam runs a
// sequence; the keyframes as handed out, refined.
void RunAsPrismSlam(const Rendered& r, const SlamOptions& options, SlamSystem* slam,
                    std::vector<SlamKeyframe>* keyframes) {
  ASSERT_NO_FATAL_FAILURE(RunAndFinish(r, slam, keyframes));
  slam->RefineKeyframeDepths(options.final_refinement_neighbours, options.final_refinement_relative_sigma,
                             options.final_refinement_rounds, keyframes);
}

// The tracked frames' poses of a SLAM trajectory.
Trajectory TrackedPoses(const std::vector<SlamFrameResult>& frames) {
  Trajectory t;
  for (const SlamFrameResult& f : frames)
    if (f.state == SlamState::kTracking) t.push_back({f.timestamp, f.world_from_camera});
  return t;
}

// The ATE after Sim(3) alignment to the truth, and its RMSE as % of the path.
StatusOr<AteResult> Sim3Ate(const Trajectory& truth, const Trajectory& estimate) {
  TrajectoryEvalOptions eo;
  eo.alignment = AlignmentModel::kSim3;
  return ComputeAte(truth, estimate, eo);
}
double PercentOfPath(const AteResult& ate) { return 100 * ate.error_m.rmse / ate.trajectory_length_m; }

bool SamePose(const Rigid3d& a, const Rigid3d& b) {
  return a.rotation.coeffs() == b.rotation.coeffs() && a.translation == b.translation;
}
bool SameSim3(const Sim3d& a, const Sim3d& b) {
  return a.scale == b.scale && a.rotation.coeffs() == b.rotation.coeffs() && a.translation == b.translation;
}

// Two runs' trajectories (after Finish) and keyframe poses are the same to the bit.
void ExpectSamePoses(const std::vector<SlamFrameResult>& a_trajectory, const std::vector<Sim3d>& a_keyframes,
                     const std::vector<SlamFrameResult>& b_trajectory, const std::vector<Sim3d>& b_keyframes) {
  ASSERT_EQ(a_trajectory.size(), b_trajectory.size());
  for (size_t i = 0; i < b_trajectory.size(); ++i)
    EXPECT_TRUE(SamePose(a_trajectory[i].world_from_camera, b_trajectory[i].world_from_camera)) << "frame " << i;
  ASSERT_EQ(a_keyframes.size(), b_keyframes.size());
  for (size_t k = 0; k < b_keyframes.size(); ++k)
    EXPECT_TRUE(SameSim3(a_keyframes[k], b_keyframes[k])) << "keyframe " << k;
}

struct SlamCase {
  std::string preset;
  int frames;
  double max_ate_percent_of_path;
  double max_depth_median_rel_error;
  int min_loop_closures = 0;
  int supersampling = 1;       // RenderOptions::supersampling
  bool init_raw_grey = false;  // the initialisation's KLT on raw grey (init_track_normalised off)
  // |EstimateMetricScale / the trajectory's Sim(3) scale - 1| after the rounds (0: not checked).
  double max_metric_scale_rel_error = 0;
};

void PrintTo(const SlamCase& c, std::ostream* os) { *os << c.preset << ", " << c.frames << " frames"; }

class SlamSystemPresetTest : public ::testing::TestWithParam<SlamCase> {};

// One round of RefineKeyframeDepths may not make the median depth error worse by more than this.
// Measured on the seed-1 presets: it lowers it on every one (see the README).
constexpr double kRefinementSlack = 0.002;
// prism-slam's default rounds (which move the poses) against one round. They help on average, not on
// every run. Over the 54 standard runs (9 presets x seeds 1-6, prism-slam --set final_refinement_rounds=1
// against the default of 8; nineteenth round) they lower the median depth error on 49 (by 0.67 points in
// the median) and raise it on 5: the uniform sphere, whose poses are wrong, by up to 3.9 points, the
// multi-coloured sphere's seed 3 by 1.4 (3.65% -> 5.08%), the dragon by up to 0.18. The trajectory error
// rises by up to 0.32 points of the path on the uniform sphere and 0.074 elsewhere (dragon, seed 6).
// (With 4 rounds, fourteenth round: lower on 47, rises up to 0.66 points on the presets below.) So these
// bounds catch rounds that break a run, with room for that spread on the seed-1 presets tested here.
constexpr double kRoundsDepthSlack = 0.01;
constexpr double kRoundsAteSlackPercent = 0.15;

TEST_P(SlamSystemPresetTest, TracksEveryFrameAgainstGroundTruth) {
  const SlamCase& c = GetParam();
  Rendered r;
  std::string why;
  if (!Render(c.preset, c.frames, c.supersampling, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  SlamOptions options;
  if (c.init_raw_grey) {
    options.init_track_normalised = false;
    options.init_min_feature_local_mean = 0;
  }
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, &pool);
  ASSERT_TRUE(slam.ok()) << slam.status();
  std::vector<SlamKeyframe> keyframes;
  for (int i = 0; i < c.frames; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok()) << f.status();
    EXPECT_EQ(f->frame_id, i);
    EXPECT_NE(f->state, SlamState::kLost) << "frame " << i << ": " << f->message;
    for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) keyframes.push_back(std::move(k));
  }
  const int adjustments_before_finish = (*slam)->num_keyframe_adjustments();
  for (SlamKeyframe& k : (*slam)->Finish()) keyframes.push_back(std::move(k));
  // The final adjustment of all keyframes (SlamOptions::final_adjustment) ran at Finish, unless there
  // are too many keyframes for it (the orbit).
  const bool final_adjustment = (*slam)->num_keyframes() <= SlamOptions().final_adjustment_max_keyframes;
  EXPECT_EQ((*slam)->num_keyframe_adjustments(), adjustments_before_finish + (final_adjustment ? 1 : 0));
  (*slam)->AdjustAllKeyframes();  // once only
  EXPECT_EQ((*slam)->num_keyframe_adjustments(), adjustments_before_finish + (final_adjustment ? 1 : 0));
  // The feature adjustment ran with it, or alone beyond its limit (the orbit).
  const bool feature_adjustment = options.final_feature_adjustment && options.keyframe_adjustment &&
                                  (*slam)->num_keyframes() <= std::max(options.final_adjustment_max_keyframes,
                                                                       options.feature_adjustment_max_keyframes);
  EXPECT_EQ((*slam)->feature_adjustment().applied, feature_adjustment) << (*slam)->feature_adjustment().error;
  EXPECT_TRUE((*slam)->TakeFinishedKeyframes().empty()) << "each keyframe is handed out once";
  ASSERT_EQ(static_cast<int>(keyframes.size()), (*slam)->num_keyframes());
  ASSERT_GE(keyframes.size(), 2u);
  for (size_t i = 0; i < keyframes.size(); ++i) EXPECT_EQ(keyframes[i].id, static_cast<int>(i));

  // Every frame has a pose once initialised (the initialisation frames are resolved afterwards).
  Trajectory estimate;
  for (const SlamFrameResult& f : (*slam)->Trajectory()) {
    EXPECT_EQ(f.state, SlamState::kTracking) << "frame " << f.frame_id << ": " << f.message;
    if (f.state == SlamState::kTracking) estimate.push_back({f.timestamp, f.world_from_camera});
  }
  StatusOr<AteResult> ate = Sim3Ate(r.trajectory, estimate);
  ASSERT_TRUE(ate.ok()) << ate.status();
  const double ate_percent = PercentOfPath(*ate);

  // Keyframe depth in metres through the trajectory's scale and the keyframe's (pose-graph) scale.
  const std::vector<Sim3d> keyframe_poses = (*slam)->KeyframePoses();
  ASSERT_EQ(keyframe_poses.size(), keyframes.size());
  // Relative errors of every depth pixel of `ks`, with keyframe poses `poses` and the trajectory's scale
  // `gt_per_est` (metres per unit).
  auto relative_errors = [&](const std::vector<SlamKeyframe>& ks, const std::vector<Sim3d>& poses, double gt_per_est) {
    std::vector<double> out;
    for (const SlamKeyframe& k : ks) {
      const double scale = gt_per_est * poses[static_cast<size_t>(k.id)].scale;
      const cv::Mat& gt = r.frames[static_cast<size_t>(k.frame_id)].depth;
      for (int y = 0; y < gt.rows; ++y)
        for (int x = 0; x < gt.cols; ++x) {
          const float d = k.depth.inverse_depth.at<float>(y, x);
          const float z = gt.at<float>(y, x);
          if (d > 0 && z > 0) out.push_back(std::abs(scale / d - z) / z);
        }
    }
    return out;
  };
  auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    return v[v.size() / 2];
  };
  const std::vector<double> rel = relative_errors(keyframes, keyframe_poses, ate->gt_from_est.scale);
  ASSERT_FALSE(rel.empty());
  const double depth_median = median(rel);
  // The same after one round of RefineKeyframeDepths (2 keyframes on each side, 5% prior: prism-slam's
  // --set final_refinement_neighbours=2 final_refinement_rounds=1): the poses do not move.
  std::vector<SlamKeyframe> refined = keyframes;
  (*slam)->RefineKeyframeDepths(2, 0.05, 1, &refined);
  const std::vector<double> rel_refined = relative_errors(refined, keyframe_poses, ate->gt_from_est.scale);
  ASSERT_GT(rel_refined.size(), rel.size() / 2);
  const double refined_median = median(rel_refined);
  std::printf("%s: depth median rel error %.4f after one round of RefineKeyframeDepths, on %zu pixels\n",
              c.preset.c_str(), refined_median, rel_refined.size());
  EXPECT_LE(refined_median, depth_median + kRefinementSlack);
  EXPECT_EQ((*slam)->num_keyframe_adjustments(), adjustments_before_finish + (final_adjustment ? 1 : 0));
  // prism-slam's default rounds: between rounds the final adjustment runs again on the refined depths,
  // which moves the keyframe poses and the trajectory; both are scored again.
  const SlamOptions defaults;
  std::vector<SlamKeyframe> rounds = keyframes;
  (*slam)->RefineKeyframeDepths(defaults.final_refinement_neighbours, defaults.final_refinement_relative_sigma,
                                defaults.final_refinement_rounds, &rounds);
  EXPECT_EQ((*slam)->num_keyframe_adjustments(),
            adjustments_before_finish + (final_adjustment ? defaults.final_refinement_rounds : 0));
  const Trajectory estimate_after_rounds = TrackedPoses((*slam)->Trajectory());
  StatusOr<AteResult> ate_rounds = Sim3Ate(r.trajectory, estimate_after_rounds);
  ASSERT_TRUE(ate_rounds.ok()) << ate_rounds.status();
  const double ate_rounds_percent = PercentOfPath(*ate_rounds);
  const std::vector<double> rel_rounds =
      relative_errors(rounds, (*slam)->KeyframePoses(), ate_rounds->gt_from_est.scale);
  ASSERT_GT(rel_rounds.size(), rel.size() / 2);
  const double rounds_median = median(rel_rounds);
  std::printf("%s: after %d rounds: ATE %.3f%% of path, depth median rel error %.4f on %zu pixels\n", c.preset.c_str(),
              defaults.final_refinement_rounds, ate_rounds_percent, rounds_median, rel_rounds.size());
  EXPECT_LE(rounds_median, refined_median + kRoundsDepthSlack);
  EXPECT_LE(ate_rounds_percent, ate_percent + kRoundsAteSlackPercent);
  // The metres per world unit from the co-moving lights, against the trajectory's Sim(3) scale (the
  // truth's metres per world unit); the SLAM's state does not change.
  if (c.max_metric_scale_rel_error > 0) {
    StatusOr<MetricScaleEstimate> metric = (*slam)->EstimateMetricScale();
    ASSERT_TRUE(metric.ok()) << metric.status();
    const double metric_error = metric->metres_per_world_unit / ate_rounds->gt_from_est.scale - 1;
    std::printf(
        "%s: metric scale %.4f m per unit (start %.4f, %d passes), truth %.4f: %+.2f%%; keyframe pairs' shading "
        "scales spread by %.4f (%d pairs)\n",
        c.preset.c_str(), metric->metres_per_world_unit, metric->start_metres_per_world_unit, metric->passes,
        ate_rounds->gt_from_est.scale, 100 * metric_error, metric->pair_spread, metric->pairs);
    EXPECT_LE(std::abs(metric_error), c.max_metric_scale_rel_error);
    // These runs are within the trajectory bar: the shading agrees with them.
    EXPECT_TRUE(metric->consistent) << "pair spread " << metric->pair_spread;
    size_t j = 0;
    for (const SlamFrameResult& f : (*slam)->Trajectory()) {
      if (f.state != SlamState::kTracking) continue;
      ASSERT_LT(j, estimate_after_rounds.size());
      EXPECT_EQ(f.world_from_camera.translation, estimate_after_rounds[j++].world_from_camera.translation);
    }
    EXPECT_EQ(j, estimate_after_rounds.size());
  }
  std::printf(
      "%s: %zu frames, %zu keyframes, %d loop closures, ATE %.4f m = %.3f%% of %.3f m, depth median rel "
      "error %.4f on %zu pixels\n",
      c.preset.c_str(), estimate.size(), keyframes.size(), (*slam)->num_loop_closures(), ate->error_m.rmse, ate_percent,
      ate->trajectory_length_m, depth_median, rel.size());
  EXPECT_GE((*slam)->num_loop_closures(), c.min_loop_closures);
  EXPECT_LE(ate_percent, c.max_ate_percent_of_path);
  EXPECT_LE(depth_median, c.max_depth_median_rel_error);
  EXPECT_GT((*slam)->SemiDenseCloud().size(), 1000u);
}

// Tolerances from measurement (printed): see the note of the SLAM issue.
INSTANTIATE_TEST_SUITE_P(
    DarkRoomPresets, SlamSystemPresetTest,
    // Measured (ATE % of path / depth median) with the 8-keyframe window (eighteenth
    // round; with 6 before it): bunny 0.23% / 1.8% (1.6%), dragon 0.38% / 2.1% (2.4%),
    // armadillo 0.25% / 1.4% (1.7%), multi-coloured sphere 0.46% / 3.3% (3.3%), relief
    // 0.58% / 4.1% (4.4%), boxes 0.39% / 3.0% (3.8%), torus 0.62% / 5.2% (5.4%). The depth
    // tolerances of the sphere, relief, boxes and torus are regression bounds above the
    // issue's 3% bar, which they miss (other seeds: 3.1-15.6%). No loop closure on these
    // 120 deg arcs.
    // Metric scale (EstimateMetricScale against the trajectory's Sim(3) scale, after the 8
    // rounds; twenty-first round, prism-slam on the same sequences): bunny +2.7%, dragon
    // +1.9%, armadillo +2.4%, multi-coloured sphere -0.8%, relief +4.4%, boxes +0.6%, torus
    // -1.9% (with metric_scale_min_band_fraction 0.15: the multi-coloured presets 4-9% low).
    ::testing::Values(SlamCase{"bunny-multicolor-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.03, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.05},
                      SlamCase{"dragon-multicolor-sideways", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.03, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.04},
                      SlamCase{"armadillo-textured-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.03, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.05},
                      SlamCase{"sphere-multicolor-sideways", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.04, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.04},
                      SlamCase{"relief-uniform-sideways", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.06, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.07},
                      SlamCase{"boxes-multicolor-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.05, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.04},
                      // Metric scale: +3.6% before the final adjustment's gradient weight
                      // (thirty-seventh round), +4.2% with it (the trajectory it is scored against
                      // moved; over the 54 standard runs the median error 2.1 -> 2.2%), +5.6% with
                      // the window adjustment's 12 px cells (fiftieth round; ATE 0.145% of path,
                      // depth 1.3% after the 8 rounds).
                      SlamCase{"torus-textured-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.07, /*min_loop_closures=*/0,
                               /*supersampling=*/1, false, /*max_metric_scale_rel_error=*/0.07},
                      // A full orbit and 40 deg beyond: loop closure. 65 keyframes, 26 loop
                      // edges: over final_adjustment_max_keyframes = 64, no direct final
                      // adjustment; the feature adjustment alone (feature_adjustment_max_keyframes
                      // = 96): 0.022% / 1.1% at Finish (0.125% / 1.5% without it), after the 8
                      // refinement rounds 0.022% / 0.82% (0.125% / 1.1%).
                      SlamCase{"bunny-multicolor-orbit", 450, /*max_ate_percent_of_path=*/0.5,
                               /*max_depth_median_rel_error=*/0.04, /*min_loop_closures=*/1},
                      // The demo's bunny rendered with 2x2 rays per pixel (pixel-area
                      // integration: soft edges, as a real sensor): measured 0.26% / 3.1%
                      // (window 6: 0.39% / 4.3%), against 0.23% / 1.8% point-sampled. Seeds 1-3 of the 9 presets:
                      // 20 of 27 runs within 1% against 23 point-sampled (see the README).
                      SlamCase{"bunny-multicolor-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.05, /*min_loop_closures=*/0,
                               /*supersampling=*/2},
                      // The same path three times faster (120 degrees in 50 frames): with the
                      // initialisation's KLT on raw grey (before the thirty-sixth round) 31
                      // features survived the dim sideways start and it began turning about the
                      // optical axis (7.7% of path, 5 keyframes, no loss reported); on J (the
                      // default) measured 0.15% / 1.8% (after prism-slam's rounds 0.09% / 0.9%).
                      SlamCase{"sphere-multicolor-sideways", 50, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.03},
                      // The initialisation's KLT on raw grey (SlamOptions::init_track_normalised
                      // false; the default before the thirty-sixth round, and what rigs without
                      // lights use): measured 0.19% / 2.2% (after the rounds 0.12% / 1.0%; on J
                      // 0.12% / 1.9%).
                      SlamCase{"bunny-multicolor-forward", 150, /*max_ate_percent_of_path=*/1.0,
                               /*max_depth_median_rel_error=*/0.035, /*min_loop_closures=*/0,
                               /*supersampling=*/1, /*init_raw_grey=*/true}),
    [](const ::testing::TestParamInfo<SlamCase>& info) {
      std::string n = info.param.preset;
      std::replace(n.begin(), n.end(), '-', '_');
      if (info.param.init_raw_grey) n += "_init_raw_grey";
      if (info.param.frames < 150) n += "_" + std::to_string(info.param.frames) + "_frames";
      if (info.param.supersampling > 1) n += "_supersampled" + std::to_string(info.param.supersampling);
      return n;
    });

// The shading check (MetricScaleEstimate::consistent): the uniform bunny's seed 1 (the renderer's noise
// as prism-synth --seed 1) starts in the bas-relief ambiguity of its sideways arc (rotation 30% short from
// the first frames; 3.9% of path after prism-slam's rounds, README twenty-second round) without any
// other sign. The keyframe pairs' shading scales then scatter (measured: a spread of 0.30 of their
// median against 0.02 on seeds 2 and 3; the limit is 0.16), and the check reports it. Written as an equivalence so that
// a fix of the initialisation keeps the test meaningful: a run within the 1% bar must pass the check,
// one above kDistortedAtePercent must fail it. The start check (on by default since the twenty-third
// round) replaces this start; it is off here so that the end-of-run check still sees it.
constexpr double kDistortedAtePercent = 2.0;

// A run as prism-slam runs it, its ATE (% of path) and the shading check at its end.
struct ShadingCheckRun {
  double ate_percent = 0;
  int keyframes = 0;
  MetricScaleEstimate metric;
};

void RunForShadingCheck(const Rendered& r, const SlamOptions& options, ThreadPool* pool, ShadingCheckRun* out) {
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, pool);
  ASSERT_TRUE(slam.ok()) << slam.status();
  std::vector<SlamKeyframe> keyframes;
  ASSERT_NO_FATAL_FAILURE(RunAsPrismSlam(r, options, slam->get(), &keyframes));
  StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses((*slam)->Trajectory()));
  ASSERT_TRUE(ate.ok()) << ate.status();
  out->ate_percent = PercentOfPath(*ate);
  out->keyframes = (*slam)->num_keyframes();
  StatusOr<MetricScaleEstimate> metric = (*slam)->EstimateMetricScale();
  ASSERT_TRUE(metric.ok()) << metric.status();
  out->metric = *metric;
}

TEST(SlamSystem, TheShadingCheckReportsADistortedReconstruction) {
  Rendered r;
  std::string why;
  if (!Render("bunny-uniform-sideways", 150, 1, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  SlamOptions options;
  options.start_check_keyframes = 0;  // the distorted start stays
  // The distorted start comes from the initialisation's features on raw grey; on J (the default since the
  // thirty-sixth round) this seed starts right (0.11% of path).
  options.init_track_normalised = false;
  options.init_min_feature_local_mean = 0;
  // And the frame after each keyframe tracked from no motion, as before the thirty-eighth round. With the
  // velocity carried over this start ends at 2.93% of path with a pair spread of 0.144, under the 0.16
  // limit: the check misses that milder distortion (README, thirty-eighth round).
  options.keep_velocity_across_keyframes = false;
  ShadingCheckRun run;
  ASSERT_NO_FATAL_FAILURE(RunForShadingCheck(r, options, &pool, &run));
  std::printf("uniform bunny, seed 1: ATE %.3f%% of path; keyframe pairs' shading scales spread by %.4f (%d pairs)\n",
              run.ate_percent, run.metric.pair_spread, run.metric.pairs);
  if (run.ate_percent <= 1.0) {
    EXPECT_TRUE(run.metric.consistent) << "pair spread " << run.metric.pair_spread;
  }
  if (run.ate_percent >= kDistortedAtePercent) {
    EXPECT_FALSE(run.metric.consistent) << "pair spread " << run.metric.pair_spread;
  }
  EXPECT_TRUE(run.ate_percent <= 1.0 || run.ate_percent >= kDistortedAtePercent)
      << "between the bar and the distorted case: the test says nothing; re-measure";
}

// The uniform sphere's forward start (a preset outside the standard nine; README, forty-sixth round),
// seed 6. With keyframes by rotation at 15 deg (the default before that round) the arc after the
// forward start is tracked at 0.69 of its true turn and 0.7 deg per frame, too little translation for the
// distance test: one keyframe is tracked over 23 frames, 9 keyframes in all (16-20 on the other seeds),
// 19.1% of path. Its first six keyframes' pairs spread by 0.151, under the start check's 0.16; at the end
// by 0.61, and the shading check must report it (an equivalence as above, so that a fix of the tracking
// keeps it meaningful). With the default of 10 deg the first six keyframes spread by 2.54, the start
// check starts again and keeps the second start: 17 keyframes and 1.53% of path (the other seeds
// unchanged: 1.24-2.77%, they never turn 10 deg between keyframes).
constexpr double kUniformSphereForwardMaxAtePercent = 2.0;
constexpr int kUniformSphereForwardMinKeyframes = 14;

TEST(SlamSystem, KeyframesByRotationKeepTheUniformSpheresForwardArc) {
  Rendered r;
  std::string why;
  if (!Render("sphere-uniform-forward", 150, 1, &r, &why, /*seed=*/6)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  for (double max_rotation_deg : {SlamOptions().keyframe_max_rotation_deg, 15.0}) {
    SCOPED_TRACE("keyframe_max_rotation_deg " + std::to_string(max_rotation_deg));
    SlamOptions options;
    options.keyframe_max_rotation_deg = max_rotation_deg;
    ShadingCheckRun run;
    ASSERT_NO_FATAL_FAILURE(RunForShadingCheck(r, options, &pool, &run));
    std::printf(
        "uniform sphere, forward start, seed 6, keyframes by rotation at %.0f deg: ATE %.3f%% of path, %d "
        "keyframes; pairs spread by %.4f\n",
        max_rotation_deg, run.ate_percent, run.keyframes, run.metric.pair_spread);
    if (max_rotation_deg == SlamOptions().keyframe_max_rotation_deg) {
      EXPECT_LE(run.ate_percent, kUniformSphereForwardMaxAtePercent);
      EXPECT_GE(run.keyframes, kUniformSphereForwardMinKeyframes);
    }
    if (run.ate_percent >= kDistortedAtePercent) {
      EXPECT_FALSE(run.metric.consistent) << "pair spread " << run.metric.pair_spread;
    }
  }
}

// The uniform sphere's seed 2, the run that missed the bar longest: its shading is the same from
// every direction and its path's scale drifts along the arc (2.64 -> 2.05 units per metre over 140
// frames). With each keyframe's propagated depth at 1% relative sigma (the default before the
// fifty-seventh round) prism-slam ends at 2.00% of path; at 1.25% (the default) the new stereo re-anchors
// each keyframe's scale to the tracked motion and it ends at 0.86% (seeds 1-9: 7 -> 8 of 9 within 1%;
// README, fifty-seventh round); 0.57% with the local mean's edge test (fifty-eighth round).
constexpr double kUniformSphereMaxAtePercent = 1.0;  // the bar

// One seed of a preset as prism-slam runs it (refinement rounds included; default options unless
// given), the uniform sphere's sideways start unless another preset is named.
struct PrismSlamRun {
  Rendered r;
  std::vector<SlamKeyframe> keyframes;
  std::vector<Sim3d> keyframe_poses;
  Trajectory tracked;
  AteResult ate;
};
// False (and *why) when the preset cannot be rendered; fatal failures on errors.
bool RunSeedAsPrismSlam(int seed, PrismSlamRun* run, std::string* why, const SlamOptions& options = SlamOptions(),
                        const std::string& preset = "sphere-uniform-sideways") {
  if (!Render(preset, 150, 1, &run->r, why, seed)) return false;
  ThreadPool pool(2);
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(run->r.setup.rig, options, &pool);
  EXPECT_TRUE(slam.ok()) << slam.status();
  if (!slam.ok()) return true;
  RunAsPrismSlam(run->r, options, slam->get(), &run->keyframes);
  run->tracked = TrackedPoses((*slam)->Trajectory());
  run->keyframe_poses = (*slam)->KeyframePoses();
  StatusOr<AteResult> ate = Sim3Ate(run->r.trajectory, run->tracked);
  EXPECT_TRUE(ate.ok()) << ate.status();
  if (ate.ok()) run->ate = *ate;
  return true;
}

// Every frame tracked and the ATE within the bar, printed with `label`.
void ExpectTrackedWithinTheBar(const PrismSlamRun& run, const char* label) {
  std::printf("%s: ATE %.3f%% of path, %zu keyframes\n", label, PercentOfPath(run.ate), run.keyframes.size());
  EXPECT_EQ(run.tracked.size(), run.r.trajectory.size()) << "every frame tracked";
  EXPECT_LE(PercentOfPath(run.ate), kUniformSphereMaxAtePercent);
}

// The keyframes' median relative depth error through the trajectory's Sim(3) scale (as prism-slam
// scores it), over the pixels they claim; *pixels: how many.
double DepthMedianThroughTheTrajectory(const PrismSlamRun& run, size_t* pixels) {
  std::vector<double> rel;
  for (const SlamKeyframe& k : run.keyframes) {
    const double scale = run.ate.gt_from_est.scale * run.keyframe_poses[static_cast<size_t>(k.id)].scale;
    const cv::Mat& gt = run.r.frames[static_cast<size_t>(k.frame_id)].depth;
    for (int y = 0; y < gt.rows; ++y)
      for (int x = 0; x < gt.cols; ++x) {
        const float d = k.depth.inverse_depth.at<float>(y, x);
        const float z = gt.at<float>(y, x);
        if (d > 0 && z > 0) rel.push_back(std::abs(scale / d - z) / z);
      }
  }
  *pixels = rel.size();
  if (rel.empty()) return 1.0;
  std::nth_element(rel.begin(), rel.begin() + static_cast<std::ptrdiff_t>(rel.size() / 2), rel.end());
  return rel[rel.size() / 2];
}

constexpr double kMaxDepthMedian = 0.03;  // the bar
constexpr size_t kMinDepthPixels = 100000;

// The ATE and the depth within the bars, printed with `label`.
void ExpectWithinBothBars(const PrismSlamRun& run, const char* label) {
  size_t pixels = 0;
  const double depth_median = DepthMedianThroughTheTrajectory(run, &pixels);
  std::printf("%s: ATE %.3f%% of path, depth median rel error %.4f on %zu pixels, %zu keyframes\n", label,
              PercentOfPath(run.ate), depth_median, pixels, run.keyframes.size());
  EXPECT_EQ(run.tracked.size(), run.r.trajectory.size()) << "every frame tracked";
  EXPECT_LE(PercentOfPath(run.ate), kUniformSphereMaxAtePercent);
  EXPECT_GT(pixels, kMinDepthPixels);
  EXPECT_LE(depth_median, kMaxDepthMedian);
}

// The uniform sphere's seed 2 also missed the depth bar until the sixty-first round (5.65%: every
// keyframe's depth 3-9% too far for the path, the turn 0.982 of the truth). The feature adjustment of the
// keyframes (SlamOptions::final_feature_adjustment) pins the turn: here (two threads) 0.18% of path and
// 1.08% depth, prism-slam --threads 1 0.18% and 1.08% (README, sixty-first round).
TEST(SlamSystem, TheUniformSpheresSeed2IsWithinTheBar) {
  PrismSlamRun run;
  std::string why;
  if (!RunSeedAsPrismSlam(2, &run, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ASSERT_FALSE(HasFailure());
  ExpectWithinBothBars(run, "uniform sphere, seed 2");
}

// The uniform sphere's seed 4, the run furthest over the depth bar before the fifty-eighth round
// (10.7%): its ground beside the bright sphere took the sphere's outline into J through the local mean,
// a pattern that stays put in the image while the ground slides under it. With the dim side of the
// local mean's edges left out (DepthFilterOptions::max_local_mean_log_gradient, on in SlamOptions)
// prism-slam's keyframe depth is within 2.83% in the median (README, fifty-eighth round); 0.97% with the
// feature adjustment (sixty-first round).
TEST(SlamSystem, TheUniformSpheresSeed4DepthIsWithinTheBar) {
  PrismSlamRun run;
  std::string why;
  if (!RunSeedAsPrismSlam(4, &run, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ASSERT_FALSE(HasFailure());
  ExpectWithinBothBars(run, "uniform sphere, seed 4");
}

// The torus's seed 5, the other run over the depth bar until the sixty-first round (4.83%): the cast
// shadows of the co-moving lights (rendered without them it reached 1.54%) left the direct adjustments
// a turn 0.969 of the truth, with each keyframe's depth scale drifting 1.00 -> 0.91 along the arc. Their
// cost is nearly flat along that turn-for-depth direction; the feature adjustment's is not (here 0.12%
// of path and 1.30% depth; README, sixty-first round).
TEST(SlamSystem, TheTorussSeed5IsWithinBothBars) {
  PrismSlamRun run;
  std::string why;
  if (!RunSeedAsPrismSlam(5, &run, &why, SlamOptions(), "torus-textured-forward"))
    GTEST_SKIP() << "preset unavailable: " << why;
  ASSERT_FALSE(HasFailure());
  ExpectWithinBothBars(run, "torus, seed 5");
}

// The uniform sphere's forward start (outside the standard nine), seed 2: with the local mean's edge test
// in the first keyframe's depth (the default) prism-slam ends at 1.30% of path; without it there
// (SlamOptions::init_depth_edge_test false) at 0.50% (README, fifty-ninth round). There the edge test
// takes the ground beside the sphere from the first keyframe's depth; why the start is better with that
// ground kept was not isolated.
TEST(SlamSystem, TheUniformSpheresForwardStartWithoutTheEdgeTestInTheFirstDepth) {
  PrismSlamRun run;
  std::string why;
  SlamOptions options;
  options.init_depth_edge_test = false;
  if (!RunSeedAsPrismSlam(2, &run, &why, options, "sphere-uniform-forward"))
    GTEST_SKIP() << "preset unavailable: " << why;
  ASSERT_FALSE(HasFailure());
  ExpectTrackedWithinTheBar(run, "uniform sphere, forward start, seed 2");
}

// The start check on a start that fails it: the uniform bunny's seed 1 with the first start's
// initialisation from 6 frames and any parallax, checked against a limit of 0.05 (default 0.16). The
// first start's pairs spread by 0.077 (measured), so a second start with the default retry baseline runs
// beside it; it spreads by 0.033 and replaces it. (With the default options this seed starts well and
// passes the check, as every preset seed has since the thirty-sixth round.)
constexpr double kStartCheckAtePercent = 1.0;  // the bar

SlamOptions AStartThatFailsTheCheck() {
  SlamOptions options;
  options.start_check_keyframes = 6;
  options.init_track_normalised = false;
  options.init_min_feature_local_mean = 0;
  options.keyframe_max_rotation_deg = 15;
  options.init_min_frames = 6;
  options.init_min_parallax_fraction = 0.005;
  options.start_check_max_pair_spread = 0.05;
  return options;
}

TEST(SlamSystem, TheStartCheckReplacesAStartThatSpreadsMore) {
  Rendered r;
  std::string why;
  if (!Render("bunny-uniform-sideways", 150, 1, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  const SlamOptions options = AStartThatFailsTheCheck();
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, &pool);
  ASSERT_TRUE(slam.ok()) << slam.status();
  std::vector<SlamKeyframe> keyframes;
  int first_handed_out = -1;
  for (int i = 0; i < 150; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok()) << f.status();
    EXPECT_EQ(f->frame_id, i);
    for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) {
      if (first_handed_out < 0) first_handed_out = i;
      keyframes.push_back(std::move(k));
    }
  }
  const StartCheckReport check = (*slam)->start_check();
  for (SlamKeyframe& k : (*slam)->Finish()) keyframes.push_back(std::move(k));
  std::printf("start check: first spread %.4f, second %.4f, second kept %d; keyframes handed out from frame %d\n",
              check.first_spread, check.second_spread, check.second_kept ? 1 : 0, first_handed_out);
  EXPECT_TRUE(check.checked);
  EXPECT_TRUE(check.done);
  EXPECT_FALSE(check.passed);
  EXPECT_GT(check.first_spread, options.start_check_max_pair_spread);
  EXPECT_TRUE(check.retried);
  ASSERT_TRUE(check.second_checked);
  EXPECT_LE(check.second_spread, options.start_check_max_pair_spread);
  EXPECT_TRUE(check.second_kept);
  // The second start ran on its own thread: the frames did not wait for its replay.
  EXPECT_LT(check.second_frames_on_caller, 5);
  // Keyframes were held until the check was done, then handed out once each, in order, from the second
  // start.
  EXPECT_GT(first_handed_out, 0);
  ASSERT_EQ(static_cast<int>(keyframes.size()), (*slam)->num_keyframes());
  for (size_t k = 0; k < keyframes.size(); ++k) EXPECT_EQ(keyframes[k].id, static_cast<int>(k));
  const std::vector<SlamFrameResult> trajectory = (*slam)->Trajectory();
  ASSERT_EQ(trajectory.size(), 150u);
  Trajectory estimate;
  for (size_t i = 0; i < trajectory.size(); ++i) {
    EXPECT_EQ(trajectory[i].frame_id, static_cast<int64_t>(i));
    if (trajectory[i].state == SlamState::kTracking)
      estimate.push_back({trajectory[i].timestamp, trajectory[i].world_from_camera});
  }
  StatusOr<AteResult> ate = Sim3Ate(r.trajectory, estimate);
  ASSERT_TRUE(ate.ok()) << ate.status();
  const double ate_percent = PercentOfPath(*ate);
  std::printf("uniform bunny, seed 1, a start that fails the check: ATE %.3f%% of path after the final adjustment\n",
              ate_percent);
  EXPECT_LE(ate_percent, kStartCheckAtePercent);
}

// SlamOptions::start_check_async: the first start's pair shading scales and the second start on their own
// threads give the same run to the bit as inline, on a start that passes the check and on one that fails it
// (the second start kept; as in TheStartCheckReplacesAStartThatSpreadsMore). Only the frame the check
// closes at may move (later), and the second start's frames no longer pause the caller's.
TEST(SlamSystem, TheStartCheckOnItsThreadGivesTheSameRun) {
  Rendered r;
  std::string why;
  if (!Render("bunny-uniform-sideways", 150, 1, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  for (const bool failing : {false, true}) {
    SCOPED_TRACE(failing ? "a start that fails the check" : "a good start");
    struct Run {
      std::vector<SlamFrameResult> trajectory;
      std::vector<Sim3d> keyframe_poses;
      std::vector<SlamKeyframe> keyframes;
      StartCheckReport check;
      int first_handed_out = -1;
    };
    Run runs[2];
    for (const bool async : {false, true}) {
      SlamOptions options = failing ? AStartThatFailsTheCheck() : SlamOptions();
      options.start_check_async = async;
      StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, &pool);
      ASSERT_TRUE(slam.ok()) << slam.status();
      Run& run = runs[async];
      for (int i = 0; i < 150; ++i) {
        StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
        ASSERT_TRUE(f.ok()) << f.status();
        for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) {
          if (run.first_handed_out < 0) run.first_handed_out = i;
          run.keyframes.push_back(std::move(k));
        }
      }
      run.check = (*slam)->start_check();
      for (SlamKeyframe& k : (*slam)->Finish()) run.keyframes.push_back(std::move(k));
      run.trajectory = (*slam)->Trajectory();
      run.keyframe_poses = (*slam)->KeyframePoses();
    }
    const Run& inline_run = runs[0];
    const Run& async_run = runs[1];
    std::printf(
        "%s: first spread %.4f, second kept %d; check inline %.1f ms in the frames, on its thread %.1f ms in "
        "the frames and %.1f ms on the thread; keyframes handed out from frame %d inline, %d on the thread\n",
        failing ? "failing start" : "good start", async_run.check.first_spread, async_run.check.second_kept ? 1 : 0,
        1000 * inline_run.check.seconds, 1000 * async_run.check.seconds, 1000 * async_run.check.thread_seconds,
        inline_run.first_handed_out, async_run.first_handed_out);
    ASSERT_TRUE(inline_run.check.checked);
    EXPECT_EQ(inline_run.check.passed, !failing);
    EXPECT_EQ(inline_run.check.second_kept, failing);
    EXPECT_TRUE(async_run.check.checked);
    EXPECT_TRUE(async_run.check.done);
    EXPECT_EQ(async_run.check.first_spread, inline_run.check.first_spread);
    EXPECT_EQ(async_run.check.passed, inline_run.check.passed);
    EXPECT_EQ(async_run.check.retried, inline_run.check.retried);
    EXPECT_EQ(async_run.check.second_spread, inline_run.check.second_spread);
    EXPECT_EQ(async_run.check.second_kept, inline_run.check.second_kept);
    EXPECT_EQ(inline_run.check.thread_seconds, 0.0);
    EXPECT_GT(async_run.check.thread_seconds, 0.0);
    if (failing) {
      EXPECT_GT(inline_run.check.second_frames_on_caller, 30);
      EXPECT_LT(async_run.check.second_frames_on_caller, 5);
    }
    EXPECT_GE(async_run.first_handed_out, inline_run.first_handed_out);

    ASSERT_NO_FATAL_FAILURE(ExpectSamePoses(async_run.trajectory, async_run.keyframe_poses, inline_run.trajectory,
                                            inline_run.keyframe_poses));
    ASSERT_EQ(async_run.keyframes.size(), inline_run.keyframes.size());
    for (size_t k = 0; k < inline_run.keyframes.size(); ++k) {
      EXPECT_EQ(async_run.keyframes[k].id, inline_run.keyframes[k].id);
      EXPECT_EQ(cv::norm(async_run.keyframes[k].depth.inverse_depth, inline_run.keyframes[k].depth.inverse_depth,
                         cv::NORM_INF),
                0.0)
          << "keyframe " << k;
    }
  }
}

// SlamOptions::init_threads: the first keyframe's depth updates with the buffered frames (and their
// normalised images) on a pool of their own, on the SLAM's pool, or on its one thread give the same start
// to the bit: every frame's pose and the keyframes' depth. Also with a second refinement round
// (init_rounds = 2), which estimates the depth again from the seed.
TEST(SlamSystem, TheInitialisationOnTwoThreadsGivesTheSameStart) {
  Rendered r;
  std::string why;
  constexpr int kFrames = 24;  // initialised at frame 9
  if (!Render("bunny-uniform-sideways", kFrames, 1, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  for (const int rounds : {1, 2}) {
    SCOPED_TRACE("init_rounds " + std::to_string(rounds));
    struct Run {
      std::vector<SlamFrameResult> trajectory;
      std::vector<Sim3d> keyframe_poses;
      std::vector<SlamKeyframe> keyframes;
      double initialisation_s = 0;
    };
    // One thread; a pool of init_threads' own; the SLAM's pool of 2 (init_threads 1: it has enough).
    const struct {
      int init_threads;
      ThreadPool* pool;
      const char* what;
    } kinds[] = {{1, nullptr, "one thread"}, {2, nullptr, "its own 2 threads"}, {1, &pool, "the SLAM's pool"}};
    std::vector<Run> runs;
    for (const auto& kind : kinds) {
      SlamOptions options;
      options.init_rounds = rounds;
      options.init_threads = kind.init_threads;
      StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, kind.pool);
      ASSERT_TRUE(slam.ok()) << slam.status();
      Run run;
      int tracked = 0;
      for (int i = 0; i < kFrames; ++i) {
        StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
        ASSERT_TRUE(f.ok()) << f.status();
        tracked += f->state == SlamState::kTracking;
        for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) run.keyframes.push_back(std::move(k));
      }
      ASSERT_GT(tracked, 0) << kind.what << ": not initialised within " << kFrames << " frames";
      run.initialisation_s = (*slam)->timings().initialisation;
      for (SlamKeyframe& k : (*slam)->Finish()) run.keyframes.push_back(std::move(k));
      run.trajectory = (*slam)->Trajectory();
      run.keyframe_poses = (*slam)->KeyframePoses();
      std::printf("init_rounds %d, %s: initialisation %.1f ms, %zu keyframes\n", rounds, kind.what,
                  1000 * run.initialisation_s, run.keyframes.size());
      runs.push_back(std::move(run));
    }
    for (size_t k = 1; k < runs.size(); ++k) {
      SCOPED_TRACE(kinds[k].what);
      ASSERT_NO_FATAL_FAILURE(
          ExpectSamePoses(runs[k].trajectory, runs[k].keyframe_poses, runs[0].trajectory, runs[0].keyframe_poses));
      ASSERT_EQ(runs[k].keyframes.size(), runs[0].keyframes.size());
      for (size_t i = 0; i < runs[0].keyframes.size(); ++i) {
        EXPECT_EQ(
            cv::norm(runs[k].keyframes[i].depth.inverse_depth, runs[0].keyframes[i].depth.inverse_depth, cv::NORM_INF),
            0.0)
            << "keyframe " << i;
        EXPECT_EQ(cv::norm(runs[k].keyframes[i].depth.variance, runs[0].keyframes[i].depth.variance, cv::NORM_INF), 0.0)
            << "keyframe " << i;
      }
    }
  }
}

// With a pool of two, RefineKeyframeDepths refines the keyframes in parallel (each on one thread) and the
// final adjustments between its rounds run on the pool: the same depths, variances and poses to the bit
// as on one thread (prism-slam's defaults, two rounds).
TEST(SlamSystem, TheFinalRefinementOnTwoThreadsGivesTheSameDepths) {
  Rendered r;
  std::string why;
  if (!Render("sphere-uniform-sideways", 60, 1, &r, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  ThreadPool pool(2);
  SlamOptions options;
  options.final_refinement_rounds = 2;
  struct Run {
    std::vector<SlamKeyframe> keyframes;
    std::vector<SlamFrameResult> trajectory;
    std::vector<Sim3d> keyframe_poses;
  };
  std::vector<Run> runs;
  for (ThreadPool* p : {static_cast<ThreadPool*>(nullptr), &pool}) {
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options, p);
    ASSERT_TRUE(slam.ok()) << slam.status();
    Run run;
    ASSERT_NO_FATAL_FAILURE(RunAsPrismSlam(r, options, slam->get(), &run.keyframes));
    run.trajectory = (*slam)->Trajectory();
    run.keyframe_poses = (*slam)->KeyframePoses();
    runs.push_back(std::move(run));
  }
  ASSERT_GE(runs[0].keyframes.size(), 3u);
  ASSERT_NO_FATAL_FAILURE(
      ExpectSamePoses(runs[1].trajectory, runs[1].keyframe_poses, runs[0].trajectory, runs[0].keyframe_poses));
  ASSERT_EQ(runs[1].keyframes.size(), runs[0].keyframes.size());
  for (size_t i = 0; i < runs[0].keyframes.size(); ++i) {
    const InverseDepthMap& a = runs[0].keyframes[i].depth;
    const InverseDepthMap& b = runs[1].keyframes[i].depth;
    ASSERT_FALSE(a.inverse_depth.empty()) << "keyframe " << i;
    EXPECT_EQ(cv::norm(a.inverse_depth, b.inverse_depth, cv::NORM_INF), 0.0) << "keyframe " << i;
    EXPECT_EQ(cv::norm(a.variance, b.variance, cv::NORM_INF), 0.0) << "keyframe " << i;
  }
}

TEST(SlamSystem, RejectsBadInputAndReportsStates) {
  const RigCalibration rig = synth::MakeDefaultRig(128, 96);
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(rig, SlamOptions());
  ASSERT_TRUE(slam.ok()) << slam.status();
  // Wrong size and type: a clear error, nothing recorded.
  StatusOr<SlamFrameResult> bad = (*slam)->ProcessFrame(0.0, cv::Mat::zeros(96, 120, CV_8UC3));
  EXPECT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("128x96"), std::string::npos) << bad.status();
  EXPECT_FALSE((*slam)->ProcessFrame(0.0, cv::Mat::zeros(96, 128, CV_8UC1)).ok());
  EXPECT_TRUE((*slam)->Trajectory().empty());
  // Blank frames: stays initialising, says why, never crashes.
  for (int i = 0; i < 5; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(i / 30.0, cv::Mat::zeros(96, 128, CV_8UC3));
    ASSERT_TRUE(f.ok()) << f.status();
    EXPECT_EQ(f->state, SlamState::kInitializing);
    EXPECT_FALSE(f->message.empty());
  }
  EXPECT_EQ((*slam)->Trajectory().size(), 5u);
  EXPECT_TRUE((*slam)->Finish().empty());

  RigCalibration distorted = rig;
  distorted.camera.distortion[0] = 0.1;
  EXPECT_FALSE(SlamSystem::Create(distorted, SlamOptions()).ok());
  SlamOptions bad_options;
  bad_options.keyframe_distance_fraction = 0;
  EXPECT_FALSE(SlamSystem::Create(rig, bad_options).ok());
  bad_options = SlamOptions();
  bad_options.final_adjustment_max_keyframes = 2;
  EXPECT_FALSE(SlamSystem::Create(rig, bad_options).ok());
}

// After initialisation, a blank frame is reported lost (with the last good pose) and the next good
// frame is tracked or relocalised.
TEST(SlamSystem, ReportsLossAndRecovers) {
  Rendered r;
  std::string why;
  if (!Render("bunny-multicolor-forward", 50, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  // The start check off: the counts below are of one start (on this 50-frame bunny the first start's
  // pairs spread by 0.183, the check calls for a second start, and its counts would replace these).
  SlamOptions options;
  options.start_check_keyframes = 0;
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
  ASSERT_TRUE(slam.ok()) << slam.status();
  int i = 0, after_init = 0;  // ProcessFrame calls after the one that finished initialising
  bool initialised = false;
  for (; i < 40; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok()) << f.status();
    after_init += initialised;
    initialised = f->state != SlamState::kInitializing;
  }
  ASSERT_EQ((*slam)->Trajectory().back().state, SlamState::kTracking) << (*slam)->Trajectory().back().message;
  const cv::Mat blank(r.frames[0].rgb.size(), CV_8UC3, cv::Scalar(0, 0, 0));
  StatusOr<SlamFrameResult> lost = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s + 0.001, blank);
  ASSERT_TRUE(lost.ok());
  ++after_init;
  EXPECT_EQ(lost->state, SlamState::kLost);
  EXPECT_NE(lost->message.find("lost"), std::string::npos) << lost->message;
  for (; i < 50; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok());
    ++after_init;
    EXPECT_EQ(f->state, SlamState::kTracking) << "frame " << i << ": " << f->message;
  }
  // Every frame after initialisation reached the tracker (the blank one too); each tracked one updated
  // the depth (depth_update_interval 1), the lost one did not.
  const SlamTimings t = (*slam)->timings();
  EXPECT_EQ(t.tracked_frames, after_init);
  EXPECT_EQ(t.depth_updates, after_init - 1);
  EXPECT_GT(t.tracking, 0);
  EXPECT_GT(t.depth_update, 0);
  EXPECT_GT(t.keyframes, 0);
  EXPECT_GT(t.initialisation, 0);
  EXPECT_LE(t.keyframe_adjustment + t.loop_search, t.keyframes + t.relocalisation);
}

// SlamOptions::depth_update_interval: the stereo update runs on every third frame after a keyframe and
// on each frame that makes a keyframe; tracking goes on with every frame.
TEST(SlamSystem, UpdatesTheDepthOnEveryNthFrame) {
  Rendered r;
  std::string why;
  if (!Render("bunny-multicolor-forward", 40, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  SlamOptions options;
  options.depth_update_interval = 3;
  // The start check off: a second start that replaces the first brings its own timings (from its own
  // initialisation), which would not match the frames counted here from the first start's.
  options.start_check_keyframes = 0;
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
  ASSERT_TRUE(slam.ok()) << slam.status();
  int updates = 0, tracked = 0, since_update = 0;
  bool initialised = false;
  for (int i = 0; i < 40; ++i) {
    StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
    ASSERT_TRUE(f.ok()) << f.status();
    if (initialised) {
      ASSERT_EQ(f->state, SlamState::kTracking) << "frame " << i << ": " << f->message;
      ++tracked;
      // A relocalised frame becomes a keyframe without an update.
      const bool relocalised = f->message.find("relocalised") != std::string::npos;
      if (f->new_keyframe && !relocalised) {
        EXPECT_TRUE(f->depth_updated) << "frame " << i;
      }
      since_update = f->depth_updated || f->new_keyframe ? 0 : since_update + 1;
      EXPECT_LT(since_update, 3) << "frame " << i;
    } else {
      EXPECT_FALSE(f->depth_updated);
    }
    updates += f->depth_updated;
    initialised = f->state != SlamState::kInitializing;
  }
  ASSERT_TRUE(initialised);
  const SlamTimings t = (*slam)->timings();
  EXPECT_EQ(t.tracked_frames, tracked);
  EXPECT_EQ(t.depth_updates, updates);
  EXPECT_LT(updates, tracked * 2 / 3);
  options.depth_update_interval = 0;
  EXPECT_FALSE(SlamSystem::Create(r.setup.rig, options).ok());
}

// SlamOptions::mapping_budget_ms. A budget no mapping can meet leaves out every stereo update but those of
// the first tracked frame and of the frames that make keyframes (each counted in
// depth_updates_over_budget); tracking goes on with every frame, and the trajectory stays usable. A
// budget every mapping meets changes nothing: the same poses, bit for bit, as without one.
TEST(SlamSystem, AMappingBudgetLeavesOutUpdatesOnlyWhenOverIt) {
  // ATE with only the keyframe frames' updates, 60-frame bunny; measured 0.16% (0.17% without a budget).
  constexpr double kMaxAtePercentStarved = 2.0;
  constexpr int kFrames = 60;
  Rendered r;
  std::string why;
  if (!Render("bunny-multicolor-forward", kFrames, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  // The start check off, as in UpdatesTheDepthOnEveryNthFrame (its second start brings its own timings).
  // results: as ProcessFrame returned them (the initialisation's frames kInitializing); the poses are
  // scored from Trajectory() (those frames tracked again).
  auto run = [&](double budget_ms, std::vector<SlamFrameResult>* results, SlamTimings* timings,
                 std::vector<SlamFrameResult>* trajectory) {
    SlamOptions options;
    options.mapping_budget_ms = budget_ms;
    options.start_check_keyframes = 0;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    for (int i = 0; i < kFrames; ++i) {
      StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
      ASSERT_TRUE(f.ok()) << f.status();
      results->push_back(*f);
    }
    *timings = (*slam)->timings();
    *trajectory = (*slam)->Trajectory();
  };
  std::vector<SlamFrameResult> starved, unlimited, plain, starved_poses, unlimited_poses, plain_poses;
  SlamTimings t_starved, t_unlimited, t_plain;
  ASSERT_NO_FATAL_FAILURE(run(1e-9, &starved, &t_starved, &starved_poses));
  ASSERT_NO_FATAL_FAILURE(run(1e9, &unlimited, &t_unlimited, &unlimited_poses));
  ASSERT_NO_FATAL_FAILURE(run(0, &plain, &t_plain, &plain_poses));

  // The frames after the one that finishes the initialisation reach the tracker.
  int tracked = 0, updated = 0, keyframe_updates = 0;
  bool initialised = false;
  for (const SlamFrameResult& f : starved) {
    if (initialised) {
      EXPECT_EQ(f.state, SlamState::kTracking) << f.message;
      ++tracked;
      updated += f.depth_updated;
      keyframe_updates += f.depth_updated && f.new_keyframe;
    }
    initialised = f.state != SlamState::kInitializing;
  }
  std::printf("starved: %d tracked frames, %d updated (%d of them making keyframes), %d over budget\n", tracked,
              updated, keyframe_updates, t_starved.depth_updates_over_budget);
  EXPECT_EQ(tracked, t_starved.tracked_frames);
  EXPECT_EQ(updated, t_starved.depth_updates);
  EXPECT_LE(updated, keyframe_updates + 1);  // the first tracked frame's, when it makes no keyframe
  EXPECT_EQ(t_starved.depth_updates_over_budget, tracked - updated);
  EXPECT_GT(t_starved.depth_updates_over_budget, tracked / 2);

  const auto count_keyframes = [](const std::vector<SlamFrameResult>& results) {
    return std::count_if(results.begin(), results.end(), [](const SlamFrameResult& f) { return f.new_keyframe; });
  };
  std::printf("new keyframes: %d starved, %d without a budget\n", static_cast<int>(count_keyframes(starved)),
              static_cast<int>(count_keyframes(plain)));
  EXPECT_EQ(t_unlimited.depth_updates_over_budget, 0);
  EXPECT_EQ(t_unlimited.depth_updates, t_plain.depth_updates);
  ASSERT_EQ(unlimited_poses.size(), plain_poses.size());
  for (size_t i = 0; i < plain_poses.size(); ++i)
    EXPECT_TRUE(unlimited_poses[i].world_from_camera.translation == plain_poses[i].world_from_camera.translation) << i;

  for (const auto* poses : {&starved_poses, &plain_poses}) {
    StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses(*poses));
    ASSERT_TRUE(ate.ok()) << ate.status();
    std::printf("%s: ATE %.3f%% of the path\n", poses == &starved_poses ? "starved" : "no budget", PercentOfPath(*ate));
    if (poses == &starved_poses) {
      EXPECT_LT(PercentOfPath(*ate), kMaxAtePercentStarved);
    }
  }

  SlamOptions options;
  options.mapping_budget_ms = -1;
  EXPECT_FALSE(SlamSystem::Create(r.setup.rig, options).ok());
}

// SlamOptions::keyframe_adjustment_interval: the window adjustment runs after every second new keyframe
// only (at most (keyframes - 1) / 2 of them; with the default after more than half of them: the first
// keyframe has none, and a window with too few points is not adjusted).
TEST(SlamSystem, AdjustsTheWindowAfterEveryNthKeyframe) {
  Rendered r;
  std::string why;
  // 60 frames: with the 25x25 normalisation box (thirty-fifth round) the 40-frame bunny relocalised at
  // frames 31-37, and a keyframe made by a relocalisation has no adjustment.
  constexpr int kFrames = 60;
  if (!Render("bunny-multicolor-forward", kFrames, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  for (const int interval : {1, 2}) {
    SlamOptions options;
    options.keyframe_adjustment_interval = interval;
    options.start_check_keyframes = 0;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    for (int i = 0; i < kFrames; ++i)
      ASSERT_TRUE((*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb).ok());
    const int keyframes = (*slam)->num_keyframes(), adjustments = (*slam)->num_keyframe_adjustments();
    std::printf("interval %d: %d keyframes, %d window adjustments\n", interval, keyframes, adjustments);
    ASSERT_GE(keyframes, 5);
    if (interval == 1) {
      EXPECT_GT(adjustments, (keyframes - 1) / 2);
    } else {
      EXPECT_LE(adjustments, (keyframes - 1) / interval);
      EXPECT_GE(adjustments, 1);
    }
  }
  SlamOptions options;
  options.keyframe_adjustment_interval = 0;
  EXPECT_FALSE(SlamSystem::Create(r.setup.rig, options).ok());
}

// SlamOptions::keyframe_adjustment_async: the window adjustment on its own thread, applied when the next
// keyframe is made, gives exactly what the inline adjustment gives without the re-propagation (the one
// thing it leaves out): every frame's pose, every keyframe handed out (poses and depths) and the final
// keyframe poses, to the bit, whatever the thread's timing. Each keyframe is handed out at most one
// keyframe later than inline. A blank frame after frame kBlankAfter loses the tracking while an adjustment
// runs on its thread: the relocalisation applies it first, and the runs stay the same through it.
TEST(SlamSystem, AsyncWindowAdjustmentEqualsTheInlineOneWithoutRepropagation) {
  Rendered r;
  std::string why;
  constexpr int kFrames = 60;
  constexpr int kBlankAfter = 44;
  if (!Render("bunny-multicolor-forward", kFrames, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  struct Run {
    std::vector<SlamFrameResult> live;        // as ProcessFrame returned them
    std::vector<SlamKeyframe> keyframes;      // as handed out
    std::vector<int64_t> handed_out_at;       // the frame after which each was handed out
    std::vector<SlamFrameResult> trajectory;  // after Finish
    std::vector<Sim3d> keyframe_poses;
    SlamTimings timings;
    int adjustments = 0;
  };
  Run runs[2];
  for (const bool async : {false, true}) {
    SlamOptions options;
    options.keyframe_adjustment_async = async;
    options.keyframe_adjustment_max_wait_ms = -1;  // applied at the next keyframe, whatever the timing
    options.repropagate_after_adjustment = false;
    options.start_check_keyframes = 0;  // async from the first adjustment (inline while a check runs)
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    Run& run = runs[async];
    const cv::Mat blank(r.frames[0].rgb.size(), CV_8UC3, cv::Scalar(0, 0, 0));
    for (int i = 0; i < kFrames; ++i) {
      StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
      ASSERT_TRUE(f.ok()) << f.status();
      run.live.push_back(*f);
      if (i == kBlankAfter) {
        // Async: the newest keyframe's adjustment is still pending here (applied at the next keyframe).
        ASSERT_GE((*slam)->num_keyframe_adjustments(), 2) << "no adjustment before the loss";
        StatusOr<SlamFrameResult> lost = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s + 0.001, blank);
        ASSERT_TRUE(lost.ok()) << lost.status();
        EXPECT_EQ(lost->state, SlamState::kLost) << lost->message;
        run.live.push_back(*lost);
      }
      for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) {
        run.keyframes.push_back(std::move(k));
        run.handed_out_at.push_back(i);
      }
    }
    for (SlamKeyframe& k : (*slam)->Finish()) {
      run.keyframes.push_back(std::move(k));
      run.handed_out_at.push_back(kFrames);
    }
    run.trajectory = (*slam)->Trajectory();
    run.keyframe_poses = (*slam)->KeyframePoses();
    run.timings = (*slam)->timings();
    run.adjustments = (*slam)->num_keyframe_adjustments();
  }
  const Run& inline_run = runs[0];
  const Run& async_run = runs[1];
  std::printf(
      "%zu keyframes, %d window adjustments; adjustment %.1f ms inline, %.1f ms on its thread (%.2f ms "
      "waited for)\n",
      async_run.keyframe_poses.size(), async_run.adjustments, 1000 * inline_run.timings.keyframe_adjustment,
      1000 * async_run.timings.keyframe_adjustment_thread, 1000 * async_run.timings.keyframe_adjustment_wait);
  ASSERT_GE(inline_run.adjustments, 3);
  EXPECT_EQ(async_run.adjustments, inline_run.adjustments);
  EXPECT_GT(async_run.timings.keyframe_adjustment_thread, 0.0);
  EXPECT_EQ(inline_run.timings.keyframe_adjustment_thread, 0.0);

  ASSERT_EQ(async_run.live.size(), inline_run.live.size());
  for (size_t i = 0; i < inline_run.live.size(); ++i) {
    EXPECT_EQ(async_run.live[i].state, inline_run.live[i].state) << "frame " << i;
    EXPECT_EQ(async_run.live[i].keyframe_id, inline_run.live[i].keyframe_id) << "frame " << i;
    EXPECT_EQ(async_run.live[i].new_keyframe, inline_run.live[i].new_keyframe) << "frame " << i;
  }
  // The frame after the blank one is relocalised (tracked again).
  EXPECT_EQ(async_run.live[kBlankAfter + 2].state, SlamState::kTracking) << async_run.live[kBlankAfter + 2].message;
  ASSERT_NO_FATAL_FAILURE(ExpectSamePoses(async_run.trajectory, async_run.keyframe_poses, inline_run.trajectory,
                                          inline_run.keyframe_poses));

  ASSERT_EQ(async_run.keyframes.size(), inline_run.keyframes.size());
  int handed_out_before_finish = 0;
  for (size_t k = 0; k < inline_run.keyframes.size(); ++k) {
    const SlamKeyframe& a = async_run.keyframes[k];
    const SlamKeyframe& b = inline_run.keyframes[k];
    EXPECT_EQ(a.id, b.id);
    EXPECT_TRUE(SameSim3(a.world_from_keyframe, b.world_from_keyframe)) << "keyframe " << b.id;
    EXPECT_EQ(cv::norm(a.depth.inverse_depth, b.depth.inverse_depth, cv::NORM_INF), 0.0) << "keyframe " << b.id;
    EXPECT_GE(async_run.handed_out_at[k], inline_run.handed_out_at[k]);
    handed_out_before_finish += async_run.handed_out_at[k] < kFrames;
    // Held at most until the frame that makes the keyframe after the next one (or as long as inline: the
    // start check holds the first ones).
    if (k + 2 < inline_run.keyframes.size()) {
      const int64_t later = std::max(inline_run.keyframes[k + 2].frame_id, inline_run.handed_out_at[k]);
      EXPECT_LE(async_run.handed_out_at[k], later) << "keyframe " << b.id;
    }
  }
  EXPECT_GE(handed_out_before_finish, 2);
}

// SlamOptions::keyframe_adjustment_max_wait_ms = 0: a new keyframe never waits for the adjustment on its
// thread. With 8 px cells the adjustment takes several keyframes' time here, so keyframes are made while
// one runs, it is applied between keyframes and the owed one starts then. Every keyframe is still handed
// out once, in order, every frame tracked, and the trajectory within the bar and close to the one that
// waits (the same cells): keyframes made meanwhile move with the adjusted one.
constexpr double kNoWaitMaxAtePercent = 1.0;
constexpr double kNoWaitAteSlackPercent = 0.15;  // against waiting, as kRoundsAteSlackPercent
TEST(SlamSystem, KeyframesMadeWhileTheAdjustmentRunsFollowItWhenItIsApplied) {
  Rendered r;
  std::string why;
  constexpr int kFrames = 60;
  if (!Render("bunny-multicolor-forward", kFrames, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  double ate_percent[2] = {0, 0};
  for (const double max_wait_ms : {-1.0, 0.0}) {
    SlamOptions options;
    options.keyframe_window_cell_px = 8;
    options.start_check_keyframes = 0;  // async from the first adjustment
    options.keyframe_adjustment_max_wait_ms = max_wait_ms;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    std::vector<int> handed_out;
    for (int i = 0; i < kFrames; ++i) {
      StatusOr<SlamFrameResult> f = (*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb);
      ASSERT_TRUE(f.ok()) << f.status();
      EXPECT_NE(f->state, SlamState::kLost) << "frame " << i << ": " << f->message;
      for (const SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) handed_out.push_back(k.id);
    }
    for (const SlamKeyframe& k : (*slam)->Finish()) handed_out.push_back(k.id);
    const SlamTimings t = (*slam)->timings();
    const int keyframes = (*slam)->num_keyframes();
    StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses((*slam)->Trajectory()));
    ASSERT_TRUE(ate.ok()) << ate.status();
    const bool waits = max_wait_ms < 0;
    ate_percent[waits ? 0 : 1] = PercentOfPath(*ate);
    std::printf(
        "max wait %.0f ms: %d keyframes, %d window adjustments, %d keyframes made while one ran, %d started "
        "late; waited %.1f ms in all; ATE %.3f%% of the path\n",
        max_wait_ms, keyframes, (*slam)->num_keyframe_adjustments(), t.keyframes_made_before_adjustment,
        t.adjustments_started_late, 1000 * t.keyframe_adjustment_wait, PercentOfPath(*ate));
    ASSERT_GE(keyframes, 5);
    ASSERT_EQ(static_cast<int>(handed_out.size()), keyframes);
    for (int k = 0; k < keyframes; ++k) EXPECT_EQ(handed_out[static_cast<size_t>(k)], k);
    EXPECT_GE((*slam)->num_keyframe_adjustments(), 2);
    if (waits) {
      EXPECT_EQ(t.keyframes_made_before_adjustment, 0);
      EXPECT_EQ(t.adjustments_started_late, 0);
    } else {
      EXPECT_GE(t.keyframes_made_before_adjustment, 1) << "no keyframe was made while an adjustment ran";
      EXPECT_GE(t.adjustments_started_late, 1);
      EXPECT_LT((*slam)->num_keyframe_adjustments(), keyframes - 1);
    }
  }
  EXPECT_LE(ate_percent[1], kNoWaitMaxAtePercent);
  EXPECT_LE(ate_percent[1], ate_percent[0] + kNoWaitAteSlackPercent);
}

// The first keyframe's depth against the truth: the tilt c of log(estimated / true inverse depth) =
// a + b x + c y over the image (normalised coordinates, pixels within 20%), least squares.
double FirstDepthTilt(const SlamKeyframe& k, const cv::Mat& true_depth, const PinholeCamera& camera) {
  // The depth's unit is arbitrary: the cut below is around the median of log(d z), not around 0 (a unit
  // more than 22% from the truth's left no pixel, and a tilt of 0).
  std::vector<double> logs;
  for (int y = 0; y < true_depth.rows; ++y)
    for (int x = 0; x < true_depth.cols; ++x) {
      const float d = k.depth.inverse_depth.at<float>(y, x), z = true_depth.at<float>(y, x);
      if (d > 0 && z > 0) logs.push_back(std::log(d * z));
    }
  if (logs.empty()) return 0;
  std::nth_element(logs.begin(), logs.begin() + logs.size() / 2, logs.end());
  const double unit = logs[logs.size() / 2];
  Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (int y = 0; y < true_depth.rows; ++y)
    for (int x = 0; x < true_depth.cols; ++x) {
      const float d = k.depth.inverse_depth.at<float>(y, x), z = true_depth.at<float>(y, x);
      if (!(d > 0 && z > 0)) continue;
      const double e = std::log(d * z);
      if (std::abs(e - unit) > 0.2) continue;
      const Eigen::Vector3d j(1, (x - camera.cx) / camera.fx, (y - camera.cy) / camera.fy);
      a += j * j.transpose();
      b += j * e;
    }
  return a.ldlt().solve(b)(2);
}

// SlamOptions::init_rounds: on the torus (forward start over a ground plane; here its 120 degrees in
// 30 frames) the first depth map is tilted across the image's rows (the ground's relief wrong, which
// the tracker then trades for rotation). Estimating the depth again at the re-tracked poses
// straightens it. Measured: tilt 0.314 with one round, 0.120 with three; since the thirty-fifth round's
// 25x25 normalisation box 0.118 and 0.077; since the fifty-eighth round's local-mean edge test (and the
// cut around the median unit in FirstDepthTilt) -0.128 and -0.100. (The 150-frame preset, seed 1, before that: -0.271
// and -0.163, the error at the image's top and bottom edge 12.6% and 7.6%.)
TEST(SlamSystem, MoreInitialisationRoundsStraightenTheFirstDepth) {
  constexpr double kMinTilt = 0.1;       // |tilt, 1 round|: the premise; measured 0.128 (0.314 with 17x17)
  constexpr double kMaxTiltRatio = 0.8;  // |tilt, 3 rounds| / |tilt, 1 round|; measured 0.79 (0.38 with 17x17)
  Rendered r;
  std::string why;
  if (!Render("torus-textured-forward", 30, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  double tilt[2] = {0, 0};
  for (int run = 0; run < 2; ++run) {
    SlamOptions options;
    options.init_rounds = run == 0 ? 1 : 3;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    std::vector<SlamKeyframe> keyframes;
    for (int i = 0; i < 30; ++i) {
      ASSERT_TRUE((*slam)->ProcessFrame(r.trajectory[i].timestamp_s, r.frames[i].rgb).ok());
      for (SlamKeyframe& k : (*slam)->TakeFinishedKeyframes()) keyframes.push_back(std::move(k));
    }
    for (SlamKeyframe& k : (*slam)->Finish()) keyframes.push_back(std::move(k));
    ASSERT_FALSE(keyframes.empty());
    ASSERT_EQ(keyframes[0].id, 0);
    tilt[run] =
        FirstDepthTilt(keyframes[0], r.frames[static_cast<size_t>(keyframes[0].frame_id)].depth, r.setup.rig.camera);
    std::printf("init_rounds %d: first depth tilt %.4f\n", options.init_rounds, tilt[run]);
  }
  EXPECT_GT(std::abs(tilt[0]), kMinTilt) << "the one-round first depth is tilted (measured 0.128)";
  EXPECT_LT(std::abs(tilt[1]), kMaxTiltRatio * std::abs(tilt[0]));
}

// Keyframe 0 is the oldest of every adjustment it is in, which re-fits the depth unit of every keyframe
// but the oldest (held fixed: the gauge); so keyframe 0 keeps its initialisation's unit. Scored as each
// keyframe's own scale against the truth (median of true / estimated depth, through the trajectory's
// Sim(3) scale): |log(keyframe 0's scale / the others' median)|, on the dragon's first 60 frames. Measured
// again in the sixty-first round (the same figures with the sixtieth round's code; the ones this comment
// gave before, 0.046 / 0.006 / 0.002, were older rounds'):
// - without the refinement and the feature adjustment: 0.051 (0.936 against 0.985, 17 keyframes);
// - SlamOptions::refit_oldest_keyframe_scale (off): the unit re-fitted in the adjustments, 0.019;
// - SlamOptions::final_refinement_first_from_second (on by default), one refinement round: keyframe 0 seeded
//   from keyframe 1's depth, 0.018;
// - the defaults without the refinement: the feature adjustment (SlamOptions::final_feature_adjustment)
//   re-fits every keyframe's unit to its tracks, keyframe 0's too: 0.013 (1.016 against 1.003).
// The first three runs leave the feature adjustment out.
constexpr double kMinFirstScaleOffsetWithoutRefit = 0.03;
constexpr double kMaxFirstScaleOffset = 0.02;
TEST(SlamSystem, TheFirstKeyframesDepthUnitIsFittedLikeTheOthers) {
  Rendered r;
  std::string why;
  if (!Render("dragon-multicolor-sideways", 60, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  // Without any, with the re-fit, with the refinement's seed (no feature adjustment); the defaults.
  double offset[4] = {0, 0, 0, 0};
  for (int run = 0; run < 4; ++run) {
    SlamOptions options;
    if (run < 3) {
      options.final_feature_adjustment = false;
      options.refit_oldest_keyframe_scale = run == 1;
      options.final_refinement_first_from_second = run == 2;
    }
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    std::vector<SlamKeyframe> keyframes;
    ASSERT_NO_FATAL_FAILURE(RunAndFinish(r, slam->get(), &keyframes));
    ASSERT_GE(keyframes.size(), 4u);
    ASSERT_EQ(keyframes[0].id, 0);
    if (run == 2)
      (*slam)->RefineKeyframeDepths(options.final_refinement_neighbours, options.final_refinement_relative_sigma,
                                    /*rounds=*/1, &keyframes);
    StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses((*slam)->Trajectory()));
    ASSERT_TRUE(ate.ok()) << ate.status();
    const std::vector<Sim3d> poses = (*slam)->KeyframePoses();
    std::vector<double> scales;  // per keyframe: median of true / estimated depth
    for (const SlamKeyframe& k : keyframes) {
      const double unit = ate->gt_from_est.scale * poses[static_cast<size_t>(k.id)].scale;
      const cv::Mat& gt = r.frames[static_cast<size_t>(k.frame_id)].depth;
      std::vector<double> ratios;
      for (int y = 0; y < gt.rows; ++y)
        for (int x = 0; x < gt.cols; ++x) {
          const float d = k.depth.inverse_depth.at<float>(y, x), z = gt.at<float>(y, x);
          if (d > 0 && z > 0) ratios.push_back(z * d / unit);
        }
      ASSERT_GT(ratios.size(), 1000u) << "keyframe " << k.id;
      std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
      scales.push_back(ratios[ratios.size() / 2]);
    }
    std::vector<double> others(scales.begin() + 1, scales.end());
    std::nth_element(others.begin(), others.begin() + others.size() / 2, others.end());
    offset[run] = std::abs(std::log(scales[0] / others[others.size() / 2]));
    std::printf("run %d: first keyframe's scale %.4f, the others' median %.4f (%zu keyframes)\n", run, scales[0],
                others[others.size() / 2], keyframes.size());
  }
  EXPECT_GT(offset[0], kMinFirstScaleOffsetWithoutRefit) << "the unit is left as the initialisation gave it";
  EXPECT_LT(offset[1], kMaxFirstScaleOffset);
  EXPECT_LT(offset[2], kMaxFirstScaleOffset);
  EXPECT_LT(offset[3], kMaxFirstScaleOffset) << "the feature adjustment re-fits keyframe 0's unit";
}

// SlamOptions::feature_adjustment_max_keyframes: beyond the direct final adjustment's limit
// (final_adjustment_max_keyframes, lowered here to 3 on the dragon's first 60 frames) the feature
// adjustment runs alone, at Finish and in each refinement round; with its own limit as low, nothing runs
// and the keyframes keep the window adjustment's poses. Measured: 0.092% of path with the features alone
// (17 keyframes, 1889 tracks) against 0.338% without.
constexpr double kMaxAteRatioFeaturesAlone = 0.5;  // ATE with the features alone / without

TEST(SlamSystem, TheFeatureAdjustmentRunsAloneBeyondTheDirectAdjustmentsLimit) {
  Rendered r;
  std::string why;
  if (!Render("dragon-multicolor-sideways", 60, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  double ate_percent[2] = {0, 0};
  std::vector<Sim3d> poses[2];
  for (int run = 0; run < 2; ++run) {
    SlamOptions options;
    options.final_adjustment_max_keyframes = 3;
    options.feature_adjustment_max_keyframes = run == 0 ? 64 : 3;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    std::vector<SlamKeyframe> keyframes;
    const int adjustments_before = (*slam)->num_keyframe_adjustments();
    ASSERT_NO_FATAL_FAILURE(RunAndFinish(r, slam->get(), &keyframes));
    ASSERT_GT(keyframes.size(), 3u);
    const int adjustments_at_finish = (*slam)->num_keyframe_adjustments();
    EXPECT_GT(adjustments_at_finish, adjustments_before) << "the window adjustments ran";
    FeatureAdjustmentReport report = (*slam)->feature_adjustment();
    EXPECT_EQ(report.ran, run == 0);
    EXPECT_EQ(report.applied, run == 0) << report.error;
    EXPECT_EQ(report.runs, run == 0 ? 1 : 0);
    (*slam)->RefineKeyframeDepths(options.final_refinement_neighbours, options.final_refinement_relative_sigma,
                                  /*rounds=*/2, &keyframes);
    report = (*slam)->feature_adjustment();
    EXPECT_EQ(report.runs, run == 0 ? 2 : 0) << "once more in the second refinement round";
    EXPECT_EQ((*slam)->num_keyframe_adjustments(), adjustments_at_finish) << "no direct final adjustment";
    StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses((*slam)->Trajectory()));
    ASSERT_TRUE(ate.ok()) << ate.status();
    ate_percent[run] = PercentOfPath(*ate);
    poses[run] = (*slam)->KeyframePoses();
    std::printf(
        "feature_adjustment_max_keyframes %d: ATE %.3f%% of path, %zu keyframes, %d feature runs, "
        "%d tracks\n",
        options.feature_adjustment_max_keyframes, ate_percent[run], keyframes.size(), report.runs,
        report.summary.tracks);
  }
  ASSERT_EQ(poses[0].size(), poses[1].size());
  double moved = 0;
  for (size_t k = 0; k < poses[0].size(); ++k)
    moved = std::max(moved, (poses[0][k].translation - poses[1][k].translation).norm());
  EXPECT_GT(moved, 0.0) << "the features moved the keyframes";
  EXPECT_LE(ate_percent[0], kMaxAteRatioFeaturesAlone * ate_percent[1]);
}

// SlamOptions::distribute_keyframe_corrections: each keyframe's frames take their share of the difference
// between the next keyframe's adjusted pose and the pose it was tracked at. On the dragon's first 60
// frames (Finish's final adjustment, no refinement):
// - with it, the frame each keyframe was made from lies at that keyframe's pose (exactly, by construction);
//   without it up to 0.0133 world units away;
// - the Sim(3) ATE: 0.222% of the path with it against 0.369% without (the keyframes the same).
constexpr double kMaxKeyframeFrameGap = 1e-9;         // world units, with the corrections
constexpr double kMinKeyframeFrameGapWithout = 1e-3;  // world units, without
constexpr double kMaxAteRatioWithCorrections = 0.9;   // ATE with / without

TEST(SlamSystem, FramesTakeTheirShareOfTheNextKeyframesCorrection) {
  Rendered r;
  std::string why;
  if (!Render("dragon-multicolor-sideways", 60, /*supersampling=*/1, &r, &why))
    GTEST_SKIP() << "preset unavailable: " << why;
  double gap[2] = {0, 0}, ate_percent[2] = {0, 0};  // without, with
  std::vector<Sim3d> keyframe_poses[2];
  for (int run = 0; run < 2; ++run) {
    SlamOptions options;
    options.distribute_keyframe_corrections = run == 1;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(r.setup.rig, options);
    ASSERT_TRUE(slam.ok()) << slam.status();
    std::vector<SlamKeyframe> keyframes;
    ASSERT_NO_FATAL_FAILURE(RunAndFinish(r, slam->get(), &keyframes));
    ASSERT_GE(keyframes.size(), 4u);
    const std::vector<SlamFrameResult> frames = (*slam)->Trajectory();
    keyframe_poses[run] = (*slam)->KeyframePoses();
    for (const SlamKeyframe& k : keyframes) {
      if (k.id == 0) continue;
      const SlamFrameResult& f = frames[static_cast<size_t>(k.frame_id)];
      ASSERT_EQ(f.state, SlamState::kTracking);
      ASSERT_EQ(f.keyframe_id, k.id - 1) << "keyframe " << k.id << " was made from a frame tracked on the previous one";
      const Sim3d& pose = keyframe_poses[run][static_cast<size_t>(k.id)];
      gap[run] = std::max(gap[run], (f.world_from_camera.translation - pose.translation).norm());
    }
    StatusOr<AteResult> ate = Sim3Ate(r.trajectory, TrackedPoses(frames));
    ASSERT_TRUE(ate.ok()) << ate.status();
    ate_percent[run] = PercentOfPath(*ate);
    std::printf("run %d: keyframe frames off their keyframes by up to %.6f, ATE %.4f%% (%zu keyframes)\n", run,
                gap[run], ate_percent[run], keyframes.size());
  }
  ASSERT_EQ(keyframe_poses[0].size(), keyframe_poses[1].size());
  for (size_t k = 0; k < keyframe_poses[0].size(); ++k)
    EXPECT_EQ(keyframe_poses[0][k].translation, keyframe_poses[1][k].translation) << "the keyframes do not move";
  EXPECT_GT(gap[0], kMinKeyframeFrameGapWithout);
  EXPECT_LT(gap[1], kMaxKeyframeFrameGap);
  EXPECT_LT(ate_percent[1], kMaxAteRatioWithCorrections * ate_percent[0]);
}

}  // namespace
}  // namespace prism
