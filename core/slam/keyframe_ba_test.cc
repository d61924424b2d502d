#include "core/slam/keyframe_ba.h"

#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/slam/depth_filter.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// Four keyframes 12 frames apart on a prism-synth preset (about the spacing SlamSystem makes), with
// ground-truth poses (metres) and points taken from the ground-truth depth.
struct Window {
  DirectBaProblem truth;
  std::vector<cv::Mat> rgb, raw_grey;  // for the relit residual
  RigCalibration rig;
  bool ok = false;
  std::string why;
};

Window MakeWindow(const std::string& preset) {
  Window w;
  synth::PresetOptions o;
  o.frames = 60;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    w.why = setup.status().ToString();
    return w;
  }
  const Trajectory traj = synth::MakeTrajectory(setup->trajectory);
  ThreadPool pool;
  w.truth.camera = setup->rig.camera;
  const DepthFilterOptions depth_options;
  for (int k = 0; k < 4; ++k) {
    const int frame = 12 + 12 * k;
    const synth::RenderedFrame f = synth::RenderFrame(setup->scene, setup->rig, traj[frame].world_from_camera,
                                                      setup->render, 1000003ull + frame, &pool);
    const Rigid3d& pose = traj[frame].world_from_camera;
    w.truth.world_from_keyframe.push_back(Sim3d(1.0, pose.rotation, pose.translation));
    cv::Mat j, mean;
    KeyframeDepth::NormalisedGrey(f.rgb, depth_options, &j, &mean);
    w.truth.grey_j.push_back(j);
    w.rgb.push_back(f.rgb);
    w.raw_grey.push_back(MeanOfChannels(f.rgb));
    // One point per 12x12 cell: the strongest gradient with a surface (as SlamSystem picks them).
    cv::Mat inverse_depth = cv::Mat::zeros(f.depth.size(), CV_32F);
    for (int y = 0; y < f.depth.rows; ++y)
      for (int x = 0; x < f.depth.cols; ++x)
        if (f.depth.at<float>(y, x) > 0) inverse_depth.at<float>(y, x) = 1.0f / f.depth.at<float>(y, x);
    const float min_mean = static_cast<float>(depth_options.min_local_mean);
    // Gradient^2 floor 36: flat or dark cells give no point.
    SelectCellPoints(
        j, inverse_depth, k, 12, 36.0f, [&](int x, int y) { return mean.at<float>(y, x) >= min_mean; },
        &w.truth.points);
  }
  w.rig = setup->rig;
  w.ok = true;
  return w;
}

// The same window with the relit residual (the world is in metres: 1 metre per world unit).
DirectBaProblem Relit(const Window& w, const DirectBaProblem& start) {
  DirectBaProblem p = start;
  p.grey_j = w.raw_grey;
  p.relit.rig = &w.rig;
  p.relit.metres_per_world_unit = 1.0;
  p.relit.rgb = w.rgb;
  return p;
}

double Spacing(const DirectBaProblem& p) {
  return (p.world_from_keyframe[1].translation - p.world_from_keyframe[0].translation).norm();
}

// Largest camera-centre error of keyframes 2.. against the truth, as a fraction of the keyframe spacing.
double CentreError(const DirectBaProblem& p, const DirectBaProblem& truth) {
  double worst = 0;
  for (size_t k = 2; k < p.world_from_keyframe.size(); ++k)
    worst = std::max(worst, (p.world_from_keyframe[k].translation - truth.world_from_keyframe[k].translation).norm() /
                                Spacing(truth));
  return worst;
}

// Keyframe 3's distance from keyframe 0 over the truth's: the scale the window carries forward.
double ScaleRatio(const DirectBaProblem& p, const DirectBaProblem& truth) {
  return (p.world_from_keyframe[3].translation - p.world_from_keyframe[0].translation).norm() /
         (truth.world_from_keyframe[3].translation - truth.world_from_keyframe[0].translation).norm();
}

// Keyframes 2 and 3 moved 3% towards keyframe 0 (scale drift) and 5% of the spacing sideways, rotated
// by 0.2 deg; every inverse depth 5% off at random.
DirectBaProblem PerturbedStart(const Window& w) {
  DirectBaProblem start = w.truth;
  const Eigen::Vector3d c0 = w.truth.world_from_keyframe[0].translation;
  const Eigen::Vector3d side =
      (w.truth.world_from_keyframe[1].rotation * Eigen::Vector3d::UnitY()) * 0.05 * Spacing(w.truth);
  for (int k = 2; k < 4; ++k) {
    Sim3d& p = start.world_from_keyframe[static_cast<size_t>(k)];
    p.translation = c0 + 0.97 * (p.translation - c0) + side;
    p.rotation = p.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(0.2 * M_PI / 180, Eigen::Vector3d::UnitX()));
  }
  std::mt19937 rng(7);
  std::normal_distribution<float> noise(0.0f, 0.05f);
  for (DirectBaPoint& p : start.points) p.inverse_depth *= std::exp(noise(rng));
  return start;
}

