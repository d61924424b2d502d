#include "core/slam/feature_adjustment.h"

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/eval/alignment.h"
#include "core/slam/depth_filter.h"
#include "core/slam/slam_system.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// Keyframes along a whole 120-degree arc of a dark-room preset (every 12th of 150 frames, about the
// SlamSystem's spacing of 7-10 frames, halved), ground-truth poses in metres.
struct Arc {
  PinholeCamera camera;
  std::vector<FeatureImage> images;
  std::vector<Sim3d> truth;
  bool ok = false;
  std::string why;
};

Arc MakeArc(const std::string& preset) {
  Arc a;
  synth::PresetOptions o;
  o.frames = 150;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    a.why = setup.status().ToString();
    return a;
  }
  const Trajectory traj = synth::MakeTrajectory(setup->trajectory);
  ThreadPool pool;
  a.camera = setup->rig.camera;
  const DepthFilterOptions depth = SlamOptions().depth;  // J as the SLAM normalises it
  for (int frame = 0; frame < 150; frame += 12) {
    const synth::RenderedFrame f = synth::RenderFrame(setup->scene, setup->rig, traj[frame].world_from_camera,
                                                      setup->render, 5000ull + frame, &pool);
    FeatureImage image;
    KeyframeDepth::NormalisedGrey(f.rgb, depth, &image.grey_j, &image.local_mean);
    a.images.push_back(image);
    const Rigid3d& pose = traj[frame].world_from_camera;
    a.truth.push_back(Sim3d(1.0, pose.rotation, pose.translation));
  }
  a.ok = true;
  return a;
}

double Turn(const std::vector<Sim3d>& poses) {
  return RotationAngle(poses.front().rotation.conjugate() * poses.back().rotation);
}

// RMS keyframe-centre error against the truth after a Sim(3) alignment of the centres, as a fraction of
// the arc's chord from the first to the last keyframe (the trajectory error the SLAM is scored by).
double AlignedCentreError(const std::vector<Sim3d>& poses, const std::vector<Sim3d>& truth) {
  std::vector<Eigen::Vector3d> a, b;
  for (size_t k = 0; k < poses.size(); ++k) {
    a.push_back(poses[k].translation);
    b.push_back(truth[k].translation);
  }
  const StatusOr<Sim3d> t = UmeyamaAlignment(a, b, /*estimate_scale=*/true);
  if (!t.ok()) return 1e9;
  double sum = 0;
  for (size_t k = 0; k < a.size(); ++k) sum += ((*t) * a[k] - b[k]).squaredNorm();
  return std::sqrt(sum / static_cast<double>(a.size())) / (b.back() - b.front()).norm();
}

// The turn short by `factor`: each keyframe's rotation from the first scaled, the centres kept (the
// SLAM's rotation-short runs are 0.97-0.98 of the truth).
std::vector<Sim3d> ShortTurn(const std::vector<Sim3d>& truth, double factor) {
  std::vector<Sim3d> out = truth;
  for (Sim3d& p : out) {
    const Eigen::AngleAxisd aa(truth.front().rotation.conjugate() * p.rotation);
    p.rotation = truth.front().rotation * Eigen::Quaterniond(Eigen::AngleAxisd(factor * aa.angle(), aa.axis()));
  }
  return out;
}

// Tolerances from measurement (printed): from a turn 0.98 of the truth the torus's arc comes back to
// 0.9995 of the truth's turn and the uniform sphere's to 1.0002, the centres within 0.14% and 0.12% of
// the chord (aligned RMS), the same solutions as from the truth.
constexpr double kMaxTurnError = 0.003;         // relative
constexpr double kMaxCentreError = 0.003;       // of the chord
constexpr double kMaxFinalMedianErrorPx = 0.5;  // reprojection
constexpr double kShortTurn = 0.98;

class FeatureAdjustmentArcTest : public ::testing::TestWithParam<std::string> {};

