#include <algorithm>
#include <cmath>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "core/fusion/fusion_internal.h"

namespace prism {
namespace internal {

// Normals of the surface Z r(u) into *out (CV_32FC3): central differences along the tangent rows that
// were used (one-sided where a neighbour is cut off), facing the camera; 0 where a direction has no
// neighbour or the depth is not positive.
void SurfaceNormals(const std::vector<float>& depth, const internal::FusionStencil& s, const Rays& rays,
                    const RowBlocks& blocks, cv::Mat* out) {
  const int w = s.width, h = s.height;
  out->create(h, w, CV_32FC3);
  auto point = [&](size_t i) { return cv::Vec3f(rays.x[i] * depth[i], rays.y[i] * depth[i], depth[i]); };
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      cv::Vec3f* o = out->ptr<cv::Vec3f>(y);
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        o[x] = cv::Vec3f(0, 0, 0);
        if (!s.unknown[i] || !(depth[i] > 0)) continue;
        const bool r = x + 1 < w && s.right[i] != 0.f;
        const bool l = x > 0 && s.right[i - 1] != 0.f;
        const bool d = y + 1 < h && s.down[i] != 0.f;
        const bool u = y > 0 && s.down[i - w] != 0.f;
        if (!(r || l) || !(d || u)) continue;
        const cv::Vec3f tx = point(r ? i + 1 : i) - point(l ? i - 1 : i);
        const cv::Vec3f ty = point(d ? i + w : i) - point(u ? i - w : i);
        cv::Vec3f nm = tx.cross(ty);
        const float len = std::sqrt(nm.dot(nm));
        if (!(len > 0)) continue;
        nm /= len;
        if (nm[0] * rays.x[i] + nm[1] * rays.y[i] + nm[2] > 0) nm = -nm;
        o[x] = nm;
      }
    }
  });
}

namespace {

// Gaussian low-pass of a normal map's directions (not normalised). Large scales are filtered on a
// downsampled image.
cv::Mat GaussianLowPass(const cv::Mat& normals, double sigma_px) {
  const int factor = std::max(1, static_cast<int>(std::floor(sigma_px / 2.0)));
  cv::Mat small = normals;
  if (factor > 1)
    cv::resize(normals, small, cv::Size((normals.cols + factor - 1) / factor, (normals.rows + factor - 1) / factor), 0,
               0, cv::INTER_AREA);
  const double s = sigma_px / factor;
  const int k = 2 * static_cast<int>(std::ceil(3 * s)) + 1;
  cv::Mat blurred;
  cv::GaussianBlur(small, blurred, cv::Size(k, k), s, s, cv::BORDER_REPLICATE);
  if (factor == 1) return blurred;
  cv::Mat out;
  cv::resize(blurred, out, normals.size(), 0, 0, cv::INTER_LINEAR);
  return out;
}

// Edge-aware low-pass of two CV_32FC3 maps in place: the recursive filter of the domain transform
// (Gastal & Oliveira 2011), iterations of a horizontal and a vertical first-order recursive
// (exponential) filter of scale sigma_px that does not propagate across pairs without a tangent row
// (depth discontinuities, creases, holes). `factors` is scratch.
void EdgeAwareLowPass(const internal::FusionStencil& links, double sigma_px, const RowBlocks& blocks,
                      std::vector<float>* factors, cv::Mat* a, cv::Mat* b) {
  const int w = links.width, h = links.height;
  const size_t n = static_cast<size_t>(w) * h;
  // Two iterations: the third of the domain transform changed the corrected normals by < 0.05 deg.
  constexpr int kIterations = 2;
  std::vector<float>& fr = *factors;  // feedback to the right neighbour, then 3 per pixel downwards
  fr.resize(4 * n);
  float* fd = fr.data() + n;
  for (int k = 0; k < kIterations; ++k) {
    const double sigma_k =
        sigma_px * std::sqrt(3.0) * std::pow(2.0, kIterations - 1 - k) / std::sqrt(std::pow(4.0, kIterations) - 1);
    const float f = static_cast<float>(std::exp(-std::sqrt(2.0) / sigma_k));
    blocks.Run([&](int y0, int y1, int) {
      for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
        fr[i] = links.right[i] != 0.f ? f : 0.f;
        const float d = links.down[i] != 0.f ? f : 0.f;
        fd[3 * i] = fd[3 * i + 1] = fd[3 * i + 2] = d;
      }
      for (cv::Mat* m : {a, b})
        for (int y = y0; y < y1; ++y) {
          cv::Vec3f* v = m->ptr<cv::Vec3f>(y);
          const float* rt = fr.data() + static_cast<size_t>(y) * w;
          for (int x = 1; x < w; ++x) v[x] += rt[x - 1] * (v[x - 1] - v[x]);
          for (int x = w - 2; x >= 0; --x) v[x] += rt[x] * (v[x + 1] - v[x]);
        }
    });
    // Vertical, a row at a time (sequential in y, vectorised in x).
    for (cv::Mat* m : {a, b}) {
      for (int y = 1; y < h; ++y) {
        float* v = m->ptr<float>(y);
        const float* u = m->ptr<float>(y - 1);
        const float* dn = fd + 3 * static_cast<size_t>(y - 1) * w;
        for (int x = 0; x < 3 * w; ++x) v[x] += dn[x] * (u[x] - v[x]);
      }
      for (int y = h - 2; y >= 0; --y) {
        float* v = m->ptr<float>(y);
        const float* d = m->ptr<float>(y + 1);
        const float* dn = fd + 3 * static_cast<size_t>(y) * w;
        for (int x = 0; x < 3 * w; ++x) v[x] += dn[x] * (d[x] - v[x]);
      }
    }
  }
}