// Tolerances from measurement (printed). From the truth, the adjustment moves keyframes 2-3 by 1-5% of
// the keyframe spacing and changes the scale by up to 1.2%: the normalised grey level still changes
// with the co-moving lights between keyframes, so the photometric minimum is near, not at, the truth.
// From a start 3% short in scale and 5% of the spacing sideways it lowers the photometric error but
// does not find the truth again (the scale stays 2-4% short, the centres 8-12% of the spacing off): on
// these dark-room images the scale is only weakly observable in the photometric error between
// keyframes. SlamSystem uses the adjustment for the small corrections it makes (see the README).
constexpr double kMaxCentreErrorFromTruth = 0.08;  // of the spacing
constexpr double kMaxScaleErrorFromTruth = 0.015;
constexpr double kMaxCentreErrorGrowth = 0.03;  // of the spacing, from the perturbed start

class KeyframeBaPresetTest : public ::testing::TestWithParam<std::string> {};

TEST_P(KeyframeBaPresetTest, StaysNearTheTruthAndLowersTheErrorFromAPerturbedStart) {
  const Window w = MakeWindow(GetParam());
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  ASSERT_GT(w.truth.points.size(), 500u);

  DirectBaProblem from_truth = w.truth;
  StatusOr<DirectBaSummary> s0 = AdjustKeyframeWindowDirect(DirectBaOptions(), &from_truth);
  ASSERT_TRUE(s0.ok()) << s0.status();
  const double truth_drift = CentreError(from_truth, w.truth);
  std::printf("%s from the truth: centre error %.4f of the spacing, scale %.4f, RMS %.2f -> %.2f\n", GetParam().c_str(),
              truth_drift, ScaleRatio(from_truth, w.truth), s0->initial_rms, s0->final_rms);
  EXPECT_LE(truth_drift, kMaxCentreErrorFromTruth);
  EXPECT_NEAR(ScaleRatio(from_truth, w.truth), 1.0, kMaxScaleErrorFromTruth);
  EXPECT_LT(s0->final_rms, s0->initial_rms);

  DirectBaProblem start = PerturbedStart(w);
  const Eigen::Vector3d c0 = w.truth.world_from_keyframe[0].translation;
  const double start_error = CentreError(start, w.truth);
  StatusOr<DirectBaSummary> s1 = AdjustKeyframeWindowDirect(DirectBaOptions(), &start);
  ASSERT_TRUE(s1.ok()) << s1.status();
  const double end_error = CentreError(start, w.truth);
  std::printf("%s perturbed: centre error %.4f -> %.4f of the spacing, scale 0.97 -> %.4f, RMS %.2f -> %.2f\n",
              GetParam().c_str(), start_error, end_error, ScaleRatio(start, w.truth), s1->initial_rms, s1->final_rms);
  EXPECT_LE(end_error, start_error + kMaxCentreErrorGrowth);
  EXPECT_LT(s1->final_rms, s1->initial_rms);
  // The gauge: keyframe 0 does not move, keyframe 1 not along the baseline.
  EXPECT_LT((start.world_from_keyframe[0].translation - c0).norm(), 1e-12);
  const Eigen::Vector3d b = (w.truth.world_from_keyframe[1].translation - c0).normalized();
  EXPECT_LT(std::abs(b.dot(start.world_from_keyframe[1].translation - w.truth.world_from_keyframe[1].translation)),
            1e-6 * Spacing(w.truth));
}

INSTANTIATE_TEST_SUITE_P(Presets, KeyframeBaPresetTest,
                         ::testing::Values("sphere-multicolor-sideways", "bunny-uniform-sideways",
                                           "relief-uniform-sideways", "boxes-multicolor-forward"),
                         [](const ::testing::TestParamInfo<std::string>& info) {
                           std::string n = info.param;
                           for (char& c : n)
                             if (c == '-') c = '_';
                           return n;
                         });

// The gain-ratio damping (DirectBaOptions::gain_ratio_damping) against the fixed factors, with
// SlamSystem's window settings from the perturbed start: no more cost evaluations on any window, fewer
// on at least one, and as low a final cost within kGainRatioMaxRmsIncrease (relative RMS).
constexpr double kGainRatioMaxRmsIncrease = 0.01;

