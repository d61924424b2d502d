// The tracker's helpers shared by tracker.cc (tracking) and tracker_keyframe.cc (Tracker::SetKeyframe).
#pragma once

#include <algorithm>
#include <cmath>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/io/calibration_io.h"
#include "core/slam/tracker.h"

namespace prism {
namespace internal {

// Grey = mean of the three channels, as float.
void ToGrey(const cv::Mat& rgb, cv::Mat* grey);

// 2x2 box average (drops an odd last row / column).
void Downsample(const cv::Mat& in, cv::Mat* out);

// J = 128 * I / (box_mean(I) + floor), in place (see TrackerOptions::normalize_shading).
void NormalizeShading(const TrackerOptions& options, cv::Mat* grey, cv::Mat* scratch);

// The rig's lights in float, for ShadingModel::kPredictedShading.
struct RigLights {
  bool point[3] = {true, true, true};
  Eigen::Vector3f position[3];   // point lights, camera frame
  Eigen::Vector3f direction[3];  // directional lights, unit, towards the light
  float intensity[3] = {0, 0, 0};
  float max_ratio = 4;
  float floor = 8;  // TrackerOptions::local_mean_floor

  explicit RigLights(const RigCalibration& rig, float max_shading_ratio) : max_ratio(max_shading_ratio) {
    for (int l = 0; l < 3; ++l) {
      point[l] = rig.lights[l].type == LightType::kPoint;
      position[l] = rig.lights[l].position_in_camera.cast<float>();
      direction[l] = rig.lights[l].direction_in_camera.normalized().cast<float>();
      intensity[l] = static_cast<float>(rig.lights[l].intensity);
    }
  }

  // Per-light Lambertian shading E_l max(0, n.L_l) of a point and unit normal in the camera frame.
  Eigen::Vector3f Shading(const Eigen::Vector3f& point, const Eigen::Vector3f& normal) const {
    Eigen::Vector3f s;
    for (int l = 0; l < 3; ++l) {
      if (point[l]) {
        const Eigen::Vector3f d = position[l] - point;
        const float d2 = d.squaredNorm();
        s[l] = intensity[l] / d2 * std::max(0.0f, normal.dot(d) / std::sqrt(d2));
      } else {
        s[l] = intensity[l] * std::max(0.0f, normal.dot(direction[l]));
      }
    }
    return s;
  }
};

}  // namespace internal
}  // namespace prism
