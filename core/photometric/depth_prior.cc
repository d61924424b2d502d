#include "core/photometric/depth_prior.h"

#include <cmath>
#include <limits>
#include <sstream>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "core/util/thread_pool.h"

namespace prism {
namespace {

// Prior normals of one row from the inverse depth of the rows `step` above and below and the row
// itself (pointers at the first pixel computed; the row has `step` valid pixels either side):
// finite differences of the back-projected points, (0,0,0) at holes and depth edges. Float,
// branch-free, on plain arrays: vectorised.
void NormalsRow(int n, const float* __restrict up, const float* __restrict mid, const float* __restrict down, int step,
                float max_jump, float ray_x0, float ray_dx, float ray_y, float ray_dy, float* __restrict out_x,
                float* __restrict out_y, float* __restrict out_z) {
  const float ry_up = ray_y - ray_dy, ry_down = ray_y + ray_dy, rstep = step * ray_dx;
  for (int i = 0; i < n; ++i) {
    const float c = mid[i], l = mid[i - step], r = mid[i + step], u = up[i], d = down[i];
    // Holes, and depth edges on the stencil: a smooth surface is locally linear in inverse depth
    // (second differences relative to the centre; relative change of inverse depth = of depth).
    const bool valid = (c > 0) & (l > 0) & (r > 0) & (u > 0) & (d > 0) & (std::abs(l + r - 2 * c) <= max_jump * c) &
                       (std::abs(u + d - 2 * c) <= max_jump * c);
    // Back-projected stencil points (ray / inverse depth): horizontal and vertical differences.
    const float rx = ray_x0 + ray_dx * static_cast<float>(i), rx_l = rx - rstep, rx_r = rx + rstep;
    const float il = 1.f / (valid ? l : 1.f), ir = 1.f / (valid ? r : 1.f);
    const float iu = 1.f / (valid ? u : 1.f), id = 1.f / (valid ? d : 1.f);
    const float hx = rx_r * ir - rx_l * il, hy = ray_y * (ir - il), hz = ir - il;
    const float vx = rx * (id - iu), vy = ry_down * id - ry_up * iu, vz = id - iu;
    const float nx = hy * vz - hz * vy, ny = hz * vx - hx * vz, nz = hx * vy - hy * vx;
    const float len2 = nx * nx + ny * ny + nz * nz;
    const bool ok = valid & (len2 > 0) & (len2 <= std::numeric_limits<float>::max());
    // Unit length, facing the camera.
    const float facing = nx * rx + ny * ray_y + nz;
    const float scale = (facing > 0 ? -1.f : 1.f) / std::sqrt(ok ? len2 : 1.f);
    out_x[i] = ok ? nx * scale : 0.f;
    out_y[i] = ok ? ny * scale : 0.f;
    out_z[i] = ok ? nz * scale : 0.f;
  }
}

}  // namespace

Status DensifyOptions::Check() const {
  std::ostringstream e;
  if (!(sigma_px >= 0.5 && sigma_px <= 50)) e << "DensifyOptions.sigma_px = " << sigma_px << "; violated: in [0.5, 50]";
  else if (levels < 1 || levels > 10) e << "DensifyOptions.levels = " << levels << "; violated: in [1, 10]";
  else if (!(min_certainty > 0 && min_certainty <= 1))
    e << "DensifyOptions.min_certainty = " << min_certainty << "; violated: in (0, 1]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

Status PriorNormalOptions::Check() const {
  std::ostringstream e;
  if (!(max_relative_depth_jump > 0)) e << "PriorNormalOptions.max_relative_depth_jump must be > 0";
  else if (step_px < 1 || step_px > 20) e << "PriorNormalOptions.step_px = " << step_px << "; violated: in [1, 20]";
  else if (!(smoothing_sigma_px >= 0 && smoothing_sigma_px <= 20))
    e << "PriorNormalOptions.smoothing_sigma_px = " << smoothing_sigma_px << "; violated: in [0, 20]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

cv::Mat DensifyInverseDepth(const InverseDepthMap& sparse, const DensifyOptions& options) {
  const cv::Mat& d = sparse.inverse_depth;
  cv::Mat certainty(d.size(), CV_32F, cv::Scalar(0));
  // Certainty = 1/variance, normalised so the median certainty is 1 (keeps the float sums tame).
  std::vector<float> cs;
  for (int y = 0; y < d.rows; ++y) {
    const float* var = sparse.variance.ptr<float>(y);
    const float* inv = d.ptr<float>(y);
    float* c = certainty.ptr<float>(y);
    for (int x = 0; x < d.cols; ++x) {
      const float v = var[x], id = inv[x];
      if (id > 0 && v > 0 && std::isfinite(id) && std::isfinite(v)) {
        c[x] = 1.f / v;
        cs.push_back(1.f / v);
      }
    }
  }
  cv::Mat dense(d.size(), CV_32F, cv::Scalar(0));
  if (cs.empty()) return dense;
  std::nth_element(cs.begin(), cs.begin() + cs.size() / 2, cs.end());
  certainty /= cs[cs.size() / 2];
  // Coarse levels run on a pyramid (area-averaged sums, a fixed Gaussian per level) instead of ever
  // wider Gaussians at full resolution: the same filter up to resampling, at a fraction of the cost.
  cv::Mat num = certainty.mul(d), den = certainty;
  cv::Mat filled(d.size(), CV_8U, cv::Scalar(0));
  std::vector<int> unfilled(d.rows, d.cols);  // per row
  const double sigma = options.sigma_px;
  const int ksize = static_cast<int>(std::ceil(3 * sigma)) * 2 + 1;
  for (int level = 0; level < options.levels; ++level) {
    if (level > 0) {
      if (num.cols < 4 || num.rows < 4) break;
      cv::resize(num, num, cv::Size((num.cols + 1) / 2, (num.rows + 1) / 2), 0, 0, cv::INTER_AREA);
      cv::resize(den, den, cv::Size((den.cols + 1) / 2, (den.rows + 1) / 2), 0, 0, cv::INTER_AREA);
    }
    cv::Mat bn, bd;
    cv::GaussianBlur(num, bn, cv::Size(ksize, ksize), sigma, sigma, cv::BORDER_CONSTANT);
    cv::GaussianBlur(den, bd, cv::Size(ksize, ksize), sigma, sigma, cv::BORDER_CONSTANT);
    if (level > 0) {
      cv::resize(bn, bn, d.size(), 0, 0, cv::INTER_LINEAR);
      cv::resize(bd, bd, d.size(), 0, 0, cv::INTER_LINEAR);
    }
    // A Gaussian's peak weight is 1/(2 pi sigma^2), and area averaging divides a sample by 4 per
    // level: a pixel counts as filled when its neighbourhood holds at least min_certainty of one
    // median-certainty sample at the peak (the same rule as a Gaussian of sigma * 2^level).
    const float threshold =
        static_cast<float>(options.min_certainty / (2 * M_PI * sigma * sigma * std::pow(4.0, level)));
    bool all_filled = true;
    for (int y = 0; y < d.rows; ++y) {
      if (unfilled[y] == 0) continue;  // rows filled at earlier levels
      const float* n = bn.ptr<float>(y);
      const float* w = bd.ptr<float>(y);
      float* out = dense.ptr<float>(y);
      uint8_t* f = filled.ptr<uint8_t>(y);
      for (int x = 0; x < d.cols; ++x) {
        if (f[x]) continue;
        if (w[x] < threshold) {
          all_filled = false;
          continue;
        }
        out[x] = n[x] / w[x];
        f[x] = 1;
        --unfilled[y];
      }
    }
    if (all_filled) break;
  }
  return dense;
}

cv::Mat PriorNormals(const cv::Mat& raw, const PinholeCamera& camera, const PriorNormalOptions& options,
                     ThreadPool* pool, cv::Mat* smoothed_inverse_depth) {
  const int w = raw.cols, h = raw.rows;
  cv::Mat normals(raw.size(), CV_32FC3, cv::Scalar(0, 0, 0));  // the stencil's border stays 0
  cv::Mat inv = raw;
  if (options.smoothing_sigma_px > 0) {
    // Normalised smoothing over valid pixels only, so holes do not pull depth towards 0.
    cv::Mat valid(raw.size(), CV_32F), num, den;
    for (int y = 0; y < h; ++y) {
      const float* r = raw.ptr<float>(y);
      float* v = valid.ptr<float>(y);
      for (int x = 0; x < w; ++x) v[x] = r[x] > 0 ? 1.f : 0.f;
    }
    const int k = static_cast<int>(std::ceil(3 * options.smoothing_sigma_px)) * 2 + 1;
    cv::GaussianBlur(raw, num, cv::Size(k, k), options.smoothing_sigma_px);
    cv::GaussianBlur(valid, den, cv::Size(k, k), options.smoothing_sigma_px);
    inv = num;  // normalised in place
    for (int y = 0; y < h; ++y) {
      const float* r = raw.ptr<float>(y);
      const float* d = den.ptr<float>(y);
      float* out = inv.ptr<float>(y);
      for (int x = 0; x < w; ++x) out[x] = r[x] > 0 ? out[x] / std::max(d[x], 1e-6f) : 0.f;
    }
  }
  const int s = options.step_px;
  const float max_jump = static_cast<float>(options.max_relative_depth_jump);
  const float inv_fx = static_cast<float>(1.0 / camera.fx), inv_fy = static_cast<float>(1.0 / camera.fy);
  const float cx = static_cast<float>(camera.cx), cy = static_cast<float>(camera.cy);
  auto normals_row = [&](std::ptrdiff_t row) {
    const int y = static_cast<int>(row) + s;
    const int n = w - 2 * s;
    std::vector<float> nx(n), ny(n), nz(n);
    NormalsRow(n, inv.ptr<float>(y - s) + s, inv.ptr<float>(y) + s, inv.ptr<float>(y + s) + s, s, max_jump,
               (s - cx) * inv_fx, inv_fx, (y - cy) * inv_fy, s * inv_fy, nx.data(), ny.data(), nz.data());
    cv::Vec3f* out = normals.ptr<cv::Vec3f>(y) + s;
    for (int i = 0; i < n; ++i) out[i] = cv::Vec3f(nx[i], ny[i], nz[i]);
  };
  if (smoothed_inverse_depth) *smoothed_inverse_depth = inv;
  const int rows = std::max(0, h - 2 * s);
  if (pool) {
    pool->ParallelFor(0, rows, normals_row, 16);
  } else {
    for (int r = 0; r < rows; ++r) normals_row(r);
  }
  return normals;
}

}  // namespace prism