TEST(KeyframeBa, TheGainRatioDampingEvaluatesTheCostLessOften) {
  int windows = 0, fewer = 0;
  for (const char* preset : {"sphere-multicolor-sideways", "bunny-uniform-sideways", "relief-uniform-sideways",
                             "boxes-multicolor-forward"}) {
    const Window w = MakeWindow(preset);
    if (!w.ok) continue;
    ++windows;
    DirectBaOptions options;
    options.huber = 4.0;
    options.max_iterations = 6;
    DirectBaProblem fixed = PerturbedStart(w);
    StatusOr<DirectBaSummary> sf = AdjustKeyframeWindowDirect(options, &fixed);
    ASSERT_TRUE(sf.ok()) << sf.status();
    options.gain_ratio_damping = true;
    DirectBaProblem gain = PerturbedStart(w);
    StatusOr<DirectBaSummary> sg = AdjustKeyframeWindowDirect(options, &gain);
    ASSERT_TRUE(sg.ok()) << sg.status();
    std::printf("%s: evaluations %d -> %d, iterations %d -> %d, final RMS %.4f -> %.4f, centre error %.4f -> %.4f\n",
                preset, sf->evaluations, sg->evaluations, sf->iterations, sg->iterations, sf->final_rms, sg->final_rms,
                CentreError(fixed, w.truth), CentreError(gain, w.truth));
    EXPECT_LE(sg->evaluations, sf->evaluations) << preset;
    fewer += sg->evaluations < sf->evaluations;
    EXPECT_LE(sg->final_rms, sf->final_rms * (1 + kGainRatioMaxRmsIncrease)) << preset;
  }
  if (windows == 0) GTEST_SKIP() << "presets unavailable";
  EXPECT_GE(fewer, 1);
}

// The gradient-dependent residual scale (DirectBaOptions::gradient_weight_c) with SlamSystem's window
// settings, from the perturbed start on the uniform sphere, whose only texture is its silhouette and the
// shading: measured scale 0.967 -> 0.988 and centre error 0.109 -> 0.064 of the spacing (c = 20; c = 10
// and 40 gave 0.973 and 0.977). On the other presets' windows it moves the results by about as much
// either way (see the README).
constexpr double kGradientWeightMaxScaleError = 0.02;
constexpr double kGradientWeightMaxCentreError = 0.08;  // of the spacing

TEST(KeyframeBa, TheGradientWeightRecoversMoreOfTheScaleOnTheUniformSphere) {
  const Window w = MakeWindow("sphere-uniform-sideways");
  ASSERT_TRUE(w.ok) << w.why;
  DirectBaOptions options;
  options.huber = 4.0;
  options.max_iterations = 6;
  options.gradient_weight_c = 0.0;
  DirectBaProblem unweighted = PerturbedStart(w);
  ASSERT_TRUE(AdjustKeyframeWindowDirect(options, &unweighted).ok());
  options.gradient_weight_c = 20.0;
  DirectBaProblem weighted = PerturbedStart(w);
  ASSERT_TRUE(AdjustKeyframeWindowDirect(options, &weighted).ok());
  std::printf("perturbed: scale 0.97 -> weighted %.4f / unweighted %.4f, centre error -> %.4f / %.4f of the spacing\n",
              ScaleRatio(weighted, w.truth), ScaleRatio(unweighted, w.truth), CentreError(weighted, w.truth),
              CentreError(unweighted, w.truth));
  EXPECT_NEAR(ScaleRatio(weighted, w.truth), 1.0, kGradientWeightMaxScaleError);
  EXPECT_LE(CentreError(weighted, w.truth), kGradientWeightMaxCentreError);
  EXPECT_LT(std::abs(ScaleRatio(weighted, w.truth) - 1), std::abs(ScaleRatio(unweighted, w.truth) - 1));
  EXPECT_LT(CentreError(weighted, w.truth), CentreError(unweighted, w.truth));
  // Bad input: a negative c.
  options.gradient_weight_c = -1.0;
  DirectBaProblem bad = PerturbedStart(w);
  EXPECT_FALSE(AdjustKeyframeWindowDirect(options, &bad).ok());
}

// Two adjustments of the same start agree to the last bit: every keyframe pose, inverse depth and
// inlier flag (`what` names the comparison).
void ExpectSameAdjustment(const DirectBaProblem& a, const DirectBaProblem& b, const std::string& what) {
  ASSERT_EQ(a.world_from_keyframe.size(), b.world_from_keyframe.size()) << what;
  for (size_t k = 0; k < a.world_from_keyframe.size(); ++k) {
    EXPECT_EQ(a.world_from_keyframe[k].rotation.coeffs(), b.world_from_keyframe[k].rotation.coeffs())
        << "keyframe " << k << ", " << what;
    EXPECT_EQ(a.world_from_keyframe[k].translation, b.world_from_keyframe[k].translation)
        << "keyframe " << k << ", " << what;
    EXPECT_EQ(a.world_from_keyframe[k].scale, b.world_from_keyframe[k].scale) << "keyframe " << k << ", " << what;
  }
  ASSERT_EQ(a.points.size(), b.points.size()) << what;
  int differing = 0;
  for (size_t i = 0; i < a.points.size(); ++i)
    differing += a.points[i].inverse_depth != b.points[i].inverse_depth || a.points[i].ok != b.points[i].ok;
  EXPECT_EQ(differing, 0) << what;
}

