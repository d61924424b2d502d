#include <filesystem>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "core/io/sequence.h"
#include "core/synth/families.h"
#include "core/synth/mesh_bvh.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/shapes.h"
#include "core/synth/synthesize.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism::synth {
namespace {
namespace fs = std::filesystem;

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / M_PI;
}

// A sphere of radius 0.1 at (0, 0, 0.1) above the ground, seen from a fixed pose.
struct SphereFixture {
  SphereFixture(bool shadows, double noise) {
    PresetOptions o;
    o.width = 160;
    o.height = 120;
    o.frames = 2;
    setup = MakePreset("sphere-uniform-sideways", o).value();
    setup.render.cast_shadows = shadows;
    setup.render.noise_sigma = noise;
    setup.render.shot_noise = noise > 0 ? 0.05 : 0.0;
    pose = LookAt(Eigen::Vector3d(0.35, -0.3, 0.35), Eigen::Vector3d(0, 0, 0.1), Eigen::Vector3d::UnitZ());
    frame = RenderFrame(setup.scene, setup.rig, pose, setup.render, 7);
  }
  SynthSetup setup;
  Rigid3d pose;
  RenderedFrame frame;
};

TEST(RendererTest, SphereDepthAndNormalsMatchTheAnalyticSphere) {
  SphereFixture f(/*shadows=*/true, /*noise=*/1.0);
  const Eigen::Vector3d centre(0, 0, 0.1);
  const double radius = 0.1;
  const Rigid3d camera_from_world = f.pose.Inverse();
  const Eigen::Vector3d centre_in_camera = camera_from_world * centre;
  int object_pixels = 0;
  double max_depth_err = 0, max_angle_deg = 0;
  for (int y = 0; y < f.frame.depth.rows; ++y)
    for (int x = 0; x < f.frame.depth.cols; ++x) {
      if (f.frame.mask.at<uint8_t>(y, x) != 255) continue;
      ++object_pixels;
      // Analytic ray-sphere intersection in the camera frame.
      const Eigen::Vector3d d = f.setup.rig.camera.Unproject(Eigen::Vector2d(x, y)).normalized();
      const double b = d.dot(centre_in_camera);
      const double disc = b * b - (centre_in_camera.squaredNorm() - radius * radius);
      ASSERT_GE(disc, 0) << "object pixel whose ray misses the analytic sphere at " << x << "," << y;
      const double t = b - std::sqrt(disc);
      const Eigen::Vector3d p = t * d;
      const Eigen::Vector3d n = (p - centre_in_camera) / radius;
      max_depth_err = std::max(max_depth_err, std::abs(f.frame.depth.at<float>(y, x) - p.z()));
      const cv::Vec3f rn = f.frame.normals.at<cv::Vec3f>(y, x);
      max_angle_deg = std::max(max_angle_deg, AngleDeg(Eigen::Vector3d(rn[0], rn[1], rn[2]), n));
    }
  EXPECT_GT(object_pixels, 2000);
  EXPECT_LT(max_depth_err, /*max_depth_error_m=*/1e-6);
  EXPECT_LT(max_angle_deg, /*max_normal_error_deg=*/1e-3);
}