TEST_P(FeatureAdjustmentArcTest, RestoresAShortTurnAndKeepsTheTruth) {
  const Arc arc = MakeArc(GetParam());
  if (!arc.ok) GTEST_SKIP() << "preset unavailable: " << arc.why;
  FeatureAdjustmentOptions options;
  ThreadPool pool(2);
  StatusOr<FeatureTracks> tracks = BuildFeatureTracks(arc.camera, options, arc.images, arc.truth, &pool);
  ASSERT_TRUE(tracks.ok()) << tracks.status();
  std::printf("%s: %d features, %d of %d pairs matched, %zu tracks\n", GetParam().c_str(), tracks->features,
              tracks->pairs_matched, tracks->pairs_tried, tracks->tracks.size());
  ASSERT_GT(tracks->tracks.size(), 300u);
  // The same tracks without a pool (the strongest features in a thread-independent order).
  StatusOr<FeatureTracks> alone = BuildFeatureTracks(arc.camera, options, arc.images, arc.truth);
  ASSERT_TRUE(alone.ok()) << alone.status();
  EXPECT_EQ(alone->features, tracks->features);
  EXPECT_EQ(alone->pairs_matched, tracks->pairs_matched);
  ASSERT_EQ(alone->tracks.size(), tracks->tracks.size());
  for (size_t t = 0; t < tracks->tracks.size(); ++t) {
    ASSERT_EQ(alone->tracks[t].size(), tracks->tracks[t].size()) << "track " << t;
    for (size_t i = 0; i < tracks->tracks[t].size(); ++i) {
      EXPECT_EQ(alone->tracks[t][i].keyframe, tracks->tracks[t][i].keyframe);
      EXPECT_EQ(alone->tracks[t][i].u, tracks->tracks[t][i].u);
      EXPECT_EQ(alone->tracks[t][i].v, tracks->tracks[t][i].v);
    }
  }

  std::vector<Sim3d> from_truth = arc.truth;
  StatusOr<FeatureAdjustmentSummary> s0 = AdjustKeyframesByFeatures(arc.camera, options, *tracks, &from_truth);
  ASSERT_TRUE(s0.ok()) << s0.status();
  const double truth_turn = Turn(arc.truth);
  std::printf(
      "  from the truth: turn %.5f of the truth, centres %.5f of the chord (aligned RMS), median %.3f -> %.3f px\n",
      Turn(from_truth) / truth_turn, AlignedCentreError(from_truth, arc.truth), s0->initial_median_px,
      s0->final_median_px);
  EXPECT_NEAR(Turn(from_truth) / truth_turn, 1.0, kMaxTurnError);
  EXPECT_LT(AlignedCentreError(from_truth, arc.truth), kMaxCentreError);
  EXPECT_LT(s0->final_median_px, kMaxFinalMedianErrorPx);

  std::vector<Sim3d> start = ShortTurn(arc.truth, kShortTurn);
  StatusOr<FeatureAdjustmentSummary> s1 = AdjustKeyframesByFeatures(arc.camera, options, *tracks, &start);
  ASSERT_TRUE(s1.ok()) << s1.status();
  std::printf(
      "  from a turn %.2f of the truth: %.5f, centres %.5f of the chord (aligned RMS), median %.3f -> %.3f px, %d "
      "tracks, %d iterations\n",
      kShortTurn, Turn(start) / truth_turn, AlignedCentreError(start, arc.truth), s1->initial_median_px,
      s1->final_median_px, s1->tracks, s1->iterations);
  EXPECT_NEAR(Turn(start) / truth_turn, 1.0, kMaxTurnError);
  EXPECT_LT(AlignedCentreError(start, arc.truth), kMaxCentreError);
  EXPECT_LT(s1->final_median_px, s1->initial_median_px);
  // The gauge: keyframe 0 unchanged, keyframe 1 as far from it as before; the scales unchanged.
  EXPECT_EQ(start[0].translation, arc.truth[0].translation);
  EXPECT_TRUE(start[0].rotation.isApprox(arc.truth[0].rotation));
  const double baseline = (arc.truth[1].translation - arc.truth[0].translation).norm();
  EXPECT_NEAR((start[1].translation - start[0].translation).norm(), baseline, 1e-12);
  for (const Sim3d& p : start) EXPECT_EQ(p.scale, 1.0);
  // A Sim(3) scale (the depth unit) does not enter the reprojection: the same start with every scale 2.5
  // gives the same rotations and centres, and keeps the scales.
  std::vector<Sim3d> scaled = ShortTurn(arc.truth, kShortTurn);
  for (Sim3d& p : scaled) p.scale = 2.5;
  ASSERT_TRUE(AdjustKeyframesByFeatures(arc.camera, options, *tracks, &scaled).ok());
  for (size_t k = 0; k < scaled.size(); ++k) {
    EXPECT_EQ(scaled[k].scale, 2.5) << "keyframe " << k;
    EXPECT_TRUE(scaled[k].translation.isApprox(start[k].translation, 1e-12)) << "keyframe " << k;
    EXPECT_TRUE(scaled[k].rotation.isApprox(start[k].rotation, 1e-12)) << "keyframe " << k;
  }
  // Each keyframe's observations carry the adjusted depth (positive, near the scene's 0.4-0.9 m).
  ASSERT_EQ(s1->observations_by_keyframe.size(), arc.truth.size());
  for (const std::vector<FeatureObservation>& k : s1->observations_by_keyframe)
    for (const FeatureObservation& o : k) {
      EXPECT_GT(o.depth, 0.1);
      EXPECT_LT(o.depth, 3.0);
    }
}