// With a pool the residuals are linearised and evaluated target by target in parallel, and every sum is
// still formed in the one-thread order: the same poses, inverse depths and summary to the last bit.
TEST(KeyframeBa, GivesTheSameResultToTheLastBitWithAPool) {
  const Window w = MakeWindow("boxes-multicolor-forward");
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  const DirectBaProblem start = PerturbedStart(w);
  DirectBaProblem serial = start;
  StatusOr<DirectBaSummary> s_serial = AdjustKeyframeWindowDirect(DirectBaOptions(), &serial);
  ASSERT_TRUE(s_serial.ok()) << s_serial.status();
  for (int threads : {2, 3}) {
    ThreadPool pool(threads);
    DirectBaProblem parallel = start;
    StatusOr<DirectBaSummary> s_parallel = AdjustKeyframeWindowDirect(DirectBaOptions(), &parallel, &pool);
    ASSERT_TRUE(s_parallel.ok()) << s_parallel.status();
    EXPECT_EQ(s_parallel->iterations, s_serial->iterations);
    EXPECT_EQ(s_parallel->residuals, s_serial->residuals);
    EXPECT_EQ(s_parallel->initial_rms, s_serial->initial_rms);
    EXPECT_EQ(s_parallel->final_rms, s_serial->final_rms);
    ExpectSameAdjustment(serial, parallel, std::to_string(threads) + " threads");
  }
  // The adjustment moved the keyframes (the comparison above is of a real solve).
  EXPECT_GT((serial.world_from_keyframe[3].translation - start.world_from_keyframe[3].translation).norm(), 0.0);
}

// DirectBaOptions::linearise_from_evaluation: the linearisation takes the projections and image reads of
// the evaluation at its state, so it reads fewer images and gives the same result to the last bit: with
// the defaults, SlamSystem's window settings (6 iterations, gain-ratio damping) and two pyramid levels
// (the reads of a coarser level are not reused at the next), with and without a pool.
TEST(KeyframeBa, LinearisesFromTheEvaluationToTheLastBit) {
  const Window w = MakeWindow("boxes-multicolor-forward");
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  const DirectBaProblem start = PerturbedStart(w);
  DirectBaOptions window;
  window.huber = 4.0;
  window.max_iterations = 6;
  window.gain_ratio_damping = true;
  DirectBaOptions two_levels = window;
  two_levels.pyramid_levels = 2;
  ThreadPool pool(2);
  int setting = 0;
  for (DirectBaOptions options : {DirectBaOptions(), window, two_levels}) {
    for (ThreadPool* p : {static_cast<ThreadPool*>(nullptr), &pool}) {
      const std::string what = "setting " + std::to_string(setting) + (p ? ", 2 threads" : ", 1 thread");
      options.linearise_from_evaluation = false;
      DirectBaProblem read = start;
      StatusOr<DirectBaSummary> s_read = AdjustKeyframeWindowDirect(options, &read, p);
      ASSERT_TRUE(s_read.ok()) << s_read.status();
      options.linearise_from_evaluation = true;
      DirectBaProblem kept = start;
      StatusOr<DirectBaSummary> s_kept = AdjustKeyframeWindowDirect(options, &kept, p);
      ASSERT_TRUE(s_kept.ok()) << s_kept.status();
      std::printf("%s: image samples %lld -> %lld (%d evaluations, %d iterations)\n", what.c_str(),
                  s_read->image_samples, s_kept->image_samples, s_kept->evaluations, s_kept->iterations);
      EXPECT_EQ(s_kept->iterations, s_read->iterations) << what;
      EXPECT_EQ(s_kept->evaluations, s_read->evaluations) << what;
      EXPECT_EQ(s_kept->residuals, s_read->residuals) << what;
      EXPECT_EQ(s_kept->initial_rms, s_read->initial_rms) << what;
      EXPECT_EQ(s_kept->final_rms, s_read->final_rms) << what;
      EXPECT_LT(s_kept->image_samples, s_read->image_samples) << what;
      ExpectSameAdjustment(read, kept, what);
      EXPECT_GT((kept.world_from_keyframe[3].translation - start.world_from_keyframe[3].translation).norm(), 0.0);
    }
    ++setting;
  }
}

// The relit residual (DirectBaRelit: the co-moving lights' shading change predicted from the rig under a
// grey albedo) on the same windows, against the J residual. Measured (printed), from the truth: keyframes
// 2-3 move by 1.9 / 1.5 / 0.8% of the spacing on the uniform sphere / uniform bunny / uniform relief
// (J: 2.1-4.6%); on the forward torus window both drift (relit 11-23% with any albedo colour tried,
// so it is not in the list). From the perturbed start (3% short in scale) only the uniform sphere is
// clearly better: relit ends 4.2% of the spacing off with the scale 1.1% short, J 9.7% and 2.8% short;
// on the uniform bunny and relief relit ends as far off as J or further (15 / 12% against 12 / 12%).
// In the SLAM's final adjustment it was measured and not kept (see the README).
constexpr double kRelitMaxCentreErrorFromTruth = 0.03;  // of the spacing
constexpr double kRelitMaxScaleErrorFromTruth = 0.008;

