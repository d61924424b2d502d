// Fits the three near point lights to white-paper samples on a board of known pose, with the
// renderer's and photometric stereo's image formation (core/synth/renderer.h), ambient-free:
//   I_c(x) = sum_l G(c, l) * max(0, n . (p_l - x)) / |p_l - x|^3
// over the lights l lit in the image, G(c, l) = crosstalk(c, l) * albedo_l * intensity_l the gain of
// camera channel c to light l, p_l the light position in the camera frame, n the board normal.
// Levenberg-Marquardt on the 9 positions and 9 gains from a grid-search start; the uncertainty is
// sigma^2 (J^T J)^-1 with sigma^2 the residual variance.
#pragma once

#include <array>
#include <vector>

#include <Eigen/Core>

#include "core/util/status.h"

namespace prism::calibration {

// One white-paper sample: the board point and normal (facing the camera) in the camera frame and
// the pixel's colour in [0, 1] (camera channels R, G, B).
struct LightSample {
  int lit = 0;  // bit l set: light l was on (1, 2, 4: one light; 7: all three)
  Eigen::Vector3d point_in_camera;
  Eigen::Vector3d normal_in_camera;
  Eigen::Vector3d rgb;
};

struct LightFitOptions {
  // Levenberg-Marquardt iterations, in [1, 1000].
  int max_iterations = 100;
  // Search box for the start: |x|, |y| <= search_radius_m and |z| <= search_radius_m / 2, metres, in (0, 2].
  double search_radius_m = 0.4;

  Status Check() const;
};

struct LightFitResult {
  std::array<Eigen::Vector3d, 3> position_in_camera;
  std::array<Eigen::Vector3d, 3> position_std;         // one standard deviation per axis, metres
  Eigen::Matrix3d gain = Eigen::Matrix3d::Zero();      // G(c, l)
  Eigen::Matrix3d gain_std = Eigen::Matrix3d::Zero();  // its standard deviation
  // Covariance of the 18 parameters (p_0, p_1, p_2, then G column by column).
  Eigen::Matrix<double, 18, 18> covariance = Eigen::Matrix<double, 18, 18>::Zero();
  double rms = 0;  // residual root mean square, [0, 1] pixel units
  int residuals = 0;
  int iterations = 0;
  bool converged = false;
};

// Fails when a light has no sample that it lit alone or the normal equations are singular.
StatusOr<LightFitResult> FitLights(const std::vector<LightSample>& samples, const LightFitOptions& options);

}  // namespace prism::calibration
