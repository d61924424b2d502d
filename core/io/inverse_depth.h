// The semi-dense inverse depth of a keyframe: the dense stage's input, from SLAM or simulated.
#pragma once

#include <opencv2/core.hpp>

namespace prism {

struct InverseDepthMap {
  cv::Mat inverse_depth;  // CV_32F, 1/metre (or 1/SLAM unit), 0 = no estimate
  cv::Mat variance;       // CV_32F, variance of inverse_depth, > 0 where inverse_depth > 0
};

}  // namespace prism