class RelitKeyframeBaPresetTest : public ::testing::TestWithParam<std::string> {};

TEST_P(RelitKeyframeBaPresetTest, StaysNearerTheTruthThanJ) {
  const Window w = MakeWindow(GetParam());
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  DirectBaOptions options;
  options.huber = 4.0;
  options.outlier = 20.0;
  DirectBaProblem relit = Relit(w, w.truth);
  StatusOr<DirectBaSummary> s0 = AdjustKeyframeWindowDirect(options, &relit);
  ASSERT_TRUE(s0.ok()) << s0.status();
  DirectBaProblem j = w.truth;
  ASSERT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &j).ok());
  std::printf(
      "%s from the truth: centre error relit %.4f / J %.4f of the spacing, scale relit %.4f / J %.4f, "
      "relit RMS %.2f -> %.2f over %d residuals\n",
      GetParam().c_str(), CentreError(relit, w.truth), CentreError(j, w.truth), ScaleRatio(relit, w.truth),
      ScaleRatio(j, w.truth), s0->initial_rms, s0->final_rms, s0->residuals);
  EXPECT_LE(CentreError(relit, w.truth), kRelitMaxCentreErrorFromTruth);
  EXPECT_LT(CentreError(relit, w.truth), CentreError(j, w.truth));
  EXPECT_NEAR(ScaleRatio(relit, w.truth), 1.0, kRelitMaxScaleErrorFromTruth);
  EXPECT_GT(s0->residuals, 1000);
}

INSTANTIATE_TEST_SUITE_P(GreyAlbedoPresets, RelitKeyframeBaPresetTest,
                         ::testing::Values("sphere-uniform-sideways", "bunny-uniform-sideways",
                                           "relief-uniform-sideways"),
                         [](const ::testing::TestParamInfo<std::string>& info) {
                           std::string n = info.param;
                           for (char& c : n)
                             if (c == '-') c = '_';
                           return n;
                         });

// On the uniform sphere the shading is the only signal on the object, and the relit residual makes the
// scale observable: from keyframes 2-3 3% short (and 5% of the spacing sideways, 5% depth noise) it
// recovers the scale, which J does not.
constexpr double kRelitMaxScaleErrorFromPerturbed = 0.02;
constexpr double kRelitMaxCentreErrorFromPerturbed = 0.07;  // of the spacing

TEST(RelitKeyframeBa, RecoversTheScaleOnTheUniformSphere) {
  const Window w = MakeWindow("sphere-uniform-sideways");
  ASSERT_TRUE(w.ok) << w.why;
  const DirectBaProblem start = PerturbedStart(w);
  DirectBaOptions options;
  options.huber = 4.0;
  options.outlier = 20.0;
  DirectBaProblem relit = Relit(w, start);
  ASSERT_TRUE(AdjustKeyframeWindowDirect(options, &relit).ok());
  DirectBaProblem j = start;
  ASSERT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &j).ok());
  std::printf("perturbed: centre error %.4f -> relit %.4f / J %.4f of the spacing, scale 0.97 -> relit %.4f / J %.4f\n",
              CentreError(start, w.truth), CentreError(relit, w.truth), CentreError(j, w.truth),
              ScaleRatio(relit, w.truth), ScaleRatio(j, w.truth));
  EXPECT_NEAR(ScaleRatio(relit, w.truth), 1.0, kRelitMaxScaleErrorFromPerturbed);
  EXPECT_LE(CentreError(relit, w.truth), kRelitMaxCentreErrorFromPerturbed);
  EXPECT_LT(std::abs(ScaleRatio(relit, w.truth) - 1), std::abs(ScaleRatio(j, w.truth) - 1));
}

// With K estimated jointly (DirectBaRelit::estimate_metres_per_world_unit), from the true poses and
// depths but K 20% low: K comes back to within kRelitMaxMetricScaleError of the truth (the world is in
// metres: measured 1.1 / 2.9 / 2.0% on sphere / bunny / relief) while the keyframes move by up to
// kRelitMaxCentreErrorFromWrongK of the spacing on the way (measured 2.9-4.8%; with K given 0.8-1.9%).
constexpr double kRelitMaxMetricScaleError = 0.03;
constexpr double kRelitMaxCentreErrorFromWrongK = 0.06;

TEST_P(RelitKeyframeBaPresetTest, EstimatesTheMetresPerWorldUnit) {
  const Window w = MakeWindow(GetParam());
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  DirectBaOptions options;
  options.huber = 4.0;
  options.outlier = 20.0;
  DirectBaProblem relit = Relit(w, w.truth);
  relit.relit.metres_per_world_unit = 0.8;
  relit.relit.estimate_metres_per_world_unit = true;
  StatusOr<DirectBaSummary> s0 = AdjustKeyframeWindowDirect(options, &relit);
  ASSERT_TRUE(s0.ok()) << s0.status();
  std::printf("%s, K from 0.8: %.4f, centre error %.4f of the spacing, scale %.4f\n", GetParam().c_str(),
              relit.relit.metres_per_world_unit, CentreError(relit, w.truth), ScaleRatio(relit, w.truth));
  EXPECT_NEAR(relit.relit.metres_per_world_unit, 1.0, kRelitMaxMetricScaleError);
  EXPECT_LE(CentreError(relit, w.truth), kRelitMaxCentreErrorFromWrongK);
}

