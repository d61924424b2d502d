// Fits the three near point lights to white-paper samples on a board of known pose, with the
// renderer's and photometric stereo's image formation (core/synth/renderer.h):
//   I_c(x) = sum_l G(c, l) * max(0, n . (p_l - x)) / |p_l - x|^3 + b_c
// over the lights l lit in the image, G(c, l) = crosstalk(c, l) * albedo_l * intensity_l the gain of
// camera channel c to light l, p_l the light position in the camera frame, n the board normal, b_c
// the renderer's ambient term on the paper (stray room light and the sensor's black level; 0 when
// not fitted). Levenberg-Marquardt on the 9 positions, 9 gains and 3 offsets from a grid-search
// start; the uncertainty is sigma^2 (J^T J)^-1 with sigma^2 the residual variance.
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
  // Search box for the start: |x|, |y| <= search_radius_m and |z| <= search_radius_m / 4, metres, in (0, 2].
  double search_radius_m = 0.4;
  // Fit the constant offset b_c (ambient light, black level); off: b_c = 0 (a dark room, zero black level).
  bool fit_ambient = true;

  Status Check() const;
};

struct LightFitResult {
  std::array<Eigen::Vector3d, 3> position_in_camera;
  std::array<Eigen::Vector3d, 3> position_std;         // one standard deviation per axis, metres
  Eigen::Matrix3d gain = Eigen::Matrix3d::Zero();      // G(c, l)
  Eigen::Matrix3d gain_std = Eigen::Matrix3d::Zero();  // its standard deviation
  Eigen::Vector3d ambient = Eigen::Vector3d::Zero();   // b_c, [0, 1] pixel units
  Eigen::Vector3d ambient_std = Eigen::Vector3d::Zero();
  // Covariance of the 21 parameters (p_0, p_1, p_2, then G column by column, then b).
  Eigen::Matrix<double, 21, 21> covariance = Eigen::Matrix<double, 21, 21>::Zero();
  double rms = 0;  // residual root mean square, [0, 1] pixel units
  int residuals = 0;
  int iterations = 0;
  bool converged = false;
};

// Fails when a light has no sample that it lit alone or the normal equations are singular.
StatusOr<LightFitResult> FitLights(const std::vector<LightSample>& samples, const LightFitOptions& options);

}  // namespace prism::calibration