TEST(RendererTest, LambertPerChannelWithCrosstalkAtChosenPixels) {
  SphereFixture f(/*shadows=*/false, /*noise=*/0.0);
  const RigCalibration& rig = f.setup.rig;
  ASSERT_GT((rig.crosstalk - Eigen::Matrix3d::Identity()).norm(), 0.1) << "default crosstalk must not be identity";
  const Eigen::Vector3d albedo = f.setup.scene.objects()[1].albedo.base;
  int checked = 0;
  for (int y = 10; y < f.frame.depth.rows; y += 9)
    for (int x = 10; x < f.frame.depth.cols; x += 11) {
      if (f.frame.mask.at<uint8_t>(y, x) != 255) continue;
      const double z = f.frame.depth.at<float>(y, x);
      const Eigen::Vector3d p = rig.camera.Unproject(Eigen::Vector2d(x, y)) * z;
      const cv::Vec3f nv = f.frame.normals.at<cv::Vec3f>(y, x);
      const Eigen::Vector3d n(nv[0], nv[1], nv[2]);
      // Lambert per light band, then the crosstalk mixes bands into camera channels.
      Eigen::Vector3d per_light;
      for (int l = 0; l < 3; ++l) {
        const Eigen::Vector3d to_light = rig.lights[l].position_in_camera - p;
        const double d2 = to_light.squaredNorm();
        per_light[l] = albedo[l] * rig.lights[l].intensity / d2 * std::max(0.0, n.dot(to_light.normalized()));
      }
      const Eigen::Vector3d expected = rig.crosstalk * per_light;
      const cv::Vec3f rad = f.frame.radiance.at<cv::Vec3f>(y, x);
      const cv::Vec3b rgb = f.frame.rgb.at<cv::Vec3b>(y, x);
      for (int c = 0; c < 3; ++c) {
        // Depth and normals are stored as float: a relative 1e-4 covers their rounding.
        EXPECT_NEAR(rad[c], expected[c], /*max_radiance_error=*/1e-4 + 1e-4 * expected[c]) << x << "," << y;
        EXPECT_NEAR(rgb[c], std::min(255.0, std::round(255.0 * expected[c])), /*max_level_error=*/1.0);
      }
      ++checked;
    }
  EXPECT_GT(checked, 20);
}

TEST(RendererTest, CastShadowsDarkenOnlyOccludedGround) {
  SphereFixture lit(/*shadows=*/false, 0.0), shadowed(/*shadows=*/true, 0.0);
  int darker = 0;
  for (int y = 0; y < lit.frame.rgb.rows; ++y)
    for (int x = 0; x < lit.frame.rgb.cols; ++x) {
      const cv::Vec3f a = lit.frame.radiance.at<cv::Vec3f>(y, x), b = shadowed.frame.radiance.at<cv::Vec3f>(y, x);
      for (int c = 0; c < 3; ++c) EXPECT_LE(b[c], a[c] + 1e-6f);
      if (b[0] + b[1] + b[2] < a[0] + a[1] + a[2] - 1e-3f) {
        ++darker;
        // A convex sphere never shadows itself: only the ground darkens.
        EXPECT_EQ(lit.frame.mask.at<uint8_t>(y, x), 64) << x << "," << y;
      }
    }
  EXPECT_GT(darker, 100) << "the sphere must cast visible shadows on the ground";
}

TEST(RendererTest, NoiseIsDeterministicForASeed) {
  SphereFixture a(true, 2.0), b(true, 2.0);
  EXPECT_EQ(cv::norm(a.frame.rgb, b.frame.rgb, cv::NORM_INF), 0.0);
  const RenderedFrame c = RenderFrame(a.setup.scene, a.setup.rig, a.pose, a.setup.render, 8);
  EXPECT_GT(cv::norm(a.frame.rgb, c.rgb, cv::NORM_L1), 0.0);
  ThreadPool pool(2);
  const RenderedFrame d = RenderFrame(a.setup.scene, a.setup.rig, a.pose, a.setup.render, 7, &pool);
  EXPECT_EQ(cv::norm(a.frame.rgb, d.rgb, cv::NORM_INF), 0.0) << "threading must not change the image";
}