// Mixed (DirectBaRelit::mixed): J and the relit residual together, every point twice, the relit one
// scaled by kMixedRelitScale. Measured (printed): from the truth, keyframes 2-3 move by 2.7 / 1.1 / 2.8%
// of the spacing on the uniform sphere / bunny / relief (J 2.3 / 2.1 / 4.6%); from the perturbed start
// on the uniform sphere (3% short) the scale comes back to 0.985 (J 0.972). With a relit scale of 1
// (SlamOptions::final_adjustment_mixed_relit_scale's default, the better one in the SLAM) J dominates
// there: 0.975; with 4, 0.973 (the scaled relit residuals reach the Huber threshold). In the SLAM's
// final adjustment it was measured and not kept (see the README).
constexpr double kMixedRelitScale = 2.0;
constexpr double kMixedMaxCentreExcessOverJ = 0.01;  // of the spacing

DirectBaProblem Mixed(const Window& w, const DirectBaProblem& start) {
  DirectBaProblem p = start;
  const size_t n = p.points.size();
  for (size_t i = 0; i < n; ++i) {
    DirectBaPoint q = p.points[i];
    q.relit = true;
    p.points.push_back(q);
  }
  p.relit.rig = &w.rig;
  p.relit.metres_per_world_unit = 1.0;
  p.relit.rgb = w.rgb;
  p.relit.mixed = true;
  p.relit.relit_residual_scale = kMixedRelitScale;
  return p;
}

TEST_P(RelitKeyframeBaPresetTest, MixedStaysNearTheTruth) {
  const Window w = MakeWindow(GetParam());
  if (!w.ok) GTEST_SKIP() << "preset unavailable: " << w.why;
  DirectBaProblem mixed = Mixed(w, w.truth);
  StatusOr<DirectBaSummary> s0 = AdjustKeyframeWindowDirect(DirectBaOptions(), &mixed);
  ASSERT_TRUE(s0.ok()) << s0.status();
  DirectBaProblem j = w.truth;
  ASSERT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &j).ok());
  std::printf("%s mixed from the truth: centre error %.4f (J %.4f) of the spacing, scale %.4f (J %.4f)\n",
              GetParam().c_str(), CentreError(mixed, w.truth), CentreError(j, w.truth), ScaleRatio(mixed, w.truth),
              ScaleRatio(j, w.truth));
  EXPECT_LE(CentreError(mixed, w.truth), CentreError(j, w.truth) + kMixedMaxCentreExcessOverJ);
  EXPECT_NEAR(ScaleRatio(mixed, w.truth), 1.0, kMaxScaleErrorFromTruth);
}

// The relit residual with a pool: its residuals (and the points' implied normals) are linearised and
// evaluated target by target in parallel, log K's sums too, each still formed in the one-thread order:
// the same poses, inverse depths, K and summary to the last bit. Relit with K estimated from 20% low
// (EstimateMetricScale's adjustment) and mixed (J and relit together), from the perturbed start.
TEST(RelitKeyframeBa, GivesTheSameResultToTheLastBitWithAPool) {
  const Window w = MakeWindow("sphere-uniform-sideways");
  ASSERT_TRUE(w.ok) << w.why;
  const DirectBaProblem perturbed = PerturbedStart(w);
  DirectBaProblem relit_k = Relit(w, perturbed);
  relit_k.relit.metres_per_world_unit = 0.8;
  relit_k.relit.estimate_metres_per_world_unit = true;
  DirectBaOptions relit_options;
  relit_options.huber = 4.0;
  relit_options.outlier = 20.0;
  const std::vector<std::pair<std::string, std::pair<DirectBaProblem, DirectBaOptions>>> cases = {
      {"relit, K estimated", {relit_k, relit_options}}, {"mixed", {Mixed(w, perturbed), DirectBaOptions()}}};
  for (const auto& [name, c] : cases) {
    const auto& [start, options] = c;
    DirectBaProblem serial = start;
    StatusOr<DirectBaSummary> s_serial = AdjustKeyframeWindowDirect(options, &serial);
    ASSERT_TRUE(s_serial.ok()) << s_serial.status();
    for (int threads : {2, 3}) {
      const std::string what = name + ", " + std::to_string(threads) + " threads";
      ThreadPool pool(threads);
      DirectBaProblem parallel = start;
      StatusOr<DirectBaSummary> s_parallel = AdjustKeyframeWindowDirect(options, &parallel, &pool);
      ASSERT_TRUE(s_parallel.ok()) << s_parallel.status();
      EXPECT_EQ(s_parallel->iterations, s_serial->iterations) << what;
      EXPECT_EQ(s_parallel->evaluations, s_serial->evaluations) << what;
      EXPECT_EQ(s_parallel->residuals, s_serial->residuals) << what;
      EXPECT_EQ(s_parallel->initial_rms, s_serial->initial_rms) << what;
      EXPECT_EQ(s_parallel->final_rms, s_serial->final_rms) << what;
      EXPECT_EQ(parallel.relit.metres_per_world_unit, serial.relit.metres_per_world_unit) << what;
      ExpectSameAdjustment(serial, parallel, what);
    }
    // A real solve: the keyframes moved (and K, where it is estimated).
    EXPECT_GT((serial.world_from_keyframe[3].translation - start.world_from_keyframe[3].translation).norm(), 0.0)
        << name;
    if (start.relit.estimate_metres_per_world_unit) {
      EXPECT_NE(serial.relit.metres_per_world_unit, start.relit.metres_per_world_unit) << name;
    }
  }
}

