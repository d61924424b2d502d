#include "core/eval/depth_metrics.h"

#include <cmath>
#include <sstream>

#include "core/eval/statistics.h"

namespace prism {
namespace {

bool IsValidDepth(float d) { return std::isfinite(d) && d > 0.0f; }

}  // namespace

const char* DepthScaleAlignmentName(DepthScaleAlignment alignment) {
  switch (alignment) {
    case DepthScaleAlignment::kNone:
      return "none";
    case DepthScaleAlignment::kMedianRatio:
      return "median";
    case DepthScaleAlignment::kLeastSquares:
      return "least_squares";
  }
  return "unknown";
}

StatusOr<DepthScaleAlignment> ParseDepthScaleAlignment(const std::string& name) {
  if (name == "none") return DepthScaleAlignment::kNone;
  if (name == "median") return DepthScaleAlignment::kMedianRatio;
  if (name == "least_squares") return DepthScaleAlignment::kLeastSquares;
  return InvalidArgumentError("unknown depth scale alignment '" + name + "' (expected none, median or least_squares)");
}

Status DepthEvalOptions::Check() const {
  if (scale_alignment != DepthScaleAlignment::kNone && scale_alignment != DepthScaleAlignment::kMedianRatio &&
      scale_alignment != DepthScaleAlignment::kLeastSquares) {
    std::ostringstream err;
    err << "DepthEvalOptions.scale_alignment = " << static_cast<int>(scale_alignment)
        << "; violated: none, median or least_squares";
    return InvalidArgumentError(err.str());
  }
  return Status::Ok();
}

Status DepthErrorAccumulator::Add(const cv::Mat& estimate_m, const cv::Mat& ground_truth_m, const cv::Mat& mask) {
  if (estimate_m.type() != CV_32FC1 || ground_truth_m.type() != CV_32FC1)
    return InvalidArgumentError("depth maps must be CV_32FC1");
  if (estimate_m.size() != ground_truth_m.size())
    return InvalidArgumentError("depth map sizes differ: estimate " + std::to_string(estimate_m.cols) + "x" +
                                std::to_string(estimate_m.rows) + ", ground truth " +
                                std::to_string(ground_truth_m.cols) + "x" + std::to_string(ground_truth_m.rows));
  if (!mask.empty() && (mask.type() != CV_8UC1 || mask.size() != estimate_m.size()))
    return InvalidArgumentError("mask must be CV_8UC1 of the depth maps' size");
  for (int y = 0; y < estimate_m.rows; ++y) {
    const float* e = estimate_m.ptr<float>(y);
    const float* g = ground_truth_m.ptr<float>(y);
    const uint8_t* m = mask.empty() ? nullptr : mask.ptr<uint8_t>(y);
    for (int x = 0; x < estimate_m.cols; ++x) {
      if ((m && m[x] == 0) || !IsValidDepth(g[x])) continue;
      ++gt_pixels_;
      if (!IsValidDepth(e[x])) continue;
      estimate_m_.push_back(e[x]);
      ground_truth_m_.push_back(g[x]);
    }
  }
  return Status::Ok();
}

StatusOr<DepthErrorStats> DepthErrorAccumulator::Summarize(const DepthEvalOptions& options) const {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (estimate_m_.empty())
    return FailedPreconditionError("depth: no pixel has both an estimated and a ground-truth depth");
  const size_t n = estimate_m_.size();
  DepthErrorStats s;
  s.pixels = n;
  s.gt_pixels = gt_pixels_;
  s.coverage = static_cast<double>(n) / static_cast<double>(gt_pixels_);
  switch (options.scale_alignment) {
    case DepthScaleAlignment::kNone:
      s.scale = 1.0;
      break;
    case DepthScaleAlignment::kMedianRatio: {
      std::vector<double> ratios(n);
      for (size_t i = 0; i < n; ++i)
        ratios[i] = static_cast<double>(ground_truth_m_[i]) / static_cast<double>(estimate_m_[i]);
      s.scale = Median(std::move(ratios));
      break;
    }
    case DepthScaleAlignment::kLeastSquares: {
      double cross = 0.0;
      double est_sq = 0.0;
      for (size_t i = 0; i < n; ++i) {
        cross += static_cast<double>(ground_truth_m_[i]) * estimate_m_[i];
        est_sq += static_cast<double>(estimate_m_[i]) * estimate_m_[i];
      }
      s.scale = cross / est_sq;
      break;
    }
  }
  double sum_sq = 0.0;
  double sum_abs = 0.0;
  std::vector<double> relative(n);
  for (size_t i = 0; i < n; ++i) {
    const double gt = ground_truth_m_[i];
    const double diff = std::abs(s.scale * estimate_m_[i] - gt);
    sum_sq += diff * diff;
    sum_abs += diff;
    relative[i] = diff / gt;
  }
  s.rmse_m = std::sqrt(sum_sq / static_cast<double>(n));
  s.mean_abs_m = sum_abs / static_cast<double>(n);
  s.median_rel_error = Median(std::move(relative));
  return s;
}

StatusOr<DepthErrorStats> ComputeDepthError(const cv::Mat& estimate_m, const cv::Mat& ground_truth_m,
                                            const cv::Mat& mask, const DepthEvalOptions& options) {
  DepthErrorAccumulator acc;
  PRISM_RETURN_IF_ERROR(acc.Add(estimate_m, ground_truth_m, mask));
  return acc.Summarize(options);
}

}  // namespace prism
