#include "core/slam/line_sampler.h"

#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace prism {
namespace {

// A 97 x 61 image (odd sizes, a row stride wider than the row) of noise-like values.
struct TestImage {
  static constexpr int kCols = 97, kRows = 61, kStride = 104;
  std::vector<float> pixels = std::vector<float>(static_cast<size_t>(kStride) * kRows, -7.0f);
  TestImage() {
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> value(0.0f, 255.0f);
    for (int y = 0; y < kRows; ++y)
      for (int x = 0; x < kCols; ++x) pixels[static_cast<size_t>(y) * kStride + x] = value(rng);
  }
  LineSamplerImage View() const {
    LineSamplerImage v;
    v.data = pixels.data();
    v.stride = kStride;
    v.u_end = kCols - 1;
    v.v_end = kRows - 1;
    return v;
  }
};

uint32_t Bits(float f) {
  uint32_t b;
  std::memcpy(&b, &f, sizeof(b));
  return b;
}

TEST(LineSampler, MatchesThePortableVersionBitForBit) {
  std::printf("SampleAlongLine uses AVX2 on this CPU: %s\n", LineSamplerUsesAvx2() ? "yes" : "no");
  const TestImage image;
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> pos(-20.0f, 120.0f), angle(0.0f, 6.2831853f), step(0.25f, 2.5f);
  std::uniform_int_distribution<int> num(0, 90);
  int lines_with_outside = 0, lines_inside = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    LineSamples line;
    line.start_x = pos(rng);
    line.start_y = pos(rng) * 0.6f;
    const float a = angle(rng);
    line.e_x = std::cos(a);
    line.e_y = std::sin(a);
    line.step = step(rng);
    line.k_offset = -3;
    line.num = num(rng);
    std::vector<float> fast(static_cast<size_t>(line.num) + 1, 1.0f), reference(fast.size(), 2.0f);
    std::vector<int> fast_out(static_cast<size_t>(line.num) + 1, -1), reference_out(fast_out.size(), -2);
    SampleAlongLine(image.View(), line, fast.data(), fast_out.data());
    SampleAlongLinePortable(image.View(), line, reference.data(), reference_out.data());
    for (int k = 0; k < line.num; ++k)
      ASSERT_EQ(Bits(fast[k]), Bits(reference[k])) << "trial " << trial << " sample " << k;
    for (int k = 0; k <= line.num; ++k) ASSERT_EQ(fast_out[k], reference_out[k]) << "trial " << trial << " count " << k;
    EXPECT_EQ(fast[static_cast<size_t>(line.num)], 1.0f) << "wrote past the end";
    (line.num > 0 && reference_out[line.num] > 0 ? lines_with_outside : lines_inside)++;
  }
  // Both kinds of line were exercised.
  EXPECT_GT(lines_with_outside, 300);
  EXPECT_GT(lines_inside, 300);
}

TEST(LineSampler, SamplesAPlaneExactlyAndZeroOutside) {
  // Bilinear interpolation reproduces a plane; points outside give 0 and are counted.
  constexpr int kCols = 40, kRows = 30;
  std::vector<float> plane(static_cast<size_t>(kCols) * kRows);
  for (int y = 0; y < kRows; ++y)
    for (int x = 0; x < kCols; ++x) plane[static_cast<size_t>(y) * kCols + x] = 2.0f * x + 3.0f * y + 1.0f;
  LineSamplerImage image;
  image.data = plane.data();
  image.stride = kCols;
  image.u_end = kCols - 1;
  image.v_end = kRows - 1;
  LineSamples line;  // from (-2.5, 10.25) along +x in steps of 0.75: the first 4 points are outside
  line.start_x = -2.5f;
  line.start_y = 10.25f;
  line.e_x = 1.0f;
  line.e_y = 0.0f;
  line.step = 0.75f;
  line.k_offset = 0;
  line.num = 60;  // up to u = 41.75: the points from u = 39 on are outside too
  std::vector<float> samples(60);
  std::vector<int> outside(61);
  SampleAlongLine(image, line, samples.data(), outside.data());
  int expected_outside = 0;
  for (int k = 0; k < line.num; ++k) {
    const float u = -2.5f + 0.75f * k;
    const bool inside = u >= 0 && u < kCols - 1;
    if (inside) {
      EXPECT_NEAR(samples[k], 2.0f * u + 3.0f * 10.25f + 1.0f, 1e-4f) << k;
    } else {
      EXPECT_EQ(samples[k], 0.0f) << k;
    }
    EXPECT_EQ(outside[k], expected_outside) << k;
    expected_outside += inside ? 0 : 1;
  }
  EXPECT_EQ(outside[60], expected_outside);
  EXPECT_EQ(expected_outside, 4 + 4);  // u = -2.5 .. -0.25 and u = 39.5 .. 41.75
}

}  // namespace
}  // namespace prism
