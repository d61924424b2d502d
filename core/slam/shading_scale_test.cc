#include "core/slam/shading_scale.h"

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"

namespace prism {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;
// The depth unit of these tests: 0.6 m, so the true metres per unit is 0.6 and the estimator starts at
// 1 (a 67% error) before its scan.
constexpr double kMetresPerUnit = 0.6;
// Grey-albedo presets, true depth and poses, one frame 8 after the keyframe: measured 0.3-4% (see the
// printed table); the bar leaves room for the renderer's seeds.
constexpr double kGreyAlbedoScaleTolerance = 0.06;
// Rotation error of the refined pose, degrees.
constexpr double kMaxRotationDriftDeg = 0.4;

struct Pair {
  synth::SynthSetup setup;
  synth::RenderedFrame keyframe, frame;
  Rigid3d frame_from_keyframe_units;  // translation in depth units
  cv::Mat inverse_depth_units;        // 1 / depth unit
};

// Renders frames `keyframe` and `keyframe + offset` of a 150-frame preset; false when the preset's mesh
// is not installed.
bool MakePair(const std::string& preset, int keyframe, int offset, Pair* out, std::string* why) {
  synth::PresetOptions o;
  o.frames = 150;
  o.seed = 1;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    *why = setup.status().ToString();
    return false;
  }
  out->setup = std::move(setup).value();
  const Trajectory trajectory = synth::MakeTrajectory(out->setup.trajectory);
  const Rigid3d& world_from_keyframe = trajectory[keyframe].world_from_camera;
  const Rigid3d& world_from_frame = trajectory[keyframe + offset].world_from_camera;
  out->keyframe = synth::RenderFrame(out->setup.scene, out->setup.rig, world_from_keyframe, out->setup.render, 11);
  out->frame = synth::RenderFrame(out->setup.scene, out->setup.rig, world_from_frame, out->setup.render, 12);
  Rigid3d rel = world_from_frame.Inverse() * world_from_keyframe;
  rel.translation /= kMetresPerUnit;
  out->frame_from_keyframe_units = rel;
  out->inverse_depth_units = cv::Mat::zeros(out->keyframe.depth.size(), CV_32F);
  for (int y = 0; y < out->keyframe.depth.rows; ++y) {
    for (int x = 0; x < out->keyframe.depth.cols; ++x) {
      const float z = out->keyframe.depth.at<float>(y, x);
      if (z > 0) out->inverse_depth_units.at<float>(y, x) = static_cast<float>(kMetresPerUnit / z);
    }
  }
  return true;
}

double RotationErrorDeg(const Rigid3d& a, const Rigid3d& b) {
  return RotationAngle(a.rotation * b.rotation.conjugate()) * kRadToDeg;
}

class GreyAlbedoTest : public ::testing::TestWithParam<const char*> {};

TEST_P(GreyAlbedoTest, RecoversTheMetricScaleFromTheCoMovingLights) {
  Pair pair;
  std::string why;
  if (!MakePair(GetParam(), 60, 8, &pair, &why)) GTEST_SKIP() << why;
  ShadingScaleOptions options;
  options.initial_metres_per_unit = 1.0;
  std::vector<ShadingScaleFrame> frames = {{pair.frame.rgb, pair.frame_from_keyframe_units}};
  StatusOr<ShadingScaleResult> r =
      EstimateShadingScale(pair.setup.rig, pair.keyframe.rgb, pair.inverse_depth_units, frames, options);
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  const double rel = r->metres_per_unit / kMetresPerUnit - 1;
  std::printf("%s: metres per unit %.4f (true %.2f, %+.1f%%), log sigma %.4f, %d points, rms %.2f, grey %.2f\n",
              GetParam(), r->metres_per_unit, kMetresPerUnit, 100 * rel, r->log_sigma, r->points, r->final_rms,
              r->grey_albedo_fraction);
  EXPECT_LT(std::abs(rel), kGreyAlbedoScaleTolerance);
  EXPECT_GT(r->grey_albedo_fraction, 0.9);
  // The pose stays near the truth it started from (0.05-0.29 deg measured: cast shadows and occlusions
  // pull the joint minimum a little).
  EXPECT_LT(RotationErrorDeg(r->frame_from_keyframe[0], pair.frame_from_keyframe_units), kMaxRotationDriftDeg);
}

