#include "core/slam/tracker.h"

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "core/slam/slam_system.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"

namespace prism {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

struct SynthSequence {
  synth::SynthSetup setup;
  Trajectory trajectory;

  synth::RenderedFrame Render(int index) const {
    return synth::RenderFrame(setup.scene, setup.rig, trajectory[index].world_from_camera, setup.render,
                              /*noise_seed=*/1000 + index);
  }
  Rigid3d FrameFromKeyframe(int frame, int keyframe) const {
    return trajectory[frame].world_from_camera.Inverse() * trajectory[keyframe].world_from_camera;
  }
};

// Returns false (the caller skips) when the preset's mesh is not installed.
bool MakeSequence(const std::string& preset, int width, int height, SynthSequence* out, std::string* why) {
  synth::PresetOptions o;
  o.width = width;
  o.height = height;
  o.frames = 60;
  o.seed = 1;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    *why = setup.status().ToString();
    return false;
  }
  out->setup = std::move(setup).value();
  out->trajectory = synth::MakeTrajectory(out->setup.trajectory);
  return true;
}

// Ground-truth inverse depth (1% relative standard deviation); the tracker keeps the high-gradient pixels.
InverseDepthMap GroundTruthInverseDepth(const cv::Mat& depth) {
  InverseDepthMap m;
  m.inverse_depth = cv::Mat::zeros(depth.size(), CV_32F);
  m.variance = cv::Mat::zeros(depth.size(), CV_32F);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      const float z = depth.at<float>(y, x);
      if (!(z > 0)) continue;
      const float rho = 1.0f / z;
      m.inverse_depth.at<float>(y, x) = rho;
      m.variance.at<float>(y, x) = 1e-4f * rho * rho;
    }
  }
  return m;
}

struct PoseError {
  double translation_m = 0;
  double baseline_m = 0;
  double rotation_deg = 0;
};

PoseError Compare(const Rigid3d& estimate, const Rigid3d& truth) {
  PoseError e;
  e.translation_m = (estimate.translation - truth.translation).norm();
  e.baseline_m = truth.translation.norm();
  e.rotation_deg = RotationAngle(estimate.rotation * truth.rotation.inverse()) * kRadToDeg;
  return e;
}

struct TrackCase {
  std::string preset;
  int width;
  int height;
  double max_translation_error_m;
  double max_rotation_error_deg;
  ShadingModel shading_model = ShadingModel::kLocalMeanNormalisation;
};

class TrackerPresetTest : public ::testing::TestWithParam<TrackCase> {};

