#include "core/eval/normal_metrics.h"

#include <algorithm>
#include <cmath>

#include "core/eval/statistics.h"

namespace prism {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

bool IsValidNormal(const cv::Vec3f& n) {
  return std::isfinite(n[0]) && std::isfinite(n[1]) && std::isfinite(n[2]) &&
         (n[0] != 0.0f || n[1] != 0.0f || n[2] != 0.0f);
}

}  // namespace

double AngleBetweenDeg(const cv::Vec3f& a, const cv::Vec3f& b) {
  const double ax = a[0], ay = a[1], az = a[2];
  const double bx = b[0], by = b[1], bz = b[2];
  const double cx = ay * bz - az * by;
  const double cy = az * bx - ax * bz;
  const double cz = ax * by - ay * bx;
  const double cross_norm = std::sqrt(cx * cx + cy * cy + cz * cz);
  const double dot = ax * bx + ay * by + az * bz;
  if (cross_norm == 0.0 && dot == 0.0) return 0.0;
  return std::atan2(cross_norm, dot) * kRadToDeg;
}

Status NormalErrorAccumulator::Add(const cv::Mat& estimate, const cv::Mat& ground_truth, const cv::Mat& mask) {
  if (estimate.type() != CV_32FC3 || ground_truth.type() != CV_32FC3)
    return InvalidArgumentError("normal maps must be CV_32FC3");
  if (estimate.size() != ground_truth.size())
    return InvalidArgumentError("normal map sizes differ: estimate " + std::to_string(estimate.cols) + "x" +
                                std::to_string(estimate.rows) + ", ground truth " + std::to_string(ground_truth.cols) +
                                "x" + std::to_string(ground_truth.rows));
  if (!mask.empty() && (mask.type() != CV_8UC1 || mask.size() != estimate.size()))
    return InvalidArgumentError("mask must be CV_8UC1 of the normal maps' size");
  for (int y = 0; y < estimate.rows; ++y) {
    const cv::Vec3f* e = estimate.ptr<cv::Vec3f>(y);
    const cv::Vec3f* g = ground_truth.ptr<cv::Vec3f>(y);
    const uint8_t* m = mask.empty() ? nullptr : mask.ptr<uint8_t>(y);
    for (int x = 0; x < estimate.cols; ++x) {
      if (m && m[x] == 0) continue;
      if (!IsValidNormal(e[x]) || !IsValidNormal(g[x])) continue;
      angles_deg_.push_back(static_cast<float>(AngleBetweenDeg(e[x], g[x])));
    }
  }
  return Status::Ok();
}

AngularErrorStats NormalErrorAccumulator::Summarize() const {
  AngularErrorStats s;
  s.count = angles_deg_.size();
  if (angles_deg_.empty()) return s;
  double sum = 0.0;
  double sum_sq = 0.0;
  size_t under_5 = 0, under_10 = 0, under_20 = 0;
  for (double a : angles_deg_) {
    sum += a;
    sum_sq += a * a;
    under_5 += a < 5.0;
    under_10 += a < 10.0;
    under_20 += a < 20.0;
  }
  const double n = static_cast<double>(angles_deg_.size());
  s.mean_deg = sum / n;
  s.rmse_deg = std::sqrt(sum_sq / n);
  s.pct_under_5 = 100.0 * static_cast<double>(under_5) / n;
  s.pct_under_10 = 100.0 * static_cast<double>(under_10) / n;
  s.pct_under_20 = 100.0 * static_cast<double>(under_20) / n;
  s.median_deg = Median(std::vector<double>(angles_deg_.begin(), angles_deg_.end()));
  return s;
}

StatusOr<AngularErrorStats> ComputeNormalError(const cv::Mat& estimate, const cv::Mat& ground_truth,
                                               const cv::Mat& mask) {
  NormalErrorAccumulator acc;
  PRISM_RETURN_IF_ERROR(acc.Add(estimate, ground_truth, mask));
  return acc.Summarize();
}

}  // namespace prism
