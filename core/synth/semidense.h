// Simulated semi-dense SLAM depth for testing the dense stage before SLAM exists: ground-truth
// inverse depth kept only at high-gradient pixels (where direct SLAM has depth), with noise and
// an unknown scale, like LSD-SLAM's keyframe depth maps.
#pragma once

#include <cstdint>

#include <opencv2/core.hpp>

#include "core/io/inverse_depth.h"
#include "core/util/status.h"

namespace prism::synth {

struct SemiDenseOptions {
  // Minimum intensity-gradient magnitude (grey levels per pixel, central differences) for a pixel
  // to get depth, in [0, 255].
  double min_gradient = 3.0;
  // Relative standard deviation of the inverse-depth noise, in [0, 0.5].
  double relative_noise = 0.01;
  // Unknown scale: the output is in units of `scale` metres (SLAM units), > 0.
  double scale = 1.0;
  // Fraction of high-gradient pixels randomly dropped (depth filter not converged), in [0, 1).
  double dropout = 0.1;
  // Fraction of outliers (inverse depth off by up to +-30%), in [0, 0.5].
  double outlier_fraction = 0.0;
  uint32_t seed = 1;

  Status Check() const;
};

// depth: CV_32F metres (0 = none); rgb: CV_8UC3. Variance is the noise variance in output units.
InverseDepthMap SimulateSemiDenseDepth(const cv::Mat& depth, const cv::Mat& rgb, const SemiDenseOptions& options);

}  // namespace prism::synth
