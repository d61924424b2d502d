// Bilinear samples of a float image at evenly spaced points on a line: the inner loop of the depth
// filter's epipolar search (core/slam/depth_filter.h). An AVX2 version (8 points at a time, gathers) is
// used when the CPU has it; it gives the same IEEE values as the portable one, sample for sample.
#pragma once

#include <cstddef>

namespace prism {

// The image: CV_32F data with `stride` floats per row; a point (u, v) is inside when
// 0 <= u < u_end and 0 <= v < v_end (u_end = cols - 1, v_end = rows - 1: all four taps exist).
struct LineSamplerImage {
  const float* data = nullptr;
  size_t stride = 0;
  float u_end = 0, v_end = 0;
};

// Whether all four taps of a bilinear sample at (u, v) exist.
inline bool InsideForBilinear(const LineSamplerImage& image, float u, float v) {
  return u >= 0 && v >= 0 && u < image.u_end && v < image.v_end;
}

// The bilinear sample at (u, v) (InsideForBilinear must hold): the expression, in its order, that
// every sample of this file evaluates.
inline float SampleBilinear(const LineSamplerImage& image, float u, float v) {
  const int x0 = static_cast<int>(u), y0 = static_cast<int>(v);
  const float fx = u - static_cast<float>(x0), fy = v - static_cast<float>(y0);
  const float* r0 = image.data + static_cast<size_t>(y0) * image.stride;
  const float* r1 = r0 + image.stride;
  return (1 - fy) * ((1 - fx) * r0[x0] + fx * r0[x0 + 1]) + fy * ((1 - fx) * r1[x0] + fx * r1[x0 + 1]);
}

// For k = 0 .. num - 1 the point q_k = start + (float(k + k_offset) * step) * e, computed as
// (start_x + s e_x, start_y + s e_y) with s = float(k + k_offset) * step. samples[k] is the bilinear
// sample at q_k, 0 outside; outside_before[k] counts the points before k that are outside
// (outside_before has num + 1 entries, outside_before[0] = 0).
struct LineSamples {
  float start_x = 0, start_y = 0, e_x = 0, e_y = 0, step = 0;
  int k_offset = 0;
  int num = 0;
};

// The fastest version this CPU runs.
void SampleAlongLine(const LineSamplerImage& image, const LineSamples& line, float* samples, int* outside_before);
// The portable version (the reference for the vectorised one).
void SampleAlongLinePortable(const LineSamplerImage& image, const LineSamples& line, float* samples,
                             int* outside_before);
// Whether SampleAlongLine uses the AVX2 version here.
bool LineSamplerUsesAvx2();

}  // namespace prism
