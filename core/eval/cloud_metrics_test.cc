#include "core/eval/cloud_metrics.h"

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <limits>
#include <random>

#include <gtest/gtest.h>

#include "core/eval/nearest_neighbor_grid.h"
#include "core/io/image_io.h"
#include "core/io/sequence.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

// Float coordinates carry ~1e-7 relative rounding.
constexpr double kFloatToleranceM = 1e-6;

// A square patch of the plane z = z0 sampled every `spacing_m`, x, y in [0, n * spacing).
std::vector<Eigen::Vector3f> PlanePatch(int n, double spacing_m, double z0) {
  std::vector<Eigen::Vector3f> points;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      points.emplace_back(static_cast<float>(i * spacing_m), static_cast<float>(j * spacing_m), static_cast<float>(z0));
  return points;
}

double BruteForceNearest(const std::vector<Eigen::Vector3f>& points, const Eigen::Vector3f& q) {
  double best = std::numeric_limits<double>::infinity();
  for (const auto& p : points) best = std::min(best, (p.cast<double>() - q.cast<double>()).norm());
  return best;
}

TEST(NearestNeighborGridTest, MatchesBruteForceNearAndFar) {
  std::mt19937 rng(21);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  // Points on a unit sphere plus a sparse cloud around it: many cells, uneven density.
  std::vector<Eigen::Vector3f> points;
  for (int i = 0; i < 3000; ++i) points.push_back(Eigen::Vector3f(normal(rng), normal(rng), normal(rng)).normalized());
  for (int i = 0; i < 200; ++i) points.push_back(3.0f * Eigen::Vector3f(normal(rng), normal(rng), normal(rng)));
  const NearestNeighborGrid grid(points, /*cell_size_m=*/0.02);
  EXPECT_EQ(grid.size(), points.size());
  for (int k = 0; k < 300; ++k) {
    // Near the surface, inside, and far away (up to ~1 km: reconstruction outliers).
    const float reach = k % 3 == 0 ? 0.05f : (k % 3 == 1 ? 2.0f : 500.0f);
    const Eigen::Vector3f q = Eigen::Vector3f(normal(rng), normal(rng), normal(rng)).normalized() +
                              reach * Eigen::Vector3f(normal(rng), normal(rng), normal(rng));
    const double truth = BruteForceNearest(points, q);
    EXPECT_EQ(grid.NearestDistance(q), truth) << "query " << q.transpose();
    // Bounded: the distance when within the bound, infinity otherwise.
    const double bound = 0.03;
    const double bounded = grid.NearestDistance(q, bound);
    if (truth <= bound) EXPECT_EQ(bounded, truth);
    else EXPECT_TRUE(std::isinf(bounded));
  }
}

TEST(NearestNeighborGridTest, EmptyAndNegativeCoordinates) {
  const NearestNeighborGrid empty({}, 0.1);
  EXPECT_TRUE(std::isinf(empty.NearestDistance(Eigen::Vector3f::Zero())));
  // Cells on both sides of 0 (floor division of negative indices).
  const NearestNeighborGrid grid({Eigen::Vector3f(-0.05f, -0.05f, -0.05f), Eigen::Vector3f(0.05f, 0.05f, 0.05f)}, 0.1);
  EXPECT_NEAR(grid.NearestDistance(Eigen::Vector3f(-0.06f, -0.05f, -0.05f)), 0.01, kFloatToleranceM);
  EXPECT_NEAR(grid.NearestDistance(Eigen::Vector3f(0.05f, 0.05f, 0.35f)), 0.3, kFloatToleranceM);
}

