// The rig calibration in `camera.yaml` (OpenCV FileStorage YAML): camera intrinsics, the three
// coloured lights fixed to the camera, and the spectral crosstalk matrix.
//
//   width, height, fx, fy, cx, cy: pixels
//   distortion: 1x5 matrix (k1 k2 p1 p2 k3, OpenCV order)
//   crosstalk: 3x3 matrix, entry (c, l) = response of camera channel c (R,G,B) to light l
//   lights: sequence of 3 maps (red, green, blue) with
//     name, type ("point" | "directional"),
//     position: [x, y, z] in the camera frame, metres (point lights),
//     direction: [x, y, z] unit vector from the scene towards the light, camera frame (directional),
//     color: [r, g, b] nominal colour, intensity: a white Lambertian surface facing the light
//     at 1 m (directional: anywhere) gives this value in [0, 1] pixel units, before crosstalk.
#pragma once

#include <array>
#include <cmath>
#include <string>

#include <Eigen/Core>

#include "core/geometry/camera.h"
#include "core/util/status.h"

namespace prism {

enum class LightType { kPoint, kDirectional };

struct Light {
  std::string name;
  LightType type = LightType::kPoint;
  Eigen::Vector3d position_in_camera = Eigen::Vector3d::Zero();     // point lights, metres
  Eigen::Vector3d direction_in_camera = Eigen::Vector3d(0, 0, -1);  // directional, towards the light
  Eigen::Vector3d color = Eigen::Vector3d::Ones();
  double intensity = 0.25;

  // Unit vector from `point_in_camera` towards the light and the irradiance factor
  // intensity / d^2 (point) or intensity (directional).
  // Inline: the shading models call it several times per residual (EstimateShadingScale).
  void Illuminate(const Eigen::Vector3d& point_in_camera, Eigen::Vector3d* to_light, double* irradiance) const {
    if (type == LightType::kDirectional) {
      *to_light = direction_in_camera.normalized();
      *irradiance = intensity;
      return;
    }
    const Eigen::Vector3d d = position_in_camera - point_in_camera;
    const double d2 = d.squaredNorm();
    *to_light = d / std::sqrt(d2);
    *irradiance = intensity / d2;
  }
};

struct RigCalibration {
  PinholeCamera camera;
  std::array<Light, 3> lights;  // red, green, blue
  Eigen::Matrix3d crosstalk = Eigen::Matrix3d::Identity();

  Status Check() const;
};

StatusOr<RigCalibration> ReadCalibrationYaml(const std::string& path);
Status WriteCalibrationYaml(const std::string& path, const RigCalibration& calibration);

}  // namespace prism
