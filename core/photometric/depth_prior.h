// The SLAM depth prior of a keyframe and what photometric stereo derives from it: a densified
// inverse depth (normalised convolution, Knutsson & Westin 1993) and prior normals.
#pragma once

#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/io/inverse_depth.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

struct DensifyOptions {
  // Gaussian scale of the first normalised-convolution pass, pixels, in [0.5, 50].
  double sigma_px = 2.0;
  // Passes with doubling scale that fill the remaining holes, in [1, 10].
  int levels = 6;
  // Minimum summed certainty for a pixel to count as filled at a level, relative to the peak of
  // the level's Gaussian, in (0, 1].
  double min_certainty = 0.02;

  Status Check() const;
};

// Dense inverse depth from a sparse one by multi-scale normalised convolution with certainty
// 1/variance. Pixels never reached stay 0.
cv::Mat DensifyInverseDepth(const InverseDepthMap& sparse, const DensifyOptions& options);

struct PriorNormalOptions {
  // Relative depth jump between neighbours marking a depth edge (no prior normal there), > 0.
  double max_relative_depth_jump = 0.03;
  // Half-width of the finite-difference stencil, pixels, in [1, 20]. Semi-dense depth is noisy
  // (about 1% of depth): at 0.5 m and 550 px focal length a 2-pixel baseline is 2 mm, well below
  // the noise, so prior normals need a wide stencil on a smoothed depth.
  int step_px = 4;
  // Gaussian smoothing of the inverse depth before differencing, pixels (0 = none), in [0, 20].
  double smoothing_sigma_px = 3.0;

  Status Check() const;
};

// Normals of the surface given by a dense inverse depth, in the camera frame, facing the camera;
// (0,0,0) at depth edges and holes. Rows are spread over `pool` when given. The inverse depth they
// are differentiated from (smoothed by options.smoothing_sigma_px over valid pixels; shares data
// with the input when not smoothed) goes to *smoothed_inverse_depth when given.
cv::Mat PriorNormals(const cv::Mat& dense_inverse_depth, const PinholeCamera& camera, const PriorNormalOptions& options,
                     ThreadPool* pool = nullptr, cv::Mat* smoothed_inverse_depth = nullptr);

}  // namespace prism