TEST(EvaluateCloudTest, IdenticalCloudIsPerfect) {
  const std::vector<Eigen::Vector3f> plane = PlanePatch(60, 0.001, 0.5);
  const auto metrics = EvaluateCloud(plane, plane, CloudEvalOptions());
  ASSERT_TRUE(metrics.ok()) << metrics.status();
  EXPECT_EQ(metrics->accuracy_mean_m, 0.0);
  EXPECT_EQ(metrics->accuracy_median_m, 0.0);
  EXPECT_EQ(metrics->precision, 1.0);
  EXPECT_EQ(metrics->completeness, 1.0);
  EXPECT_EQ(metrics->fscore, 1.0);
  EXPECT_EQ(metrics->points, plane.size());
  EXPECT_EQ(metrics->gt_samples, plane.size());
}

TEST(EvaluateCloudTest, ShiftedCloudHasThatAccuracy) {
  const std::vector<Eigen::Vector3f> gt = PlanePatch(60, 0.001, 0.5);
  CloudEvalOptions options;
  options.tau_m = 0.005;
  // 2 mm off the surface: inside tau.
  auto metrics = EvaluateCloud(PlanePatch(60, 0.001, 0.502), gt, options);
  ASSERT_TRUE(metrics.ok()) << metrics.status();
  EXPECT_NEAR(metrics->accuracy_mean_m, 0.002, kFloatToleranceM);
  EXPECT_NEAR(metrics->accuracy_median_m, 0.002, kFloatToleranceM);
  EXPECT_EQ(metrics->fscore, 1.0);
  // 8 mm off: outside tau, nothing counts.
  metrics = EvaluateCloud(PlanePatch(60, 0.001, 0.508), gt, options);
  ASSERT_TRUE(metrics.ok());
  EXPECT_NEAR(metrics->accuracy_mean_m, 0.008, kFloatToleranceM);
  EXPECT_EQ(metrics->precision, 0.0);
  EXPECT_EQ(metrics->completeness, 0.0);
  EXPECT_EQ(metrics->fscore, 0.0);
}

TEST(EvaluateCloudTest, MissingHalfLowersCompletenessOnly) {
  const std::vector<Eigen::Vector3f> gt = PlanePatch(100, 0.001, 0.0);
  std::vector<Eigen::Vector3f> half;
  for (const auto& p : gt)
    if (p.x() < 0.0495f) half.push_back(p);  // columns x = 0 .. 49 mm
  CloudEvalOptions options;
  options.tau_m = 0.0045;
  ThreadPool pool(2);
  const auto metrics = EvaluateCloud(half, gt, options, &pool);
  ASSERT_TRUE(metrics.ok()) << metrics.status();
  // Ground-truth columns 0 .. 53 mm lie within 4.5 mm of the reconstruction.
  EXPECT_DOUBLE_EQ(metrics->completeness, 0.54);
  EXPECT_EQ(metrics->precision, 1.0);
  EXPECT_DOUBLE_EQ(metrics->fscore, 2.0 * 0.54 / 1.54);
}

TEST(EvaluateCloudTest, OutliersAndNonFinitePoints) {
  const std::vector<Eigen::Vector3f> gt = PlanePatch(10, 0.001, 0.0);
  std::vector<Eigen::Vector3f> cloud = gt;  // 100 exact points
  cloud.emplace_back(0.0f, 0.0f, 10.0f);    // one outlier 10 m above the corner
  cloud.emplace_back(std::nanf(""), 0.0f, 0.0f);
  const auto metrics = EvaluateCloud(cloud, gt, CloudEvalOptions());
  ASSERT_TRUE(metrics.ok()) << metrics.status();
  EXPECT_EQ(metrics->points, 101u);
  EXPECT_EQ(metrics->non_finite_points, 1u);
  EXPECT_NEAR(metrics->accuracy_mean_m, 10.0 / 101.0, kFloatToleranceM);
  EXPECT_EQ(metrics->accuracy_median_m, 0.0);
  EXPECT_DOUBLE_EQ(metrics->precision, 100.0 / 101.0);
  EXPECT_EQ(metrics->completeness, 1.0);
}