TEST(RelitKeyframeBa, MixedRecoversTheScaleOnTheUniformSphere) {
  const Window w = MakeWindow("sphere-uniform-sideways");
  ASSERT_TRUE(w.ok) << w.why;
  const DirectBaProblem start = PerturbedStart(w);
  DirectBaProblem mixed = Mixed(w, start);
  ASSERT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &mixed).ok());
  DirectBaProblem j = start;
  ASSERT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &j).ok());
  std::printf("perturbed, mixed: centre error %.4f -> %.4f (J %.4f) of the spacing, scale 0.97 -> %.4f (J %.4f)\n",
              CentreError(start, w.truth), CentreError(mixed, w.truth), CentreError(j, w.truth),
              ScaleRatio(mixed, w.truth), ScaleRatio(j, w.truth));
  EXPECT_NEAR(ScaleRatio(mixed, w.truth), 1.0, kRelitMaxScaleErrorFromPerturbed);
  EXPECT_LT(std::abs(ScaleRatio(mixed, w.truth) - 1), std::abs(ScaleRatio(j, w.truth) - 1));
}

TEST(RelitKeyframeBa, RejectsBadInput) {
  DirectBaProblem p;
  p.camera = PinholeCamera::FromFov(64, 48, 60.0);
  p.world_from_keyframe.resize(2);
  p.world_from_keyframe[1].translation = Eigen::Vector3d(0.1, 0, 0);
  p.grey_j.assign(2, cv::Mat::zeros(48, 64, CV_32F));
  RigCalibration rig;
  rig.camera = p.camera;
  p.relit.rig = &rig;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "no colour images";
  p.relit.rgb.assign(2, cv::Mat::zeros(48, 64, CV_8UC3));
  EXPECT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok());
  p.relit.metres_per_world_unit = 0;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "metres per world unit 0";
  p.relit.metres_per_world_unit = 1;
  p.relit.albedo_colour = Eigen::Vector3d(1, 0, 1);
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "albedo colour with a zero";
  p.relit.albedo_colour = Eigen::Vector3d::Ones();
  DirectBaOptions pyramid;
  pyramid.pyramid_levels = 2;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(pyramid, &p).ok()) << "relit needs one level";
  p.relit.mixed = true;
  p.relit.relit_residual_scale = 0;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "mixed with a zero relit scale";
  p.relit.relit_residual_scale = 1;
  EXPECT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok());
  p.relit.rig = nullptr;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "mixed without a rig";
}

// A point of a host keyframe in a target keyframe's camera, with both poses perturbed as the adjustment
// perturbs them: R exp(w) and c + dc; d = (w_h, dc_h, w_t, dc_t).
Eigen::Vector3d PointInTarget(const Sim3d& host, const Sim3d& target, const Eigen::Vector3d& q,
                              const Eigen::Matrix<double, 12, 1>& d) {
  auto exp = [](const Eigen::Vector3d& w) {
    const double angle = w.norm();
    return angle > 0 ? Eigen::Matrix3d(Eigen::AngleAxisd(angle, w / angle)) : Eigen::Matrix3d::Identity();
  };
  const Eigen::Matrix3d r_h = host.rotation.toRotationMatrix() * exp(d.segment<3>(0));
  const Eigen::Matrix3d r_t = target.rotation.toRotationMatrix() * exp(d.segment<3>(6));
  const Eigen::Vector3d x = host.translation + d.segment<3>(3) + host.scale * (r_h * q);
  return r_t.transpose() * (x - (target.translation + d.segment<3>(9)));
}

// Tolerance of the central differences below (step 1e-6 on values of order 1).
constexpr double kMaxJacobianError = 1e-7;