// Supersampling n x n must equal point sampling at n times the resolution, averaged over n x n
// blocks (the sub-pixel rays are exactly the fine pixels' centres), and keep the centre ray's
// depth, normals and mask.
TEST(RendererTest, SupersamplingIntegratesThePixelArea) {
  constexpr int kN = 3;
  SphereFixture f(/*shadows=*/true, /*noise=*/0.0);
  RenderOptions options = f.setup.render;
  options.supersampling = kN;
  ASSERT_TRUE(options.Check().ok());
  const RenderedFrame ss = RenderFrame(f.setup.scene, f.setup.rig, f.pose, options, 7);

  RigCalibration fine = f.setup.rig;
  fine.camera.width *= kN;
  fine.camera.height *= kN;
  fine.camera.fx *= kN;
  fine.camera.fy *= kN;
  // Fine pixel i covers coarse coordinate (i - (kN - 1) / 2) / kN.
  fine.camera.cx = kN * f.setup.rig.camera.cx + 0.5 * (kN - 1);
  fine.camera.cy = kN * f.setup.rig.camera.cy + 0.5 * (kN - 1);
  const RenderedFrame hi = RenderFrame(f.setup.scene, fine, f.pose, f.setup.render, 7);
  cv::Mat block_mean;
  cv::resize(hi.radiance, block_mean, ss.radiance.size(), 0, 0, cv::INTER_AREA);
  EXPECT_LT(cv::norm(ss.radiance, block_mean, cv::NORM_INF), 1e-4);

  EXPECT_EQ(cv::norm(ss.depth, f.frame.depth, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(ss.normals, f.frame.normals, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(ss.mask, f.frame.mask, cv::NORM_INF), 0.0);
  // Silhouette pixels whose centre ray misses now carry part of the sphere's light, and the
  // interior, where shading is smooth, stays close to the point-sampled value.
  int partial = 0;
  double interior_max_diff = 0;
  for (int y = 1; y < ss.mask.rows - 1; ++y)
    for (int x = 1; x < ss.mask.cols - 1; ++x) {
      const cv::Vec3f a = ss.radiance.at<cv::Vec3f>(y, x), b = f.frame.radiance.at<cv::Vec3f>(y, x);
      if (f.frame.mask.at<uint8_t>(y, x) == 0 && a[0] + a[1] + a[2] > 1e-3f) ++partial;
      bool interior = true;
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) interior &= f.frame.mask.at<uint8_t>(y + dy, x + dx) == 255;
      if (interior) interior_max_diff = std::max(interior_max_diff, cv::norm(a - b, cv::NORM_INF));
    }
  EXPECT_GT(partial, 20);
  EXPECT_LT(interior_max_diff, 0.02) << "smooth shading must not change by more than 2% of full scale";

  options.supersampling = 0;
  EXPECT_FALSE(options.Check().ok());
  options.supersampling = 9;
  EXPECT_FALSE(options.Check().ok());
}

TEST(MeshBvhTest, ClosestHitEqualsBruteForce) {
  TriangleMesh torus = MakeTorus(0.08, 0.03, 48, 24);
  const MeshBvh bvh(torus);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-0.15, 0.15);
  int hits = 0;
  for (int i = 0; i < 500; ++i) {
    const Eigen::Vector3d origin(u(rng), u(rng), 0.5);
    const Eigen::Vector3d dir = (Eigen::Vector3d(u(rng), u(rng), u(rng) * 0.2) - origin).normalized();
    double best = 1e300;
    for (const Eigen::Vector3i& f : torus.faces) {
      const Eigen::Vector3d& v0 = torus.vertices[f[0]];
      const Eigen::Vector3d e1 = torus.vertices[f[1]] - v0, e2 = torus.vertices[f[2]] - v0;
      const Eigen::Matrix3d m = (Eigen::Matrix3d() << -dir, e1, e2).finished();
      const Eigen::Vector3d tuv = m.inverse() * (origin - v0);
      if (tuv[0] > 0 && tuv[1] >= 0 && tuv[2] >= 0 && tuv[1] + tuv[2] <= 1) best = std::min(best, tuv[0]);
    }
    RayHit hit;
    const bool found = bvh.Intersect(origin, dir, 0, 1e9, &hit);
    EXPECT_EQ(found, best < 1e300);
    if (found) {
      ++hits;
      EXPECT_NEAR(hit.t, best, 1e-9);
      EXPECT_TRUE(bvh.Occluded(origin, dir, 0, best + 1e-6));
      EXPECT_FALSE(bvh.Occluded(origin, dir, 0, best - 1e-6));
    }
  }
  EXPECT_GT(hits, 50);
}

