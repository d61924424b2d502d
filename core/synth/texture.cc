#include "core/synth/texture.h"

#include <algorithm>
#include <cmath>

namespace prism::synth {
namespace {

inline uint32_t Hash(int32_t x, int32_t y, int32_t z, uint32_t seed) {
  uint32_t h = seed * 0x9E3779B1u;
  h ^= static_cast<uint32_t>(x) * 0x85EBCA77u;
  h = (h << 13) | (h >> 19);
  h ^= static_cast<uint32_t>(y) * 0xC2B2AE3Du;
  h = (h << 17) | (h >> 15);
  h ^= static_cast<uint32_t>(z) * 0x27D4EB2Fu;
  h ^= h >> 15;
  h *= 0x2C1B3C6Du;
  h ^= h >> 12;
  h *= 0x297A2D39u;
  h ^= h >> 15;
  return h;
}

inline double Unit(uint32_t h) { return (h & 0xFFFFFF) / static_cast<double>(0xFFFFFF); }
inline double Smooth(double t) { return t * t * (3 - 2 * t); }

}  // namespace

double ValueNoise(const Eigen::Vector3d& p, uint32_t seed) {
  const double fx = std::floor(p.x()), fy = std::floor(p.y()), fz = std::floor(p.z());
  const int32_t x = static_cast<int32_t>(fx), y = static_cast<int32_t>(fy), z = static_cast<int32_t>(fz);
  const double tx = Smooth(p.x() - fx), ty = Smooth(p.y() - fy), tz = Smooth(p.z() - fz);
  double v[2][2][2];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) v[i][j][k] = Unit(Hash(x + i, y + j, z + k, seed));
  auto lerp = [](double a, double b, double t) { return a + (b - a) * t; };
  const double x00 = lerp(v[0][0][0], v[1][0][0], tx), x10 = lerp(v[0][1][0], v[1][1][0], tx);
  const double x01 = lerp(v[0][0][1], v[1][0][1], tx), x11 = lerp(v[0][1][1], v[1][1][1], tx);
  return lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz);
}

double FractalNoise(const Eigen::Vector3d& p, uint32_t seed, int octaves) {
  double sum = 0, norm = 0, amp = 1, freq = 1;
  for (int o = 0; o < octaves; ++o) {
    sum += amp * ValueNoise(p * freq, seed + 7919u * o);
    norm += amp;
    amp *= 0.5;
    freq *= 2.03;
  }
  return sum / norm;
}

uint32_t VoronoiCell(const Eigen::Vector3d& p, uint32_t seed) {
  const int32_t x = static_cast<int32_t>(std::floor(p.x())), y = static_cast<int32_t>(std::floor(p.y())),
                z = static_cast<int32_t>(std::floor(p.z()));
  double best = 1e300;
  uint32_t best_hash = 0;
  for (int i = -1; i <= 1; ++i)
    for (int j = -1; j <= 1; ++j)
      for (int k = -1; k <= 1; ++k) {
        const uint32_t h = Hash(x + i, y + j, z + k, seed);
        const Eigen::Vector3d c(x + i + Unit(h), y + j + Unit(h * 0x9E3779B1u + 1), z + k + Unit(h * 0x85EBCA77u + 2));
        const double d = (c - p).squaredNorm();
        if (d < best) {
          best = d;
          best_hash = h;
        }
      }
  return best_hash;
}

double ImageTexture::Sample(double x_m, double y_m) const {
  if (width <= 0 || height <= 0) return 1.0;
  // Texel (i, j) covers [i, i + 1) x [j, j + 1) texel units from the image's top-left corner.
  const double u = std::clamp(x_m / texel_m + 0.5 * width - 0.5, 0.0, width - 1.0);
  const double v = std::clamp(y_m / texel_m + 0.5 * height - 0.5, 0.0, height - 1.0);
  const int u0 = std::min(static_cast<int>(u), width - 2 < 0 ? 0 : width - 2);
  const int v0 = std::min(static_cast<int>(v), height - 2 < 0 ? 0 : height - 2);
  const int u1 = std::min(u0 + 1, width - 1), v1 = std::min(v0 + 1, height - 1);
  const double fu = u - u0, fv = v - v0;
  auto at = [&](int x, int y) { return static_cast<double>(values[static_cast<size_t>(y) * width + x]); };
  return (1 - fv) * ((1 - fu) * at(u0, v0) + fu * at(u1, v0)) + fv * ((1 - fu) * at(u0, v1) + fu * at(u1, v1));
}

Eigen::Vector3d AlbedoOptions::Evaluate(const Eigen::Vector3d& point_in_object) const {
  switch (kind) {
    case AlbedoKind::kUniform:
      return base;
    case AlbedoKind::kTextured: {
      const double n = FractalNoise(point_in_object / feature_size_m, seed, octaves);
      return base * (1.0 - contrast + contrast * n);
    }
    case AlbedoKind::kMultiColor: {
      if (palette.empty()) return base;
      const uint32_t cell = VoronoiCell(point_in_object / feature_size_m, seed);
      return palette[(cell >> 8) % palette.size()];
    }
    case AlbedoKind::kImage:
      if (!image) return base;
      return base * image->Sample(point_in_object.x(), point_in_object.y());
  }
  return base;
}

}  // namespace prism::synth
