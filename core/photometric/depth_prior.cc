#include "core/photometric/depth_prior.h"

#include <cmath>
#include <sstream>

#include <opencv2/imgproc.hpp>

namespace prism {

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
  for (int y = 0; y < d.rows; ++y)
    for (int x = 0; x < d.cols; ++x) {
      const float v = sparse.variance.at<float>(y, x), id = d.at<float>(y, x);
      if (id > 0 && v > 0 && std::isfinite(id) && std::isfinite(v)) {
        certainty.at<float>(y, x) = 1.f / v;
        cs.push_back(1.f / v);
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
      }
    }
    if (all_filled) break;
  }
  return dense;
}

cv::Mat PriorNormals(const cv::Mat& raw, const PinholeCamera& camera, const PriorNormalOptions& options) {
  cv::Mat normals(raw.size(), CV_32FC3, cv::Scalar(0, 0, 0));
  cv::Mat inv = raw;
  if (options.smoothing_sigma_px > 0) {
    // Normalised smoothing over valid pixels only, so holes do not pull depth towards 0.
    cv::Mat valid = raw > 0, num, den;
    valid.convertTo(valid, CV_32F, 1.0 / 255.0);
    const int k = static_cast<int>(std::ceil(3 * options.smoothing_sigma_px)) * 2 + 1;
    cv::GaussianBlur(raw, num, cv::Size(k, k), options.smoothing_sigma_px);
    cv::GaussianBlur(valid, den, cv::Size(k, k), options.smoothing_sigma_px);
    inv = num / cv::max(den, 1e-6f);
    inv.setTo(0, raw <= 0);
  }
  const int s = options.step_px;
  const float max_jump = static_cast<float>(options.max_relative_depth_jump);
  auto point = [&](int x, int y, Eigen::Vector3d* p) {
    const float id = inv.at<float>(y, x);
    if (!(id > 0)) return false;
    *p = Eigen::Vector3d((x - camera.cx) / camera.fx, (y - camera.cy) / camera.fy, 1.0) / id;
    return true;
  };
  for (int y = s; y < inv.rows - s; ++y) {
    cv::Vec3f* out = normals.ptr<cv::Vec3f>(y);
    for (int x = s; x < inv.cols - s; ++x) {
      const float c = inv.at<float>(y, x);
      if (!(c > 0)) continue;
      // Depth edge test on the stencil (relative change of inverse depth = of depth, to first order).
      const float l = inv.at<float>(y, x - s), r = inv.at<float>(y, x + s), u = inv.at<float>(y - s, x),
                  d = inv.at<float>(y + s, x);
      if (!(l > 0 && r > 0 && u > 0 && d > 0)) continue;
      // Second differences: a smooth surface is locally linear in inverse depth; a depth edge is not.
      if (std::abs(l + r - 2 * c) > max_jump * c || std::abs(u + d - 2 * c) > max_jump * c) continue;
      Eigen::Vector3d pl, pr, pu, pd;
      if (!point(x - s, y, &pl) || !point(x + s, y, &pr) || !point(x, y - s, &pu) || !point(x, y + s, &pd)) continue;
      Eigen::Vector3d n = (pr - pl).cross(pd - pu);
      const double len = n.norm();
      if (len <= 0) continue;
      n /= len;
      const Eigen::Vector3d ray((x - camera.cx) / camera.fx, (y - camera.cy) / camera.fy, 1.0);
      if (n.dot(ray) > 0) n = -n;  // face the camera
      out[x] = cv::Vec3f(static_cast<float>(n.x()), static_cast<float>(n.y()), static_cast<float>(n.z()));
    }
  }
  return normals;
}

}  // namespace prism
