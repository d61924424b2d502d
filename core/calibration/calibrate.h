// Rig calibration from images only (issue 76): camera intrinsics and distortion from views of a
// ChArUco board, then the three lights (position in the camera frame, intensity, crosstalk) fitted
// to the board's white paper in views lit by each light alone and by all three (light_fit.h).
//
// Input folder:
//   intrinsics/*.png|jpg           the board under any light, many poses
//   lights/red|green|blue/*.png|jpg  the board lit by that light alone (dark room)
//   lights/all/*.png|jpg           optional: all three lights together
// Crosstalk convention: crosstalk(l, l) = 1, so intensity_l is the response of camera channel l to
// light l; intensities are for a white of albedo 1 given `white_albedo` of the board's paper.
#pragma once

#include <array>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "core/calibration/charuco_board.h"
#include "core/calibration/light_fit.h"
#include "core/io/calibration_io.h"
#include "core/util/status.h"

namespace prism::calibration {

struct CalibrateOptions {
  CharucoBoardOptions board;
  // Views with the board found needed for the intrinsics, in [3, 1000]; more views, tighter focal length.
  int min_intrinsics_views = 6;
  // Views with the board found needed per light folder (red, green, blue), in [1, 1000].
  int min_light_views = 2;
  // Chessboard corners a view needs to count, in [6, 10000].
  int min_corners = 8;
  // Fit the sixth-order radial term k3 (off: k3 = 0, steadier with few views or a mild lens).
  bool fit_k3 = false;
  // Albedo of the board's white paper, in (0, 1]; intensities scale with 1 / white_albedo.
  double white_albedo = 1.0;
  // 8-bit level at or above which a pixel counts as saturated, in [1, 255].
  int saturation_level = 250;
  // Largest fraction of saturated white-paper samples before a light image is rejected, in [0, 1].
  double max_saturated_fraction = 0.2;
  // A light image whose 99th-percentile level stays below this (8-bit) is dark, in [0, 255].
  int dark_level = 20;
  // Spacing of the white-paper samples on the board and their distance from ink, metres, in (0, 0.1].
  double sample_spacing_m = 0.004;
  double sample_inset_m = 0.002;
  // Largest RMS reprojection error of the intrinsics, pixels, in (0, 100]: above it the board options
  // do not match the printed board (or the images are blurred).
  double max_reprojection_rms_px = 1.0;
  // Largest RMS residual of the light fit, 8-bit levels, in (0, 255]: above it the images do not
  // follow the model (ambient light, glossy paper, auto exposure, a wrong board).
  double max_light_rms_levels = 5.0;
  LightFitOptions light_fit;

  Status Check() const;
};

struct CalibrationReport {
  RigCalibration rig;
  // Intrinsics: views used / found, RMS reprojection error, standard deviations.
  int intrinsics_images = 0;
  int intrinsics_views = 0;
  double reprojection_rms_px = 0;
  Eigen::Vector4d intrinsics_std = Eigen::Vector4d::Zero();  // fx, fy, cx, cy, pixels
  std::array<double, 5> distortion_std{};
  // Whether a distortion coefficient differed from zero by 3 standard deviations; if not, the camera is
  // the pinhole model fitted without distortion, and distortion_fitted holds what the full fit found.
  bool distortion_significant = true;
  std::array<double, 5> distortion_fitted{};
  // Lights: views per folder (red, green, blue, all), samples, fit residual and uncertainty.
  std::array<int, 4> light_views{};
  std::vector<std::string> skipped;  // images without the board (relative paths)
  LightFitResult light_fit;
  std::array<double, 3> intensity_std{};
  Eigen::Matrix3d crosstalk_std = Eigen::Matrix3d::Zero();
  // What the calibration holds but a person should act on (a light placed with a large uncertainty).
  std::vector<std::string> warnings;
};

StatusOr<CalibrationReport> CalibrateRig(const std::string& folder, const CalibrateOptions& options);

// The folder names of the light images and the lights each one has on (bit l: light l).
inline constexpr std::array<const char*, 4> kLightFolders = {"red", "green", "blue", "all"};
inline constexpr std::array<int, 4> kLightFolderLit = {1, 2, 4, 7};

}  // namespace prism::calibration
