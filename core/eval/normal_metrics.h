// Angular error between estimated and ground-truth normal maps (CV_32FC3, camera frame, (0,0,0) = no
// normal; see core/io/image_io.h). Angles use atan2(|a x b|, a . b) in double, which stays accurate
// for small angles where acos(a . b) loses precision, and does not need unit-length inputs.
#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include "core/util/status.h"

namespace prism {

struct AngularErrorStats {
  size_t count = 0;  // compared pixels
  double mean_deg = 0.0;
  double median_deg = 0.0;  // mean of the two middle values for an even count
  double rmse_deg = 0.0;
  double pct_under_5 = 0.0;  // percent of pixels with error < 5 degrees, in [0, 100]
  double pct_under_10 = 0.0;
  double pct_under_20 = 0.0;
};

// Angle between two vectors in degrees, in [0, 180]; 0 when either is zero.
double AngleBetweenDeg(const cv::Vec3f& a, const cv::Vec3f& b);

// Collects per-pixel angles over many frames, then summarises them all at once.
class NormalErrorAccumulator {
 public:
  // Compares the pixels where both normals are valid (finite, not all zero) and mask != 0. `mask` may be
  // empty (every pixel) or CV_8UC1 of the same size. INVALID_ARGUMENT on wrong types or sizes.
  Status Add(const cv::Mat& estimate, const cv::Mat& ground_truth, const cv::Mat& mask = cv::Mat());
  // Statistics over every angle added so far (all zero when none).
  AngularErrorStats Summarize() const;
  size_t count() const { return angles_deg_.size(); }

 private:
  std::vector<float> angles_deg_;  // float: a long sequence has tens of millions of pixels
};

// One frame: NormalErrorAccumulator::Add followed by Summarize.
StatusOr<AngularErrorStats> ComputeNormalError(const cv::Mat& estimate, const cv::Mat& ground_truth,
                                               const cv::Mat& mask = cv::Mat());

}  // namespace prism
