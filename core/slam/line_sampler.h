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
