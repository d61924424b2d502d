#include "core/slam/line_sampler.h"

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define PRISM_LINE_SAMPLER_AVX2 1
#endif

namespace prism {
namespace {

// Points from k_begin on, one at a time; `outside` is the count before k_begin.
inline void SampleRange(const LineSamplerImage& image, const LineSamples& line, int k_begin, int outside,
                        float* samples, int* outside_before) {
  for (int k = k_begin; k < line.num; ++k) {
    const float s = static_cast<float>(k + line.k_offset) * line.step;
    const float u = line.start_x + s * line.e_x, v = line.start_y + s * line.e_y;
    const bool inside = InsideForBilinear(image, u, v);
    samples[k] = inside ? SampleBilinear(image, u, v) : 0.0f;
    outside += inside ? 0 : 1;
    outside_before[k + 1] = outside;
  }
}

#ifdef PRISM_LINE_SAMPLER_AVX2
// No FMA: the target enables AVX2 alone, so every product and sum is rounded as in the portable code.
__attribute__((target("avx2"))) void SampleAlongLineAvx2(const LineSamplerImage& image, const LineSamples& line,
                                                         float* samples, int* outside_before) {
  const __m256 step = _mm256_set1_ps(line.step);
  const __m256 start_x = _mm256_set1_ps(line.start_x), start_y = _mm256_set1_ps(line.start_y);
  const __m256 e_x = _mm256_set1_ps(line.e_x), e_y = _mm256_set1_ps(line.e_y);
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 u_end = _mm256_set1_ps(image.u_end), v_end = _mm256_set1_ps(image.v_end);
  const __m256i stride = _mm256_set1_epi32(static_cast<int>(image.stride));
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const float* r0 = image.data;
  const float* r0_next = image.data + 1;
  const float* r1 = image.data + image.stride;
  const float* r1_next = image.data + image.stride + 1;
  int outside = 0;
  outside_before[0] = 0;
  int k = 0;
  for (; k + 8 <= line.num; k += 8) {
    const __m256 kf = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(k + line.k_offset), lane));
    const __m256 s = _mm256_mul_ps(kf, step);
    const __m256 u = _mm256_add_ps(start_x, _mm256_mul_ps(s, e_x));
    const __m256 v = _mm256_add_ps(start_y, _mm256_mul_ps(s, e_y));
    const __m256 inside =
        _mm256_and_ps(_mm256_and_ps(_mm256_cmp_ps(u, zero, _CMP_GE_OQ), _mm256_cmp_ps(v, zero, _CMP_GE_OQ)),
                      _mm256_and_ps(_mm256_cmp_ps(u, u_end, _CMP_LT_OQ), _mm256_cmp_ps(v, v_end, _CMP_LT_OQ)));
    const int mask = _mm256_movemask_ps(inside);
    // Points outside are sampled at (0, 0) (always readable) and their value zeroed.
    const __m256 us = _mm256_and_ps(u, inside), vs = _mm256_and_ps(v, inside);
    const __m256i x0 = _mm256_cvttps_epi32(us), y0 = _mm256_cvttps_epi32(vs);
    const __m256 fx = _mm256_sub_ps(us, _mm256_cvtepi32_ps(x0));
    const __m256 fy = _mm256_sub_ps(vs, _mm256_cvtepi32_ps(y0));
    const __m256i index = _mm256_add_epi32(_mm256_mullo_epi32(y0, stride), x0);
    const __m256 a = _mm256_i32gather_ps(r0, index, 4), b = _mm256_i32gather_ps(r0_next, index, 4);
    const __m256 c = _mm256_i32gather_ps(r1, index, 4), d = _mm256_i32gather_ps(r1_next, index, 4);
    const __m256 gx = _mm256_sub_ps(one, fx), gy = _mm256_sub_ps(one, fy);
    const __m256 top = _mm256_add_ps(_mm256_mul_ps(gx, a), _mm256_mul_ps(fx, b));
    const __m256 bottom = _mm256_add_ps(_mm256_mul_ps(gx, c), _mm256_mul_ps(fx, d));
    const __m256 value = _mm256_add_ps(_mm256_mul_ps(gy, top), _mm256_mul_ps(fy, bottom));
    _mm256_storeu_ps(samples + k, _mm256_and_ps(value, inside));
    if (mask == 0xff) {
      for (int j = 1; j <= 8; ++j) outside_before[k + j] = outside;
    } else {
      for (int j = 0; j < 8; ++j) {
        outside += (mask >> j) & 1 ? 0 : 1;
        outside_before[k + j + 1] = outside;
      }
    }
  }
  SampleRange(image, line, k, outside, samples, outside_before);
}

bool CpuHasAvx2() {
  static const bool has = __builtin_cpu_supports("avx2");
  return has;
}
#endif

}  // namespace

void SampleAlongLinePortable(const LineSamplerImage& image, const LineSamples& line, float* samples,
                             int* outside_before) {
  outside_before[0] = 0;
  SampleRange(image, line, 0, 0, samples, outside_before);
}

bool LineSamplerUsesAvx2() {
#ifdef PRISM_LINE_SAMPLER_AVX2
  return CpuHasAvx2();
#else
  return false;
#endif
}

void SampleAlongLine(const LineSamplerImage& image, const LineSamples& line, float* samples, int* outside_before) {
#ifdef PRISM_LINE_SAMPLER_AVX2
  if (CpuHasAvx2()) return SampleAlongLineAvx2(image, line, samples, outside_before);
#endif
  SampleAlongLinePortable(image, line, samples, outside_before);
}

}  // namespace prism