TEST(TrajectoryTest, ForwardAndSidewaysStartsMoveAsNamed) {
  for (TrajectoryStart start : {TrajectoryStart::kForward, TrajectoryStart::kSideways}) {
    TrajectoryOptions o;
    o.start = start;
    o.frames = 60;
    const Trajectory t = MakeTrajectory(o);
    ASSERT_EQ(t.size(), 60u);
    const Eigen::Vector3d motion = t[3].world_from_camera.translation - t[0].world_from_camera.translation;
    const Eigen::Vector3d motion_in_camera = t[0].world_from_camera.rotation.conjugate() * motion;
    const double forwardness = std::abs(motion_in_camera.z()) / motion_in_camera.norm();
    if (start == TrajectoryStart::kForward) {
      EXPECT_GT(forwardness, 0.9);
      EXPECT_GT(motion_in_camera.z(), 0) << "forward start must approach the target";
    } else {
      EXPECT_LT(forwardness, 0.3);
    }
    EXPECT_NEAR(t[1].timestamp_s - t[0].timestamp_s, 1.0 / 30.0, 1e-6);
  }
}

class SynthesizeTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_synth_test_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

TEST_F(SynthesizeTest, WrittenPosesDepthAndNormalsAreTheOnesUsed) {
  PresetOptions o;
  o.width = 96;
  o.height = 72;
  o.frames = 6;
  o.seed = 5;
  const SynthSetup setup = MakePreset("sphere-multicolor-sideways", o).value();
  ThreadPool pool(2);
  auto summary = SynthesizeSequence(setup, o.seed, dir_.string(), &pool);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->frames, 6);

  auto seq = LoadSequence(dir_.string());
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_EQ(seq->frames.size(), 6u);
  ASSERT_TRUE(seq->has_calibration);
  const Trajectory used = MakeTrajectory(setup.trajectory);
  ASSERT_EQ(seq->groundtruth.size(), used.size());
  for (size_t i = 0; i < used.size(); ++i) {
    EXPECT_NEAR(seq->groundtruth[i].timestamp_s, used[i].timestamp_s, 1e-9);
    EXPECT_LT((seq->groundtruth[i].world_from_camera.translation - used[i].world_from_camera.translation).norm(),
              /*max_written_position_error_m=*/1e-8);
    EXPECT_LT(
        RotationAngle(seq->groundtruth[i].world_from_camera.rotation * used[i].world_from_camera.rotation.conjugate()),
        /*max_written_rotation_error_rad=*/1e-8);
  }
  // Depth and normals re-read from disk match a fresh render of the same pose.
  const RenderedFrame f = RenderFrame(setup.scene, setup.rig, used[3].world_from_camera, setup.render, 0);
  const cv::Mat depth = seq->ReadDepth(3).value();
  const cv::Mat normals = seq->ReadNormals(3).value();
  double max_depth_err = 0, max_angle = 0;
  for (int y = 0; y < depth.rows; ++y)
    for (int x = 0; x < depth.cols; ++x) {
      if (f.depth.at<float>(y, x) <= 0) continue;
      max_depth_err =
          std::max(max_depth_err, static_cast<double>(std::abs(depth.at<float>(y, x) - f.depth.at<float>(y, x))));
      const cv::Vec3f a = normals.at<cv::Vec3f>(y, x), b = f.normals.at<cv::Vec3f>(y, x);
      max_angle = std::max(max_angle, AngleDeg(Eigen::Vector3d(a[0], a[1], a[2]), Eigen::Vector3d(b[0], b[1], b[2])));
    }
  EXPECT_LT(max_depth_err, /*half a TUM depth step=*/0.5 / 5000 + 1e-6);
  EXPECT_LT(max_angle, /*max_normal_quantisation_deg=*/0.01);
  // Back-projected ground pixels lie on the plane z = 0.
  const cv::Mat mask = seq->ReadMask(3).value();
  const Rigid3d pose = seq->GroundTruthPose(3).value();
  int ground = 0;
  for (int y = 0; y < depth.rows; y += 3)
    for (int x = 0; x < depth.cols; x += 3) {
      if (mask.at<uint8_t>(y, x) != 64) continue;
      const Eigen::Vector3d p =
          pose * (seq->calibration.camera.Unproject(Eigen::Vector2d(x, y)) * depth.at<float>(y, x));
      EXPECT_NEAR(p.z(), 0.0, /*max_ground_height_error_m=*/1e-3);
      ++ground;
    }
  EXPECT_GT(ground, 50);
}