TEST(EvaluateCloudTest, BadInputIsAnError) {
  const std::vector<Eigen::Vector3f> gt = PlanePatch(5, 0.001, 0.0);
  EXPECT_EQ(EvaluateCloud({}, gt, CloudEvalOptions()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(EvaluateCloud(gt, {}, CloudEvalOptions()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(EvaluateCloud({Eigen::Vector3f(std::nanf(""), 0, 0)}, gt, CloudEvalOptions()).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(EvaluateCloud(gt, {Eigen::Vector3f(1e30f, 0, 0)}, CloudEvalOptions()).status().code(),
            StatusCode::kInvalidArgument);
  CloudEvalOptions bad;
  bad.tau_m = 0.0;
  EXPECT_EQ(EvaluateCloud(gt, gt, bad).status().code(), StatusCode::kInvalidArgument);
}

TEST(VoxelDownsampleTest, CentroidPerVoxel) {
  const std::vector<Eigen::Vector3f> points = {
      {0.01f, 0.01f, 0.01f}, {0.03f, 0.05f, 0.07f}, {0.15f, 0.0f, 0.0f}, {std::nanf(""), 0.0f, 0.0f}};
  const std::vector<Eigen::Vector3f> out = VoxelDownsample(points, 0.1);
  ASSERT_EQ(out.size(), 2u);
  EXPECT_LT((out[0] - Eigen::Vector3f(0.02f, 0.03f, 0.04f)).norm(), kFloatToleranceM);
  EXPECT_LT((out[1] - Eigen::Vector3f(0.15f, 0.0f, 0.0f)).norm(), kFloatToleranceM);
  EXPECT_EQ(VoxelDownsample(points, 0.0).size(), points.size());
}

// A small sequence: a fronto-parallel wall 1 m in front of a camera sliding along x, an object
// rectangle in the middle of the mask.
class SurfaceSamplingTest : public ::testing::Test {
 protected:
  static constexpr int kWidth = 32;
  static constexpr int kHeight = 24;
  static constexpr int kFrames = 6;

  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_eval_cloud_test_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    RigCalibration calibration;
    calibration.camera = PinholeCamera::FromFov(kWidth, kHeight, 60.0);
    calibration.camera.distortion = {0.02, -0.01, 0.0, 0.0, 0.0};
    auto writer = SequenceWriter::Create(dir_.string(), calibration);
    ASSERT_TRUE(writer.ok()) << writer.status();
    Trajectory gt;
    const cv::Mat depth(kHeight, kWidth, CV_32FC1, cv::Scalar(1.0));
    cv::Mat mask(kHeight, kWidth, CV_8UC1, cv::Scalar(kMaskBackground));
    mask(cv::Rect(8, 6, 16, 12)).setTo(kMaskObject);
    for (int i = 0; i < kFrames; ++i) {
      const double t = 1.0 + i * 0.1;
      ASSERT_TRUE(writer->WriteFrame(t, cv::Mat(), depth, cv::Mat(), mask).ok());
      gt.push_back({t, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.05 * i, 0.0, 0.0))});
    }
    ASSERT_TRUE(writer->Finish(gt, /*has_depth=*/true, /*has_normals=*/false, /*has_mask=*/true).ok());
    auto sequence = LoadSequence(dir_.string());
    ASSERT_TRUE(sequence.ok()) << sequence.status();
    sequence_ = *sequence;
  }
  void TearDown() override { fs::remove_all(dir_); }

  fs::path dir_;
  Sequence sequence_;
};

TEST_F(SurfaceSamplingTest, BackProjectsGroundTruthDepth) {
  SurfaceSamplingOptions options;
  options.frame_step = 2;
  options.voxel_size_m = 0.0;
  auto samples = SampleGroundTruthSurface(sequence_, options);
  ASSERT_TRUE(samples.ok()) << samples.status();
  EXPECT_EQ(samples->frames_used, 3u);  // frames 0, 2, 4
  EXPECT_EQ(samples->points_in_world.size(), 3u * kWidth * kHeight);
  for (const auto& p : samples->points_in_world) EXPECT_NEAR(p.z(), 1.0, kFloatToleranceM);

  options.object_only = true;
  samples = SampleGroundTruthSurface(sequence_, options);
  ASSERT_TRUE(samples.ok());
  EXPECT_EQ(samples->points_in_world.size(), 3u * 16u * 12u);

  // Downsampling keeps the samples on the wall and thins them out.
  options.voxel_size_m = 0.05;
  const auto coarse = SampleGroundTruthSurface(sequence_, options);
  ASSERT_TRUE(coarse.ok());
  EXPECT_LT(coarse->points_in_world.size(), samples->points_in_world.size());
  for (const auto& p : coarse->points_in_world) EXPECT_NEAR(p.z(), 1.0, kFloatToleranceM);

  // Bounds of the object samples: the wall at z = 1, x spanning the slide of 0.2 m plus the object width.
  const auto bounds = GroundTruthSurfaceBounds(sequence_, options);
  ASSERT_TRUE(bounds.ok()) << bounds.status();
  EXPECT_NEAR(bounds->min().z(), 1.0, kFloatToleranceM);
  EXPECT_NEAR(bounds->max().z(), 1.0, kFloatToleranceM);
  EXPECT_GT(bounds->sizes().x(), 0.2);
}

TEST_F(SurfaceSamplingTest, ObjectPixelCoverageOfItsOwnBackProjection) {
  SurfaceSamplingOptions options;
  options.frame_step = 100;  // frame 0 only
  options.voxel_size_m = 0.0;
  options.object_only = true;
  const auto samples = SampleGroundTruthSurface(sequence_, options);
  ASSERT_TRUE(samples.ok()) << samples.status();
  const auto mask = sequence_.ReadMask(0);
  const auto pose = sequence_.GroundTruthPose(0);
  ASSERT_TRUE(mask.ok() && pose.ok());
  const PinholeCamera& camera = sequence_.calibration.camera;

  auto coverage = ObjectPixelCoverage(samples->points_in_world, camera, *pose, *mask);
  ASSERT_TRUE(coverage.ok()) << coverage.status();
  EXPECT_EQ(coverage->object_pixels, 16u * 12u);
  EXPECT_EQ(coverage->covered_pixels, 16u * 12u);
  EXPECT_EQ(coverage->fraction, 1.0);

  // Half the points cover half the pixels; points behind the camera count for nothing.
  std::vector<Eigen::Vector3f> half(samples->points_in_world.begin(),
                                    samples->points_in_world.begin() + samples->points_in_world.size() / 2);
  half.emplace_back(0.0f, 0.0f, -1.0f);
  coverage = ObjectPixelCoverage(half, camera, *pose, *mask);
  ASSERT_TRUE(coverage.ok());
  EXPECT_EQ(coverage->fraction, 0.5);

  coverage = ObjectPixelCoverage({}, camera, *pose, *mask);
  ASSERT_TRUE(coverage.ok());
  EXPECT_EQ(coverage->fraction, 0.0);
  EXPECT_EQ(ObjectPixelCoverage({}, camera, *pose, cv::Mat(5, 5, CV_8UC1)).status().code(),
            StatusCode::kInvalidArgument);
}

TEST_F(SurfaceSamplingTest, OptionsAndMissingDataAreErrors) {
  SurfaceSamplingOptions options;
  options.frame_step = 0;
  EXPECT_EQ(SampleGroundTruthSurface(sequence_, options).status().code(), StatusCode::kInvalidArgument);
  options.frame_step = 1;
  Sequence no_calibration = sequence_;
  no_calibration.has_calibration = false;
  EXPECT_EQ(SampleGroundTruthSurface(no_calibration, options).status().code(), StatusCode::kFailedPrecondition);
  Sequence no_groundtruth = sequence_;
  no_groundtruth.groundtruth.clear();
  EXPECT_EQ(SampleGroundTruthSurface(no_groundtruth, options).status().code(), StatusCode::kFailedPrecondition);
}

}  // namespace
}  // namespace prism
