// Pinhole camera with OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).
// Camera frame: x right, y down, z forward (OpenCV). Pixel centres at integer coordinates.
#pragma once

#include <array>
#include <string>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/util/status.h"

namespace prism {

struct PinholeCamera {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  // OpenCV order: k1, k2, p1, p2, k3. All zero = no distortion.
  std::array<double, 5> distortion{0, 0, 0, 0, 0};

  // Square pixels, principal point at the centre, horizontal field of view in degrees.
  static PinholeCamera FromFov(int width, int height, double hfov_deg);

  Status Check() const;
  bool HasDistortion() const;
  Eigen::Matrix3d K() const;
  // The camera of an image pyramid's level (each level a 2x2 average of the one below; level 0 = this).
  PinholeCamera AtPyramidLevel(int level) const;

  // Projects a point in the camera frame to pixel coordinates (with distortion). z must be > 0.
  Eigen::Vector2d Project(const Eigen::Vector3d& point_in_camera) const;
  // Ray direction (z = 1) through a pixel; undoes distortion iteratively when present.
  Eigen::Vector3d Unproject(const Eigen::Vector2d& pixel) const;
  bool InImage(const Eigen::Vector2d& pixel, double border = 0) const {
    return pixel.x() >= border && pixel.y() >= border && pixel.x() <= width - 1 - border &&
           pixel.y() <= height - 1 - border;
  }
};

}  // namespace prism