// The torus (textured object, cast shadows of the co-moving lights on the ground) and the uniform sphere
// (texture on the ground alone): the two presets whose direct adjustment ends with a short turn.
INSTANTIATE_TEST_SUITE_P(Presets, FeatureAdjustmentArcTest,
                         ::testing::Values("torus-textured-forward", "sphere-uniform-sideways"),
                         [](const ::testing::TestParamInfo<std::string>& info) {
                           std::string n = info.param;
                           for (char& c : n)
                             if (c == '-') c = '_';
                           return n;
                         });

TEST(FeatureAdjustment, RefusesBadInputAndLeavesThePosesWithTooFewTracks) {
  PinholeCamera camera = PinholeCamera::FromFov(64, 48, 60);
  FeatureImage blank;
  blank.grey_j = cv::Mat(48, 64, CV_32F, cv::Scalar(128));
  blank.local_mean = cv::Mat(48, 64, CV_32F, cv::Scalar(100));
  std::vector<Sim3d> poses(3);
  poses[1].translation = Eigen::Vector3d(0.1, 0, 0);
  poses[2].translation = Eigen::Vector3d(0.2, 0, 0);
  const FeatureAdjustmentOptions options;
  // Fewer than 3 keyframes; a pose per image; CV_32F of the camera's size.
  EXPECT_EQ(BuildFeatureTracks(camera, options, {blank, blank}, {poses[0], poses[1]}).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(BuildFeatureTracks(camera, options, {blank, blank, blank}, {poses[0], poses[1]}).status().code(),
            StatusCode::kInvalidArgument);
  FeatureImage wrong = blank;
  wrong.grey_j = cv::Mat(48, 64, CV_8U, cv::Scalar(128));
  EXPECT_EQ(BuildFeatureTracks(camera, options, {blank, wrong, blank}, poses).status().code(),
            StatusCode::kInvalidArgument);
  FeatureAdjustmentOptions bad;
  bad.outlier_px = 0.5;  // below huber_px
  const Status check = bad.Check();
  EXPECT_EQ(check.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(check.message()).find("outlier_px"), std::string::npos) << check.message();
  // Blank images: no features, no tracks; the adjustment refuses and leaves the poses.
  StatusOr<FeatureTracks> tracks = BuildFeatureTracks(camera, options, {blank, blank, blank}, poses);
  ASSERT_TRUE(tracks.ok()) << tracks.status();
  EXPECT_EQ(tracks->tracks.size(), 0u);
  std::vector<Sim3d> adjusted = poses;
  EXPECT_EQ(AdjustKeyframesByFeatures(camera, options, *tracks, &adjusted).status().code(),
            StatusCode::kFailedPrecondition);
  for (size_t k = 0; k < poses.size(); ++k) EXPECT_EQ(adjusted[k].translation, poses[k].translation);
  // Keyframes 0 and 1 at one place: no scale gauge.
  std::vector<Sim3d> coincident = poses;
  coincident[1].translation = coincident[0].translation;
  const Status no_gauge = AdjustKeyframesByFeatures(camera, options, *tracks, &coincident).status();
  EXPECT_EQ(no_gauge.code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(std::string(no_gauge.message()).find("coincide"), std::string::npos) << no_gauge.message();
  // Poses that do not match the tracks' keyframes.
  std::vector<Sim3d> four(4);
  EXPECT_EQ(AdjustKeyframesByFeatures(camera, options, *tracks, &four).status().code(), StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace prism