TEST(KeyframeBa, HostJacobianIsTheTargetJacobianTimesTheMap) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  auto random_pose = [&](double scale) {
    const Eigen::Vector3d axis = Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized();
    return Sim3d(scale, Eigen::Quaterniond(Eigen::AngleAxisd(u(rng), axis)), Eigen::Vector3d(u(rng), u(rng), u(rng)));
  };
  for (int trial = 0; trial < 20; ++trial) {
    const Sim3d host = random_pose(0.5 + 0.5 * (u(rng) + 1)), target = random_pose(1.0);
    const Eigen::Vector3d q(u(rng), u(rng), 2 + u(rng));
    Eigen::Matrix<double, 3, 12> j;
    for (int c = 0; c < 12; ++c) {
      Eigen::Matrix<double, 12, 1> d = Eigen::Matrix<double, 12, 1>::Zero();
      d(c) = 1e-6;
      j.col(c) = (PointInTarget(host, target, q, d) - PointInTarget(host, target, q, -d)) / 2e-6;
    }
    const Eigen::Matrix<double, 6, 6> a = DirectBaHostFromTarget(
        host.rotation.toRotationMatrix(), host.translation, target.rotation.toRotationMatrix(), target.translation);
    const Eigen::Matrix<double, 3, 6> j_host = j.leftCols<6>(), j_target = j.rightCols<6>();
    EXPECT_LT((j_host - j_target * a).norm(), kMaxJacobianError * std::max(1.0, j_host.norm())) << "trial " << trial;
  }
}

TEST(KeyframeBa, DepthOverlapFractionOfAPlaneSeenFromAShiftedCamera) {
  // A fronto-parallel plane 2 units in front of keyframe a; its image spans x in [-2, 2] on the plane
  // (fx = width / 2). Keyframe b moved sideways by 1 sees 3/4 of it.
  PinholeCamera cam;
  cam.width = 64;
  cam.height = 48;
  cam.fx = cam.fy = 32;
  cam.cx = 31.5;
  cam.cy = 23.5;
  const cv::Mat plane(cam.height, cam.width, CV_32F, cv::Scalar(0.5f));
  const Sim3d a(1.0, Eigen::Quaterniond::Identity(), Eigen::Vector3d(1, 2, 3));
  EXPECT_EQ(DepthOverlapFraction(cam, plane, a, a, 1), 1.0);
  const Sim3d b(1.0, Eigen::Quaterniond::Identity(), Eigen::Vector3d(2, 2, 3));
  EXPECT_NEAR(DepthOverlapFraction(cam, plane, a, b, 1), 0.75, 0.02);
  // In a's units: with a's unit twice the world's, b's shift is 0.5 of a's units.
  const Sim3d a2(2.0, a.rotation, a.translation);
  EXPECT_NEAR(DepthOverlapFraction(cam, plane, a2, b, 1), 0.875, 0.02);
  // Turned away by 180 degrees: nothing is in front of b.
  const Sim3d behind(1.0, Eigen::Quaterniond(Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY())), a.translation);
  EXPECT_EQ(DepthOverlapFraction(cam, plane, a, behind, 4), 0.0);
  // No depth at all: nothing to lose.
  EXPECT_EQ(DepthOverlapFraction(cam, cv::Mat::zeros(cam.height, cam.width, CV_32F), a, behind, 4), 1.0);
}

TEST(KeyframeBa, RejectsBadInput) {
  DirectBaProblem p;
  p.camera = PinholeCamera::FromFov(64, 48, 60.0);
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), nullptr).ok());
  p.world_from_keyframe.resize(1);
  p.grey_j.assign(1, cv::Mat::zeros(48, 64, CV_32F));
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "one keyframe";
  p.world_from_keyframe.resize(2);
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "one grey image for two keyframes";
  p.grey_j.assign(2, cv::Mat::zeros(48, 64, CV_32F));
  p.world_from_keyframe[1].translation = Eigen::Vector3d(0.1, 0, 0);
  EXPECT_TRUE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "no points is allowed";
  p.grey_j[1] = cv::Mat::zeros(48, 64, CV_8U);
  StatusOr<DirectBaSummary> wrong_type = AdjustKeyframeWindowDirect(DirectBaOptions(), &p);
  EXPECT_FALSE(wrong_type.ok());
  p.grey_j[1] = cv::Mat::zeros(48, 64, CV_32F);
  DirectBaPoint bad;
  bad.host = 5;
  bad.inverse_depth = 1;
  p.points.push_back(bad);
  StatusOr<DirectBaSummary> bad_host = AdjustKeyframeWindowDirect(DirectBaOptions(), &p);
  EXPECT_FALSE(bad_host.ok());
  p.points[0].host = 0;
  p.points[0].inverse_depth = 0;
  EXPECT_FALSE(AdjustKeyframeWindowDirect(DirectBaOptions(), &p).ok()) << "inverse depth 0";
  DirectBaOptions o;
  o.outlier = o.huber;
  EXPECT_FALSE(o.Check().ok());
  o = DirectBaOptions();
  o.border_px = 1;
  EXPECT_FALSE(o.Check().ok());
}

}  // namespace
}  // namespace prism