// From a pose with the tracker's typical bias (translation 5% short, 0.2 deg of rotation off), the
// joint refinement still finds the scale. The pose it ends at is not better than the start on every
// preset (measured: 0.05-0.29 deg from 0.2 deg), so only a bound is checked.
TEST_P(GreyAlbedoTest, RefinesABiasedPoseAndTheScaleTogether) {
  Pair pair;
  std::string why;
  if (!MakePair(GetParam(), 60, 8, &pair, &why)) GTEST_SKIP() << why;
  Rigid3d biased = pair.frame_from_keyframe_units;
  biased.translation *= 0.95;
  biased.rotation = ExpSo3(Eigen::Vector3d(0.2 / kRadToDeg, 0, 0)) * biased.rotation;
  ShadingScaleOptions options;
  std::vector<ShadingScaleFrame> frames = {{pair.frame.rgb, biased}};
  StatusOr<ShadingScaleResult> r =
      EstimateShadingScale(pair.setup.rig, pair.keyframe.rgb, pair.inverse_depth_units, frames, options);
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  const double rel = r->metres_per_unit / kMetresPerUnit - 1;
  const double before = RotationErrorDeg(biased, pair.frame_from_keyframe_units);
  const double after = RotationErrorDeg(r->frame_from_keyframe[0], pair.frame_from_keyframe_units);
  std::printf("%s, biased start: metres per unit %+.1f%%, rotation error %.3f -> %.3f deg\n", GetParam(), 100 * rel,
              before, after);
  EXPECT_LT(std::abs(rel), kGreyAlbedoScaleTolerance);
  EXPECT_LT(after, kMaxRotationDriftDeg);
}

INSTANTIATE_TEST_SUITE_P(DarkRoom, GreyAlbedoTest,
                         ::testing::Values("sphere-uniform-sideways", "bunny-uniform-sideways",
                                           "torus-textured-forward", "relief-uniform-sideways"),
                         [](const ::testing::TestParamInfo<const char*>& info) {
                           std::string s = info.param;
                           for (char& c : s)
                             if (c == '-') c = '_';
                           return s;
                         });

TEST(ShadingScaleTest, RejectsBadInput) {
  RigCalibration rig;
  rig.camera.width = 64;
  rig.camera.height = 48;
  rig.camera.fx = rig.camera.fy = 60;
  rig.camera.cx = 32;
  rig.camera.cy = 24;
  rig.lights[0].position_in_camera = Eigen::Vector3d(-0.2, 0, 0);
  rig.lights[1].position_in_camera = Eigen::Vector3d(0.2, 0, 0);
  rig.lights[2].position_in_camera = Eigen::Vector3d(0, -0.2, 0);
  const cv::Mat rgb(48, 64, CV_8UC3, cv::Scalar(100, 100, 100));
  const cv::Mat depth(48, 64, CV_32F, cv::Scalar(1.0f));
  ShadingScaleOptions options;
  const std::vector<ShadingScaleFrame> frames = {{rgb, Rigid3d()}};
  EXPECT_EQ(EstimateShadingScale(rig, rgb, depth, {}, options).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(EstimateShadingScale(rig, rgb, cv::Mat(48, 64, CV_64F), frames, options).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(EstimateShadingScale(rig, cv::Mat(48, 63, CV_8UC3), depth, frames, options).status().code(),
            StatusCode::kInvalidArgument);
  const std::vector<ShadingScaleFrame> wrong = {{cv::Mat(47, 64, CV_8UC3), Rigid3d()}};
  EXPECT_EQ(EstimateShadingScale(rig, rgb, depth, wrong, options).status().code(), StatusCode::kInvalidArgument);
  ShadingScaleOptions bad;
  bad.outlier_sigmas = bad.huber_sigmas;
  EXPECT_EQ(EstimateShadingScale(rig, rgb, depth, frames, bad).status().code(), StatusCode::kInvalidArgument);
  // A flat image has no gradient: no usable point.
  const StatusOr<ShadingScaleResult> r = EstimateShadingScale(rig, rgb, depth, frames, options);
  EXPECT_EQ(r.status().code(), StatusCode::kFailedPrecondition);
  EXPECT_NE(r.status().message().find("usable points"), std::string::npos) << r.status().ToString();
}

}  // namespace
}  // namespace prism