// Keyframe = frame 0 with ground-truth depth; frames 1..10 tracked in sequence with a constant-velocity
// guess, and frames 1, 3, 5 and 10 also from the identity.
TEST_P(TrackerPresetTest, TracksFramesAgainstGroundTruth) {
  const TrackCase& c = GetParam();
  SynthSequence seq;
  std::string why;
  if (!MakeSequence(c.preset, c.width, c.height, &seq, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  const synth::RenderedFrame key = seq.Render(0);
  TrackerOptions options;
  options.shading_model = c.shading_model;
  StatusOr<Tracker> tracker = Tracker::Create(seq.setup.rig, options);
  ASSERT_TRUE(tracker.ok()) << tracker.status();
  ASSERT_TRUE(tracker->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());

  // Per-preset tolerances, chosen after measuring (the printed values; worst case about 2/3 of these).
  const double max_translation_error_m = c.max_translation_error_m;
  const double max_rotation_error_deg = c.max_rotation_error_deg;

  Rigid3d previous, before_previous;
  for (int frame = 1; frame <= 10; ++frame) {
    const synth::RenderedFrame f = seq.Render(frame);
    const Rigid3d truth = seq.FrameFromKeyframe(frame, 0);
    const Rigid3d velocity_guess = (previous * before_previous.Inverse()) * previous;
    for (bool from_identity : {false, true}) {
      if (from_identity && frame != 1 && frame != 3 && frame != 5 && frame != 10) continue;
      const Rigid3d guess = from_identity ? Rigid3d() : velocity_guess;
      StatusOr<TrackingResult> r = tracker->Track(f.rgb, guess);
      ASSERT_TRUE(r.ok()) << r.status();
      const PoseError e = Compare(r->frame_from_keyframe, truth);
      std::printf(
          "%s gap %2d %s: t_err %.3f mm (baseline %.1f mm, %.2f%%) r_err %.4f deg | ok %d rms %.2f vis %.2f "
          "inl %.2f a %.3f b %.2f it %d/%d/%d/%d %s\n",
          c.preset.c_str(), frame, from_identity ? "identity" : "velocity", 1e3 * e.translation_m, 1e3 * e.baseline_m,
          100 * e.translation_m / e.baseline_m, e.rotation_deg, r->ok, r->residual_rms, r->visible_fraction,
          r->inlier_fraction, r->affine_a, r->affine_b, r->iterations[0], r->iterations[1], r->iterations[2],
          r->iterations[3], r->lost_reason.c_str());
      EXPECT_TRUE(r->ok) << r->lost_reason;
      EXPECT_LT(e.translation_m, max_translation_error_m)
          << "frame " << frame << (from_identity ? " from identity" : "");
      EXPECT_LT(e.rotation_deg, max_rotation_error_deg) << "frame " << frame;
      if (!from_identity) {
        before_previous = previous;
        previous = r->frame_from_keyframe;
      }
    }
  }
}

INSTANTIATE_TEST_SUITE_P(
    DarkRoomPresets, TrackerPresetTest,
    ::testing::Values(TrackCase{"sphere-multicolor-sideways", 320, 240, /*max_translation_error_m=*/0.003,
                                /*max_rotation_error_deg=*/0.3},
                      TrackCase{"bunny-multicolor-forward", 320, 240, /*max_translation_error_m=*/0.009,
                                /*max_rotation_error_deg=*/0.8},
                      // Measured 0.5-3.9 mm (3.5-21% of the baseline), 0.05-0.41 deg.
                      TrackCase{"torus-textured-forward", 320, 240, /*max_translation_error_m=*/0.006,
                                /*max_rotation_error_deg=*/0.65}),
    [](const ::testing::TestParamInfo<TrackCase>& info) {
      std::string name = info.param.preset;
      for (char& ch : name)
        if (ch == '-') ch = '_';
      return name;
    });

// ShadingModel::kPredictedShading (the rig predicts each point's shading change, on top of the
// local-mean normalisation). Measured 0.32-1.82 mm / <= 0.22 deg (sphere), 1.53-6.31 mm / <= 0.57 deg
// (bunny), 0.57-3.47 mm / <= 0.36 deg (torus): about the default's accuracy (torus better, sphere and
// bunny marginally worse), so it is not the default. On sphere-uniform-forward it diverges (23-150 mm).
constexpr double kPredictedSphereMaxTranslationM = 0.003, kPredictedSphereMaxRotationDeg = 0.3;
constexpr double kPredictedBunnyMaxTranslationM = 0.009, kPredictedBunnyMaxRotationDeg = 0.8;
constexpr double kPredictedTorusMaxTranslationM = 0.0055, kPredictedTorusMaxRotationDeg = 0.55;
INSTANTIATE_TEST_SUITE_P(
    PredictedShading, TrackerPresetTest,
    ::testing::Values(TrackCase{"sphere-multicolor-sideways", 320, 240, kPredictedSphereMaxTranslationM,
                                kPredictedSphereMaxRotationDeg, ShadingModel::kPredictedShading},
                      TrackCase{"bunny-multicolor-forward", 320, 240, kPredictedBunnyMaxTranslationM,
                                kPredictedBunnyMaxRotationDeg, ShadingModel::kPredictedShading},
                      TrackCase{"torus-textured-forward", 320, 240, kPredictedTorusMaxTranslationM,
                                kPredictedTorusMaxRotationDeg, ShadingModel::kPredictedShading}),
    [](const ::testing::TestParamInfo<TrackCase>& info) {
      std::string name = info.param.preset;
      for (char& ch : name)
        if (ch == '-') ch = '_';
      return name;
    });

// A keyframe's depth is refreshed every few frames while its image stays: the tracker keeps the image's
// pyramid then, recognising the image by its bytes. A tracker given another image and depth first, then
// this image (also rewritten in place in the same buffer, which must not reuse the stale pyramid), must
// track exactly as a fresh tracker given only the last image and depth.
TEST(TrackerTest, ANewDepthForTheSameImageTracksAsAFreshTracker) {
  SynthSequence seq;
  std::string why;
  if (!MakeSequence("bunny-multicolor-forward", 320, 240, &seq, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  const synth::RenderedFrame key = seq.Render(0), other = seq.Render(12), frame = seq.Render(3);
  const InverseDepthMap depth = GroundTruthInverseDepth(key.depth);
  InverseDepthMap scaled;  // another depth for the same image
  scaled.inverse_depth = depth.inverse_depth * 1.05;
  scaled.variance = depth.variance * (1.05 * 1.05);
  for (ShadingModel model : {ShadingModel::kLocalMeanNormalisation, ShadingModel::kPredictedShading}) {
    TrackerOptions options;
    options.shading_model = model;
    StatusOr<Tracker> fresh = Tracker::Create(seq.setup.rig, options);
    StatusOr<Tracker> reused = Tracker::Create(seq.setup.rig, options);
    ASSERT_TRUE(fresh.ok() && reused.ok());
    ASSERT_TRUE(fresh->SetKeyframe(key.rgb, scaled).ok());
    cv::Mat buffer = other.rgb.clone();
    ASSERT_TRUE(reused->SetKeyframe(buffer, GroundTruthInverseDepth(other.depth)).ok());
    key.rgb.copyTo(buffer);  // the same buffer, now holding the keyframe's image
    ASSERT_TRUE(reused->SetKeyframe(buffer, depth).ok());
    ASSERT_TRUE(reused->SetKeyframe(buffer, scaled).ok());  // the refresh: same image, new depth
    StatusOr<TrackingResult> a = fresh->Track(frame.rgb, Rigid3d());
    StatusOr<TrackingResult> b = reused->Track(frame.rgb, Rigid3d());
    ASSERT_TRUE(a.ok() && b.ok());
    EXPECT_TRUE(a->ok);
    EXPECT_EQ(a->frame_from_keyframe.translation, b->frame_from_keyframe.translation);
    EXPECT_EQ(a->frame_from_keyframe.rotation.coeffs(), b->frame_from_keyframe.rotation.coeffs());
    EXPECT_EQ(a->residual_rms, b->residual_rms);
    EXPECT_EQ(a->iterations, b->iterations);
  }
}

// SlamSystem hands the tracker's image of a frame to the depth filter in place of computing it again
// (their normalisations agree in SlamOptions): it must be KeyframeDepth::NormalisedGrey's, bit for bit.
TEST(TrackerTest, LastFrameGreyIsTheDepthFiltersNormalisedImage) {
  SynthSequence seq;
  std::string why;
  if (!MakeSequence("bunny-multicolor-forward", 320, 240, &seq, &why)) GTEST_SKIP() << "preset unavailable: " << why;
  const synth::RenderedFrame key = seq.Render(0), frame = seq.Render(3);
  const SlamOptions slam;
  StatusOr<Tracker> tracker = Tracker::Create(seq.setup.rig, slam.tracker);
  ASSERT_TRUE(tracker.ok()) << tracker.status();
  EXPECT_TRUE(tracker->last_frame_grey().empty());
  ASSERT_TRUE(tracker->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());
  ASSERT_TRUE(tracker->Track(frame.rgb, Rigid3d()).ok());
  cv::Mat j, mean;
  KeyframeDepth::NormalisedGrey(frame.rgb, slam.depth, &j, &mean);
  const cv::Mat& t = tracker->last_frame_grey();
  ASSERT_EQ(t.size(), j.size());
  ASSERT_EQ(t.type(), CV_32F);
  EXPECT_EQ(cv::norm(t, j, cv::NORM_INF), 0.0);
}

TEST(TrackerTest, RejectsInvalidInput) {
  SynthSequence seq;
  std::string why;
  ASSERT_TRUE(MakeSequence("sphere-multicolor-sideways", 320, 240, &seq, &why)) << why;
  TrackerOptions bad;
  bad.pyramid_levels = 0;
  EXPECT_FALSE(Tracker::Create(seq.setup.rig.camera, bad).ok());
  // The predicted shading needs the rig.
  TrackerOptions predicted;
  predicted.shading_model = ShadingModel::kPredictedShading;
  EXPECT_EQ(Tracker::Create(seq.setup.rig.camera, predicted).status().code(), StatusCode::kInvalidArgument);
  EXPECT_TRUE(Tracker::Create(seq.setup.rig, predicted).ok());
  StatusOr<Tracker> tracker = Tracker::Create(seq.setup.rig.camera, TrackerOptions());
  ASSERT_TRUE(tracker.ok()) << tracker.status();
  const synth::RenderedFrame key = seq.Render(0);
  // No keyframe yet.
  EXPECT_EQ(tracker->Track(key.rgb, Rigid3d()).status().code(), StatusCode::kFailedPrecondition);
  ASSERT_TRUE(tracker->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());
  cv::Mat wrong_size;
  cv::resize(key.rgb, wrong_size, cv::Size(160, 120));
  EXPECT_EQ(tracker->Track(wrong_size, Rigid3d()).status().code(), StatusCode::kInvalidArgument);
  cv::Mat grey(key.rgb.size(), CV_8U, cv::Scalar(0));
  EXPECT_EQ(tracker->Track(grey, Rigid3d()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_FALSE(tracker->SetKeyframe(wrong_size, GroundTruthInverseDepth(key.depth)).ok());
  // No depth at all: too few points.
  InverseDepthMap empty;
  empty.inverse_depth = cv::Mat::zeros(key.depth.size(), CV_32F);
  EXPECT_EQ(tracker->SetKeyframe(key.rgb, empty).code(), StatusCode::kFailedPrecondition);
}

// A keyframe refused for too few points (a new image without depth) leaves the tracker as it was: the
// next frame tracks against the previous keyframe exactly as on a tracker that never saw the refusal.
TEST(TrackerTest, ARefusedKeyframeLeavesTheTrackerAsItWas) {
  SynthSequence seq;
  std::string why;
  ASSERT_TRUE(MakeSequence("sphere-multicolor-sideways", 320, 240, &seq, &why)) << why;
  TrackerOptions options;
  options.camera_attached_min_votes = 2;  // as the SLAM runs it: per-keyframe vote images
  StatusOr<Tracker> refused = Tracker::Create(seq.setup.rig.camera, options);
  StatusOr<Tracker> plain = Tracker::Create(seq.setup.rig.camera, options);
  ASSERT_TRUE(refused.ok() && plain.ok());
  const synth::RenderedFrame key = seq.Render(0);
  ASSERT_TRUE(refused->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());
  ASSERT_TRUE(plain->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());
  const cv::Mat frame1 = seq.Render(1).rgb;
  ASSERT_TRUE(refused->Track(frame1, Rigid3d()).ok());
  ASSERT_TRUE(plain->Track(frame1, Rigid3d()).ok());
  InverseDepthMap empty;
  empty.inverse_depth = cv::Mat::zeros(key.depth.size(), CV_32F);
  EXPECT_EQ(refused->SetKeyframe(seq.Render(3).rgb, empty).code(), StatusCode::kFailedPrecondition);
  const cv::Mat frame2 = seq.Render(2).rgb;
  StatusOr<TrackingResult> a = refused->Track(frame2, Rigid3d()), b = plain->Track(frame2, Rigid3d());
  ASSERT_TRUE(a.ok() && b.ok());
  ASSERT_TRUE(b->ok);
  EXPECT_EQ(a->ok, b->ok);
  EXPECT_EQ(a->frame_from_keyframe.translation, b->frame_from_keyframe.translation);
  EXPECT_EQ(a->frame_from_keyframe.rotation.coeffs(), b->frame_from_keyframe.rotation.coeffs());
  EXPECT_EQ(a->residual_rms, b->residual_rms);
}

// A guess 90 degrees off (or a frame looking elsewhere) leaves the keyframe's points outside the
// image: reported as lost, not as a pose.
TEST(TrackerTest, HugeMotionIsReportedLost) {
  SynthSequence seq;
  std::string why;
  ASSERT_TRUE(MakeSequence("sphere-multicolor-sideways", 320, 240, &seq, &why)) << why;
  const synth::RenderedFrame key = seq.Render(0);
  StatusOr<Tracker> tracker = Tracker::Create(seq.setup.rig.camera, TrackerOptions());
  ASSERT_TRUE(tracker.ok()) << tracker.status();
  ASSERT_TRUE(tracker->SetKeyframe(key.rgb, GroundTruthInverseDepth(key.depth)).ok());
  const Rigid3d turned(Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitY())),
                       Eigen::Vector3d::Zero());
  StatusOr<TrackingResult> r = tracker->Track(seq.Render(1).rgb, turned);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->ok);
  EXPECT_FALSE(r->lost_reason.empty());
  // The camera turned away from the object: the frame sees none of the keyframe's points.
  const Rigid3d world_from_away =
      LookAt(seq.trajectory[0].world_from_camera.translation,
             seq.trajectory[0].world_from_camera * Eigen::Vector3d(-1, 0, 0.2), Eigen::Vector3d::UnitZ());
  const synth::RenderedFrame away =
      synth::RenderFrame(seq.setup.scene, seq.setup.rig, world_from_away, seq.setup.render, /*noise_seed=*/5);
  r = tracker->Track(away.rgb, Rigid3d());
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->ok) << "residual RMS " << r->residual_rms << ", inliers " << r->inlier_fraction << ", a "
                      << r->affine_a;
  std::printf("turned away: %s\n", r->lost_reason.c_str());
}

}  // namespace
}  // namespace prism

