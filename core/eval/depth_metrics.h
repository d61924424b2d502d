// Depth map error after aligning the estimate's scale to the ground truth (monocular depth is known up
// to scale). Depth maps are CV_32FC1 metres, 0 (or non-finite) = no depth (core/io/image_io.h).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "core/util/status.h"

namespace prism {

enum class DepthScaleAlignment {
  kNone,          // compare as is (metric estimates)
  kMedianRatio,   // scale = median over pixels of gt / est
  kLeastSquares,  // scale minimising sum (s est - gt)^2 = sum(gt est) / sum(est^2)
};

// "none", "median", "least_squares".
const char* DepthScaleAlignmentName(DepthScaleAlignment alignment);
// Parses the names above; INVALID_ARGUMENT otherwise.
StatusOr<DepthScaleAlignment> ParseDepthScaleAlignment(const std::string& name);

struct DepthEvalOptions {
  // How one scale for the estimate is chosen (over all pixels added, i.e. one scale per sequence).
  DepthScaleAlignment scale_alignment = DepthScaleAlignment::kMedianRatio;
  Status Check() const;
};

struct DepthErrorStats {
  double scale = 1.0;             // factor applied to the estimate
  size_t pixels = 0;              // pixels with both depths valid (inside the mask)
  size_t gt_pixels = 0;           // pixels with valid ground truth inside the mask
  double coverage = 0.0;          // pixels / gt_pixels, in [0, 1]
  double rmse_m = 0.0;            // sqrt(mean (s est - gt)^2)
  double mean_abs_m = 0.0;        // mean |s est - gt|
  double median_rel_error = 0.0;  // median |s est - gt| / gt
};

// Collects valid depth pairs over many frames; the scale and statistics are computed once at the end.
class DepthErrorAccumulator {
 public:
  // Uses the pixels with mask != 0 (`mask` empty = every pixel, else CV_8UC1 of the same size);
  // INVALID_ARGUMENT on wrong types or sizes.
  Status Add(const cv::Mat& estimate_m, const cv::Mat& ground_truth_m, const cv::Mat& mask = cv::Mat());
  // FAILED_PRECONDITION when no pixel has both depths valid.
  StatusOr<DepthErrorStats> Summarize(const DepthEvalOptions& options) const;

 private:
  std::vector<float> estimate_m_;  // parallel to ground_truth_m_, pixels with both valid
  std::vector<float> ground_truth_m_;
  size_t gt_pixels_ = 0;
};

// One frame: DepthErrorAccumulator::Add followed by Summarize.
StatusOr<DepthErrorStats> ComputeDepthError(const cv::Mat& estimate_m, const cv::Mat& ground_truth_m,
                                            const cv::Mat& mask, const DepthEvalOptions& options);

}  // namespace prism
