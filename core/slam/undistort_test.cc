#include "core/slam/undistort.h"

#include <cmath>
#include <iostream>

#include <gtest/gtest.h>

namespace prism {
namespace {

PinholeCamera Camera(double k1, double k2) {
  PinholeCamera c = PinholeCamera::FromFov(320, 240, 60.0);
  c.distortion = {k1, k2, 0.001, -0.0005, 0.0};
  return c;
}

// A smooth pattern fixed to the viewing ray (what the scene looks like in every direction).
float Pattern(const Eigen::Vector3d& ray) {
  const double x = ray.x() / ray.z(), y = ray.y() / ray.z();
  return static_cast<float>(100.0 + 60.0 * std::sin(9.0 * x) * std::cos(7.0 * y) + 30.0 * x);
}

// The image a camera sees of the pattern.
cv::Mat Render(const PinholeCamera& c) {
  cv::Mat img(c.height, c.width, CV_32F);
  for (int y = 0; y < c.height; ++y)
    for (int x = 0; x < c.width; ++x) img.at<float>(y, x) = Pattern(c.Unproject(Eigen::Vector2d(x, y)));
  return img;
}

// Barrel (k1 < 0) and pincushion (k1 > 0) lenses: the undistorted image is what the undistorted pinhole
// camera sees, at every pixel (none falls outside the lens's image: no replicated border), up to the
// interpolation of a smooth pattern.
TEST(ImageUndistorterTest, TheUndistortedImageIsWhatThePinholeCameraSees) {
  for (const auto& [k1, k2] : {std::pair{-0.25, 0.08}, std::pair{0.15, 0.02}}) {
    const PinholeCamera distorted = Camera(k1, k2);
    StatusOr<ImageUndistorter> u = ImageUndistorter::Create(distorted);
    ASSERT_TRUE(u.ok()) << u.status();
    EXPECT_FALSE(u->identity());
    const PinholeCamera& pin = u->camera();
    EXPECT_FALSE(pin.HasDistortion());
    EXPECT_EQ(pin.width, distorted.width);
    EXPECT_EQ(pin.height, distorted.height);
    EXPECT_NEAR(pin.cx, 0.5 * (pin.width - 1), 1e-9);
    EXPECT_NEAR(pin.cy, 0.5 * (pin.height - 1), 1e-9);
    // Barrel distortion squeezes the edges: the pinhole camera that keeps every pixel valid has a
    // shorter focal length (wider view); pincushion the reverse.
    if (k1 < 0) EXPECT_LT(pin.fx, distorted.fx);
    else EXPECT_GT(pin.fx, distorted.fx);

    StatusOr<cv::Mat> out = u->Undistort(Render(distorted));
    ASSERT_TRUE(out.ok()) << out.status();
    const cv::Mat truth = Render(pin);
    double sum = 0, worst = 0;
    for (int y = 0; y < pin.height; ++y)
      for (int x = 0; x < pin.width; ++x) {
        const double e = std::abs(out->at<float>(y, x) - truth.at<float>(y, x));
        sum += e;
        worst = std::max(worst, e);
      }
    const double mean = sum / (pin.width * pin.height);
    std::cout << "k1 " << k1 << ": mean |error| " << mean << ", max " << worst << " grey levels\n";
    constexpr double kMeanTolerance = 0.05, kMaxTolerance = 0.3;  // grey levels, of a 180-level pattern
    EXPECT_LT(mean, kMeanTolerance);
    EXPECT_LT(worst, kMaxTolerance);
    // Without the remap the same image is far off (the test can tell).
    double ignored = 0;
    const cv::Mat raw = Render(distorted);
    for (int y = 0; y < pin.height; ++y)
      for (int x = 0; x < pin.width; ++x) ignored += std::abs(raw.at<float>(y, x) - truth.at<float>(y, x));
    EXPECT_GT(ignored / (pin.width * pin.height), 20 * kMeanTolerance);
  }
}

TEST(ImageUndistorterTest, NearestKeepsValuesAndIdentityKeepsTheImage) {
  const PinholeCamera distorted = Camera(-0.2, 0.05);
  StatusOr<ImageUndistorter> u = ImageUndistorter::Create(distorted);
  ASSERT_TRUE(u.ok());
  // Depth-like labels: 1, 2, 3 in three vertical bands; nearest-neighbour output holds only those.
  cv::Mat labels(distorted.height, distorted.width, CV_16U);
  for (int y = 0; y < labels.rows; ++y)
    for (int x = 0; x < labels.cols; ++x) labels.at<uint16_t>(y, x) = static_cast<uint16_t>(1 + 3 * x / labels.cols);
  StatusOr<cv::Mat> out = u->UndistortNearest(labels);
  ASSERT_TRUE(out.ok());
  int counts[4] = {0, 0, 0, 0};
  for (int y = 0; y < out->rows; ++y)
    for (int x = 0; x < out->cols; ++x) {
      const uint16_t v = out->at<uint16_t>(y, x);
      ASSERT_TRUE(v >= 1 && v <= 3) << v;
      ++counts[v];
    }
  EXPECT_GT(counts[1], 0);
  EXPECT_GT(counts[2], 0);
  EXPECT_GT(counts[3], 0);

  PinholeCamera plain = distorted;
  plain.distortion = {0, 0, 0, 0, 0};
  StatusOr<ImageUndistorter> id = ImageUndistorter::Create(plain);
  ASSERT_TRUE(id.ok());
  EXPECT_TRUE(id->identity());
  EXPECT_EQ(id->camera().fx, plain.fx);
  cv::Mat rgb(plain.height, plain.width, CV_8UC3, cv::Scalar(1, 2, 3));
  StatusOr<cv::Mat> same = id->Undistort(rgb);
  ASSERT_TRUE(same.ok());
  EXPECT_EQ(same->data, rgb.data);
}

// A lens that bends the image by a fraction of a pixel (prism-calibrate's result for a pinhole lens:
// k1 -0.003, k2 0.009) must not smooth it: the remap reads between pixels nearly everywhere, and an
// interpolation that averages neighbours there (bilinear, at half a pixel the mean of two) takes out
// the sensor noise and fine texture unevenly across the image, which the SLAM and the photometric
// stereo then see.
TEST(ImageUndistorterTest, ASmallDistortionKeepsTheImageSharp) {
  PinholeCamera lens = PinholeCamera::FromFov(512, 512, 50.0);
  lens.distortion = {-0.0026, 0.0091, 0.0001, -0.0004, 0.0};
  StatusOr<ImageUndistorter> u = ImageUndistorter::Create(lens);
  ASSERT_TRUE(u.ok()) << u.status();
  cv::Mat noise(lens.height, lens.width, CV_8UC3);
  cv::RNG rng(7);
  rng.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(128), cv::Scalar::all(20));
  StatusOr<cv::Mat> out = u->Undistort(noise);
  ASSERT_TRUE(out.ok()) << out.status();
  const cv::Rect inner(8, 8, lens.width - 16, lens.height - 16);
  cv::Scalar mean_in, std_in, mean_out, std_out;
  cv::meanStdDev(noise(inner), mean_in, std_in);
  cv::meanStdDev((*out)(inner), mean_out, std_out);
  const double kept = std_out[0] / std_in[0];
  std::cout << "noise standard deviation kept by the remap: " << kept << "\n";
  constexpr double kMinNoiseKept = 0.85;  // bicubic keeps 0.90 of it, bilinear 0.72
  EXPECT_GT(kept, kMinNoiseKept);
  EXPECT_NEAR(mean_out[0], mean_in[0], 1.0);
}

TEST(ImageUndistorterTest, BadCamerasAndWrongSizesAreRefused) {
  PinholeCamera bad = Camera(-0.2, 0.0);
  bad.fx = -1;
  EXPECT_EQ(ImageUndistorter::Create(bad).status().code(), StatusCode::kInvalidArgument);
  StatusOr<ImageUndistorter> u = ImageUndistorter::Create(Camera(-0.2, 0.0));
  ASSERT_TRUE(u.ok());
  const StatusOr<cv::Mat> wrong = u->Undistort(cv::Mat(10, 10, CV_8UC3, cv::Scalar(0)));
  EXPECT_EQ(wrong.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(wrong.status().message().find("10x10"), std::string::npos) << wrong.status();
}

}  // namespace
}  // namespace prism