namespace prism {
namespace {

// On the uniform sphere the sphere's three cast shadows on the ground move with the lights, and so with
// the camera: with them in the cost the tracker, on true depth, finds about 0.7 of the true rotation
// and almost none of the translation over 10 frames. Left out after their votes (the SLAM's tracker
// options), it finds nearly all of both. Keyframes at frames 30 and 60, frames tracked in sequence from
// the true velocity.
TEST(TrackerTest, CameraAttachedPointsLeaveTheCost) {
  synth::PresetOptions o;
  o.width = 512;
  o.height = 512;
  o.frames = 150;
  o.seed = 1;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset("sphere-uniform-sideways", o);
  ASSERT_TRUE(setup.ok()) << setup.status();
  SynthSequence seq;
  seq.setup = std::move(setup).value();
  seq.trajectory = synth::MakeTrajectory(seq.setup.trajectory);
  // Measured: off 0.709 / 0.720 of the rotation, 0.061 / 0.260 of the translation; on 0.988 / 0.993 and
  // 0.972 / 0.968.
  constexpr double kMaxRotationFractionOff = 0.8;
  constexpr double kMinRotationFractionOn = 0.97;
  constexpr double kMinTranslationFractionOn = 0.93;
  for (bool on : {false, true}) {
    for (int key : {30, 60}) {
      TrackerOptions options = SlamOptions().tracker;
      ASSERT_EQ(options.camera_attached_min_votes, 2);
      if (!on) options.camera_attached_min_votes = 0;
      StatusOr<Tracker> tracker = Tracker::Create(seq.setup.rig, options);
      ASSERT_TRUE(tracker.ok()) << tracker.status();
      const synth::RenderedFrame k = seq.Render(key);
      ASSERT_TRUE(tracker->SetKeyframe(k.rgb, GroundTruthInverseDepth(k.depth)).ok());
      Rigid3d previous, before_previous = seq.FrameFromKeyframe(key - 1, key);
      for (int frame = key + 1; frame <= key + 10; ++frame) {
        StatusOr<TrackingResult> r =
            tracker->Track(seq.Render(frame).rgb, (previous * before_previous.Inverse()) * previous);
        ASSERT_TRUE(r.ok()) << r.status();
        EXPECT_TRUE(r->ok) << r->lost_reason;
        before_previous = previous;
        previous = r->frame_from_keyframe;
      }
      const Rigid3d truth = seq.FrameFromKeyframe(key + 10, key);
      const double rotation = RotationAngle(previous.rotation) / RotationAngle(truth.rotation);
      const double translation = previous.translation.dot(truth.translation) / truth.translation.squaredNorm();
      std::printf("camera-attached test %s, keyframe %d: %.3f of the rotation, %.3f of the translation\n",
                  on ? "on" : "off", key, rotation, translation);
      if (on) {
        EXPECT_GT(rotation, kMinRotationFractionOn);
        EXPECT_GT(translation, kMinTranslationFractionOn);
      } else {
        EXPECT_LT(rotation, kMaxRotationFractionOff);
      }
    }
  }
}

TEST(TrackerOptions, RejectsInvalidCameraAttachedValues) {
  TrackerOptions o;
  o.camera_attached_min_votes = -1;
  EXPECT_FALSE(o.Check().ok());
  o = TrackerOptions();
  o.camera_attached_min_flow_px = 0;
  EXPECT_FALSE(o.Check().ok());
  o = TrackerOptions();
  o.camera_attached_residual_ratio = 0;
  EXPECT_FALSE(o.Check().ok());
  o.camera_attached_residual_ratio = 1.5;
  EXPECT_FALSE(o.Check().ok());
}

}  // namespace
}  // namespace prism
