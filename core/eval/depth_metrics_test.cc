#include "core/eval/depth_metrics.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace prism {
namespace {

class DepthMetricsTest : public ::testing::Test {
 protected:
  void SetUp() override { rng_.seed(5); }

  cv::Mat RandomDepth(int width, int height) {
    std::uniform_real_distribution<float> depth(0.5f, 3.0f);
    cv::Mat d(height, width, CV_32FC1);
    for (int y = 0; y < height; ++y)
      for (int x = 0; x < width; ++x) d.at<float>(y, x) = depth(rng_);
    return d;
  }

  std::mt19937 rng_;
};

TEST_F(DepthMetricsTest, ScaledEstimateIsAlignedExactly) {
  const cv::Mat gt = RandomDepth(32, 24);
  const cv::Mat estimate = gt * 0.25;  // monocular estimate at a quarter of the true scale
  constexpr double kFloatTolerance = 1e-6;
  for (DepthScaleAlignment alignment : {DepthScaleAlignment::kMedianRatio, DepthScaleAlignment::kLeastSquares}) {
    DepthEvalOptions options;
    options.scale_alignment = alignment;
    const auto stats = ComputeDepthError(estimate, gt, cv::Mat(), options);
    ASSERT_TRUE(stats.ok()) << stats.status();
    EXPECT_NEAR(stats->scale, 4.0, kFloatTolerance);
    EXPECT_LT(stats->rmse_m, kFloatTolerance);
    EXPECT_LT(stats->median_rel_error, kFloatTolerance);
    EXPECT_EQ(stats->coverage, 1.0);
    EXPECT_EQ(stats->pixels, 32u * 24u);
  }
  DepthEvalOptions none;
  none.scale_alignment = DepthScaleAlignment::kNone;
  const auto stats = ComputeDepthError(estimate, gt, cv::Mat(), none);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->scale, 1.0);
  EXPECT_NEAR(stats->median_rel_error, 0.75, kFloatTolerance);
}

TEST_F(DepthMetricsTest, KnownOffsetAndCoverage) {
  const cv::Mat gt = cv::Mat(10, 10, CV_32FC1, cv::Scalar(2.0));
  cv::Mat estimate = gt + 0.01;                // 1 cm too far everywhere
  estimate(cv::Rect(0, 0, 10, 2)).setTo(0.0);  // 20 pixels without estimate
  cv::Mat gt_with_hole = gt.clone();
  gt_with_hole.at<float>(9, 9) = 0.0f;  // one pixel without ground truth
  DepthEvalOptions options;
  options.scale_alignment = DepthScaleAlignment::kNone;
  const auto stats = ComputeDepthError(estimate, gt_with_hole, cv::Mat(), options);
  ASSERT_TRUE(stats.ok()) << stats.status();
  constexpr double kFloatTolerance = 1e-6;
  EXPECT_NEAR(stats->rmse_m, 0.01, kFloatTolerance);
  EXPECT_NEAR(stats->mean_abs_m, 0.01, kFloatTolerance);
  EXPECT_NEAR(stats->median_rel_error, 0.005, kFloatTolerance);
  EXPECT_EQ(stats->gt_pixels, 99u);
  EXPECT_EQ(stats->pixels, 79u);
  EXPECT_DOUBLE_EQ(stats->coverage, 79.0 / 99.0);
}

TEST_F(DepthMetricsTest, MedianScaleIgnoresOutliers) {
  const cv::Mat gt = RandomDepth(20, 20);
  cv::Mat estimate = gt * 0.5;
  estimate(cv::Rect(0, 0, 20, 5)) *= 10.0;  // a quarter of the pixels wildly wrong
  DepthEvalOptions options;                 // median
  const auto stats = ComputeDepthError(estimate, gt, cv::Mat(), options);
  ASSERT_TRUE(stats.ok());
  EXPECT_NEAR(stats->scale, 2.0, 1e-6);
  EXPECT_NEAR(stats->median_rel_error, 0.0, 1e-6);
}

TEST_F(DepthMetricsTest, MaskAndAccumulator) {
  const cv::Mat gt = RandomDepth(10, 10);
  cv::Mat mask = cv::Mat::zeros(10, 10, CV_8UC1);
  mask(cv::Rect(0, 0, 5, 10)).setTo(255);
  DepthErrorAccumulator acc;
  ASSERT_TRUE(acc.Add(gt * 2.0, gt, mask).ok());
  ASSERT_TRUE(acc.Add(gt * 2.0, gt, mask).ok());
  const auto stats = acc.Summarize(DepthEvalOptions());
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->pixels, 100u);
  EXPECT_NEAR(stats->scale, 0.5, 1e-7);
}

TEST_F(DepthMetricsTest, BadInputIsAnError) {
  const cv::Mat gt = RandomDepth(8, 6);
  EXPECT_EQ(ComputeDepthError(RandomDepth(6, 8), gt, cv::Mat(), DepthEvalOptions()).status().code(),
            StatusCode::kInvalidArgument);
  cv::Mat as_u16;
  gt.convertTo(as_u16, CV_16UC1);
  EXPECT_EQ(ComputeDepthError(as_u16, gt, cv::Mat(), DepthEvalOptions()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ComputeDepthError(cv::Mat::zeros(6, 8, CV_32FC1), gt, cv::Mat(), DepthEvalOptions()).status().code(),
            StatusCode::kFailedPrecondition);
  EXPECT_FALSE(ParseDepthScaleAlignment("mean").ok());
  EXPECT_EQ(*ParseDepthScaleAlignment("least_squares"), DepthScaleAlignment::kLeastSquares);
}

}  // namespace
}  // namespace prism
