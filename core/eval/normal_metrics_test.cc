#include "core/eval/normal_metrics.h"

#include <cmath>
#include <random>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

namespace prism {
namespace {

// Float storage of unit vectors limits angles to ~1e-5 degrees.
constexpr double kFloatAngleToleranceDeg = 1e-4;

cv::Vec3f ToVec(const Eigen::Vector3d& v) {
  return cv::Vec3f(static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z()));
}
Eigen::Vector3d ToEigen(const cv::Vec3f& v) { return Eigen::Vector3d(v[0], v[1], v[2]); }

class NormalMetricsTest : public ::testing::Test {
 protected:
  void SetUp() override { rng_.seed(3); }

  // Random unit normals facing the camera (negative z); a fraction of pixels is invalid (zero).
  cv::Mat RandomNormals(int width, int height, double invalid_fraction) {
    cv::Mat n(height, width, CV_32FC3);
    std::normal_distribution<double> normal(0.0, 1.0);
    std::uniform_real_distribution<double> uniform(0.0, 1.0);
    for (int y = 0; y < height; ++y)
      for (int x = 0; x < width; ++x) {
        if (uniform(rng_) < invalid_fraction) {
          n.at<cv::Vec3f>(y, x) = cv::Vec3f(0, 0, 0);
          continue;
        }
        n.at<cv::Vec3f>(y, x) =
            ToVec(Eigen::Vector3d(normal(rng_), normal(rng_), -3.0 - std::abs(normal(rng_))).normalized());
      }
    return n;
  }

  // Every valid normal turned by angle_deg about a random axis perpendicular to it.
  cv::Mat Rotated(const cv::Mat& normals, double angle_deg) {
    std::normal_distribution<double> normal(0.0, 1.0);
    cv::Mat out = normals.clone();
    for (int y = 0; y < out.rows; ++y)
      for (int x = 0; x < out.cols; ++x) {
        const Eigen::Vector3d n = ToEigen(normals.at<cv::Vec3f>(y, x));
        if (n.isZero()) continue;
        const Eigen::Vector3d axis = n.cross(Eigen::Vector3d(normal(rng_), normal(rng_), normal(rng_))).normalized();
        out.at<cv::Vec3f>(y, x) = ToVec(Eigen::AngleAxisd(angle_deg * M_PI / 180.0, axis) * n);
      }
    return out;
  }

  std::mt19937 rng_;
};

TEST_F(NormalMetricsTest, IdenticalMapsGiveZeroError) {
  const cv::Mat n = RandomNormals(40, 30, 0.2);
  const auto stats = ComputeNormalError(n, n);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_GT(stats->count, 0u);
  EXPECT_LT(stats->count, 40u * 30u);  // invalid pixels are skipped
  EXPECT_EQ(stats->mean_deg, 0.0);
  EXPECT_EQ(stats->median_deg, 0.0);
  EXPECT_EQ(stats->rmse_deg, 0.0);
  EXPECT_EQ(stats->pct_under_5, 100.0);
}

TEST_F(NormalMetricsTest, KnownRotationIsMeasured) {
  const cv::Mat gt = RandomNormals(50, 40, 0.0);
  const auto stats = ComputeNormalError(Rotated(gt, 7.0), gt);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->count, 50u * 40u);
  EXPECT_NEAR(stats->mean_deg, 7.0, kFloatAngleToleranceDeg);
  EXPECT_NEAR(stats->median_deg, 7.0, kFloatAngleToleranceDeg);
  EXPECT_NEAR(stats->rmse_deg, 7.0, kFloatAngleToleranceDeg);
  EXPECT_EQ(stats->pct_under_5, 0.0);
  EXPECT_EQ(stats->pct_under_10, 100.0);
  EXPECT_EQ(stats->pct_under_20, 100.0);
}

TEST_F(NormalMetricsTest, SmallAnglesAndUnnormalisedVectorsAreAccurate) {
  // acos(a.b) would resolve 0.01 degrees only to a few percent in float; atan2 in double does not care.
  const cv::Mat gt = RandomNormals(20, 20, 0.0);
  cv::Mat estimate = Rotated(gt, 0.01);
  estimate *= 3.0;  // length does not matter
  const auto stats = ComputeNormalError(estimate, gt);
  ASSERT_TRUE(stats.ok());
  EXPECT_NEAR(stats->mean_deg, 0.01, kFloatAngleToleranceDeg);
  EXPECT_NEAR(AngleBetweenDeg(cv::Vec3f(1, 0, 0), cv::Vec3f(-1, 0, 0)), 180.0, 1e-12);
  EXPECT_NEAR(AngleBetweenDeg(cv::Vec3f(0, 0, 2), cv::Vec3f(0, 5, 0)), 90.0, 1e-12);
}

TEST_F(NormalMetricsTest, MixtureGivesKnownMedianAndPercentages) {
  const cv::Mat gt = RandomNormals(20, 10, 0.0);
  cv::Mat estimate = Rotated(gt, 2.0);
  const cv::Mat far = Rotated(gt, 30.0);
  far(cv::Rect(0, 0, 10, 10)).copyTo(estimate(cv::Rect(0, 0, 10, 10)));  // left half 30 deg, right half 2 deg
  const auto stats = ComputeNormalError(estimate, gt);
  ASSERT_TRUE(stats.ok());
  EXPECT_NEAR(stats->median_deg, 16.0, kFloatAngleToleranceDeg);  // even count: mean of 2 and 30
  EXPECT_NEAR(stats->mean_deg, 16.0, kFloatAngleToleranceDeg);
  EXPECT_NEAR(stats->rmse_deg, std::sqrt((4.0 + 900.0) / 2.0), kFloatAngleToleranceDeg);
  EXPECT_EQ(stats->pct_under_5, 50.0);
  EXPECT_EQ(stats->pct_under_20, 50.0);
}

TEST_F(NormalMetricsTest, MaskSelectsPixelsAndAccumulatorAggregatesFrames) {
  const cv::Mat gt = RandomNormals(20, 10, 0.0);
  const cv::Mat estimate = Rotated(gt, 4.0);
  cv::Mat mask = cv::Mat::zeros(gt.size(), CV_8UC1);
  mask(cv::Rect(0, 0, 5, 10)).setTo(255);
  NormalErrorAccumulator acc;
  ASSERT_TRUE(acc.Add(estimate, gt, mask).ok());
  EXPECT_EQ(acc.count(), 50u);
  ASSERT_TRUE(acc.Add(gt, gt, mask).ok());  // a second frame with zero error
  const AngularErrorStats stats = acc.Summarize();
  EXPECT_EQ(stats.count, 100u);
  EXPECT_NEAR(stats.mean_deg, 2.0, kFloatAngleToleranceDeg);
  EXPECT_EQ(stats.pct_under_5, 100.0);
}

TEST_F(NormalMetricsTest, BadInputIsAnError) {
  const cv::Mat n = RandomNormals(8, 6, 0.0);
  EXPECT_EQ(ComputeNormalError(n, RandomNormals(6, 8, 0.0)).status().code(), StatusCode::kInvalidArgument);
  cv::Mat as_double;
  n.convertTo(as_double, CV_64FC3);
  EXPECT_EQ(ComputeNormalError(as_double, n).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ComputeNormalError(n, n, cv::Mat::ones(6, 8, CV_16UC1)).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ComputeNormalError(n, n, cv::Mat::ones(5, 8, CV_8UC1)).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(NormalErrorAccumulator().Summarize().count, 0u);
}

}  // namespace
}  // namespace prism