TEST_F(SynthesizeTest, SameSeedSameImagesDifferentSeedDifferentImages) {
  PresetOptions o;
  o.width = 64;
  o.height = 48;
  o.frames = 2;
  const SynthSetup setup = MakePreset("sphere-uniform-forward", o).value();
  ASSERT_TRUE(SynthesizeSequence(setup, 1, (dir_ / "a").string(), nullptr).ok());
  ThreadPool pool(2);
  ASSERT_TRUE(SynthesizeSequence(setup, 1, (dir_ / "b").string(), &pool).ok());
  ASSERT_TRUE(SynthesizeSequence(setup, 2, (dir_ / "c").string(), nullptr).ok());
  auto a = LoadSequence((dir_ / "a").string()).value().ReadRgb(1).value();
  auto b = LoadSequence((dir_ / "b").string()).value().ReadRgb(1).value();
  auto c = LoadSequence((dir_ / "c").string()).value().ReadRgb(1).value();
  EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0.0);
  EXPECT_GT(cv::norm(a, c, cv::NORM_L1), 0.0);
}

TEST(PresetTest, EveryPresetBuildsAndShowsItsObject) {
  const auto presets = ListPresets();
  ASSERT_GE(presets.size(), 3u);
  EXPECT_EQ(presets.front().name, "bunny-multicolor-forward");
  for (const PresetInfo& p : presets) {
    PresetOptions o;
    o.width = 64;
    o.height = 64;
    o.frames = 2;
    auto setup = MakePreset(p.name, o);
    if (!setup.ok() && setup.status().code() == StatusCode::kNotFound) {
      GTEST_SKIP() << "mesh for " << p.name << " missing (install libcgal-demo): " << setup.status();
    }
    ASSERT_TRUE(setup.ok()) << p.name << ": " << setup.status();
    const Trajectory t = MakeTrajectory(setup->trajectory);
    const RenderedFrame f = RenderFrame(setup->scene, setup->rig, t[0].world_from_camera, setup->render, 1);
    const int object_pixels = cv::countNonZero(f.mask == 255);
    EXPECT_GT(object_pixels, 64 * 64 / 20) << p.name << ": the object should fill a good part of the view";
    EXPECT_GT(cv::mean(f.rgb)[0] + cv::mean(f.rgb)[1] + cv::mean(f.rgb)[2], 30.0) << p.name << " is too dark";
  }
  EXPECT_EQ(MakePreset("no-such-preset", PresetOptions()).status().code(), StatusCode::kNotFound);
  PresetOptions bad;
  bad.width = 3;
  EXPECT_EQ(MakePreset("sphere-uniform-sideways", bad).status().code(), StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace prism::synth

namespace prism::synth {
namespace {

// Every family draws scenes whose objects are in view, lit and of the documented size, for many seeds.
TEST(FamilyTest, DrawnScenesShowTheirObjectsLitAndMoveWithinTheRanges) {
  constexpr int kSeeds = 12;
  // Dark objects at the start of a forward path (lit for 0.7 of its distance) reach a grey sum of about 45.
  for (const FamilyInfo& family : ListFamilies()) {
    for (uint32_t seed = 1; seed <= kSeeds; ++seed) {
      FamilyOptions fo;
      fo.family = family.name;
      fo.width = fo.height = 128;
      StatusOr<SynthSetup> setup = MakeRandomScene(seed, fo);
      ASSERT_TRUE(setup.ok()) << family.name << " " << seed << ": " << setup.status();
      const Trajectory traj = setup->Poses();
      ASSERT_GE(traj.size(), 150u);
      ASSERT_LE(traj.size(), 300u);
      Eigen::Vector3d centre;
      double radius = 0;
      setup->scene.ObjectBounds(&centre, &radius);
      ASSERT_TRUE(centre.allFinite() && radius > 0) << family.name << " " << seed;
      for (size_t i : {size_t{0}, traj.size() / 2, traj.size() - 1}) {
        const RenderedFrame f = RenderSequenceFrame(*setup, traj, i, 7);
        const double object_fraction = cv::countNonZero(f.mask == 255) / static_cast<double>(f.mask.total());
        const double surface_fraction = cv::countNonZero(f.mask) / static_cast<double>(f.mask.total());
        const cv::Scalar mean = cv::mean(f.rgb, f.mask);
        EXPECT_GT(object_fraction, /*min_object_in_view=*/0.01) << family.name << " seed " << seed << " frame " << i;
        EXPECT_GT(surface_fraction, /*min_surface_in_view=*/0.5) << family.name << " seed " << seed << " frame " << i;
        EXPECT_GT(mean[0] + mean[1] + mean[2], /*min_mean_grey_sum=*/30) << family.name << " seed " << seed;
        EXPECT_LT(mean[0] + mean[1] + mean[2], /*max_mean_grey_sum=*/600) << family.name << " seed " << seed;
      }
      // Per-frame rotation within the family's bound (3 deg plus jitter of up to 1 deg twice).
      for (size_t i = 1; i < traj.size(); ++i) {
        const double step_deg =
            Eigen::AngleAxisd(traj[i - 1].world_from_camera.rotation.conjugate() * traj[i].world_from_camera.rotation)
                .angle() *
            180 / M_PI;
        EXPECT_LT(step_deg, /*max_rotation_per_frame_deg=*/3.0 + 2 * 3.0) << family.name << " seed " << seed;
      }
    }
  }
}

TEST(FamilyTest, SameSeedSameSceneAndWorldLightsStayPut) {
  FamilyOptions fo;
  fo.width = fo.height = 96;
  StatusOr<SynthSetup> a = MakeRandomScene(5, fo), b = MakeRandomScene(5, fo);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->notes, b->notes);
  const Trajectory ta = a->Poses(), tb = b->Poses();
  ASSERT_EQ(ta.size(), tb.size());
  EXPECT_TRUE(ta.back().world_from_camera.translation.isApprox(tb.back().world_from_camera.translation));
  fo.lights_fixed_in_world = true;
  StatusOr<SynthSetup> w = MakeRandomScene(5, fo);
  ASSERT_TRUE(w.ok());
  const Trajectory tw = w->Poses();
  // The red light's place in the world is the same in every frame.
  const Eigen::Vector3d first = tw[0].world_from_camera * RigAtFrame(*w, tw, 0).lights[0].position_in_camera;
  const Eigen::Vector3d last =
      tw.back().world_from_camera * RigAtFrame(*w, tw, tw.size() - 1).lights[0].position_in_camera;
  EXPECT_LT((first - last).norm(), 1e-9);
  FamilyOptions unknown;
  unknown.family = "no-such-family";
  EXPECT_EQ(MakeRandomScene(5, unknown).status().code(), StatusCode::kNotFound);
}

}  // namespace
}  // namespace prism::synth