// Rotates `n` by the rotation taking unit vector a to unit vector b (Rodrigues, without trig).
inline cv::Vec3f RotateByAlignment(const cv::Vec3f& a, const cv::Vec3f& b, const cv::Vec3f& n) {
  const cv::Vec3f v = a.cross(b);
  const float c = a.dot(b);
  if (c <= -0.99f) return n;  // (nearly) opposite: no well-defined rotation
  return n * c + v.cross(n) + v * (v.dot(n) / (1.f + c));
}

}  // namespace

// Nehab's correction (see internal::CorrectNormals) into *out; a and b are scratch images.
void CorrectNormalsInto(const cv::Mat& input, const cv::Mat& reference, double sigma_px,
                        const internal::FusionStencil* links, const RowBlocks& blocks, std::vector<float>* factors,
                        cv::Mat* a, cv::Mat* b, cv::Mat* out) {
  a->create(input.size(), CV_32FC3);
  b->create(input.size(), CV_32FC3);
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      const cv::Vec3f* ni = input.ptr<cv::Vec3f>(y);
      const cv::Vec3f* nr = reference.ptr<cv::Vec3f>(y);
      cv::Vec3f* pa = a->ptr<cv::Vec3f>(y);
      cv::Vec3f* pb = b->ptr<cv::Vec3f>(y);
      for (int x = 0; x < input.cols; ++x) {
        const bool both = NormalPresent(ni[x]) && NormalPresent(nr[x]);
        pa[x] = both ? ni[x] / std::sqrt(ni[x].dot(ni[x])) : cv::Vec3f(0, 0, 0);
        pb[x] = both ? nr[x] / std::sqrt(nr[x].dot(nr[x])) : cv::Vec3f(0, 0, 0);
      }
    }
  });
  if (links != nullptr) {
    EdgeAwareLowPass(*links, sigma_px, blocks, factors, a, b);
  } else {
    *a = GaussianLowPass(*a, sigma_px);
    *b = GaussianLowPass(*b, sigma_px);
  }
  out->create(input.size(), CV_32FC3);
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      const cv::Vec3f* ni = input.ptr<cv::Vec3f>(y);
      const cv::Vec3f* pa = a->ptr<cv::Vec3f>(y);
      const cv::Vec3f* pb = b->ptr<cv::Vec3f>(y);
      cv::Vec3f* o = out->ptr<cv::Vec3f>(y);
      for (int x = 0; x < input.cols; ++x) {
        o[x] = ni[x];
        if (!NormalPresent(ni[x])) continue;
        const float na = std::sqrt(pa[x].dot(pa[x])), nb = std::sqrt(pb[x].dot(pb[x]));
        if (!(na > 1e-6f && nb > 1e-6f)) continue;
        const cv::Vec3f n = RotateByAlignment(pa[x] / na, pb[x] / nb, ni[x] / std::sqrt(ni[x].dot(ni[x])));
        const float len = std::sqrt(n.dot(n));
        if (len > 0) o[x] = n / len;
      }
    }
  });
}

}  // namespace internal
}  // namespace prism
