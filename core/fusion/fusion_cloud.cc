#include <cmath>
#include <sstream>
#include <string>

#include "core/fusion/fusion.h"
#include "core/fusion/fusion_internal.h"
#include "core/util/check.h"

namespace prism {

using internal::NormalPresent;
using internal::Rays;

cv::Mat DepthEdgeFreeMask(const cv::Mat& depth, double max_relative_step) {
  PRISM_CHECK(depth.type() == CV_32F) << "DepthEdgeFreeMask needs CV_32F depth";
  cv::Mat keep(depth.size(), CV_8U, cv::Scalar(0));
  const float t = static_cast<float>(max_relative_step);
  for (int y = 0; y < depth.rows; ++y)
    for (int x = 0; x < depth.cols; ++x) {
      const float z = depth.at<float>(y, x);
      if (!(z > 0)) continue;
      bool ok = true;
      for (int dy = -1; dy <= 1 && ok; ++dy)
        for (int dx = -1; dx <= 1 && ok; ++dx) {
          const int yy = y + dy, xx = x + dx;
          if (yy < 0 || xx < 0 || yy >= depth.rows || xx >= depth.cols) continue;
          const float zn = depth.at<float>(yy, xx);
          if (zn > 0 && std::abs(zn - z) > t * z) ok = false;
        }
      if (ok) keep.at<uint8_t>(y, x) = 255;
    }
  return keep;
}

StatusOr<PointCloud> DepthToCloud(const cv::Mat& depth, const cv::Mat& normals, const cv::Mat& rgb,
                                  const PinholeCamera& camera, const Sim3d& world_from_keyframe, int stride,
                                  const cv::Mat& mask, const cv::Mat& confidence) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (stride < 1) return InvalidArgumentError("DepthToCloud: stride = " + std::to_string(stride) + "; violated: >= 1");
  auto check = [&](const cv::Mat& m, const char* name, int type, bool may_be_empty) -> Status {
    if (m.empty() && may_be_empty) return Status::Ok();
    if (m.type() != type || m.cols != camera.width || m.rows != camera.height) {
      std::ostringstream e;
      e << "DepthToCloud: " << name << " is " << m.cols << "x" << m.rows << " of type " << m.type() << "; expected "
        << camera.width << "x" << camera.height << " of type " << type;
      return InvalidArgumentError(e.str());
    }
    return Status::Ok();
  };
  PRISM_RETURN_IF_ERROR(check(depth, "depth", CV_32F, false));
  PRISM_RETURN_IF_ERROR(check(normals, "normals", CV_32FC3, true));
  PRISM_RETURN_IF_ERROR(check(rgb, "rgb", CV_8UC3, true));
  PRISM_RETURN_IF_ERROR(check(mask, "mask", CV_8U, true));
  PRISM_RETURN_IF_ERROR(check(confidence, "confidence", CV_32F, true));
  if (!(world_from_keyframe.scale > 0) || !std::isfinite(world_from_keyframe.scale))
    return InvalidArgumentError("DepthToCloud: world_from_keyframe.scale must be finite and > 0");

  Rays rays;
  rays.Update(camera);
  const Eigen::Matrix3f rotation = world_from_keyframe.rotation.toRotationMatrix().cast<float>();
  const Eigen::Matrix3f scaled_rotation = static_cast<float>(world_from_keyframe.scale) * rotation;
  const Eigen::Vector3f translation = world_from_keyframe.translation.cast<float>();
  PointCloud cloud;
  for (int y = 0; y < depth.rows; y += stride)
    for (int x = 0; x < depth.cols; x += stride) {
      const size_t i = static_cast<size_t>(y) * depth.cols + x;
      const float z = depth.at<float>(y, x);
      if (!(z > 0) || !std::isfinite(z)) continue;
      if (!mask.empty() && mask.at<uint8_t>(y, x) == 0) continue;
      if (!normals.empty() && !NormalPresent(normals.at<cv::Vec3f>(y, x))) continue;
      const Eigen::Vector3f p(rays.x[i] * z, rays.y[i] * z, z);
      cloud.positions.push_back(scaled_rotation * p + translation);
      if (!normals.empty()) {
        const cv::Vec3f& nm = normals.at<cv::Vec3f>(y, x);
        cloud.normals.push_back((rotation * Eigen::Vector3f(nm[0], nm[1], nm[2])).normalized());
      }
      if (!rgb.empty()) {
        const cv::Vec3b& c = rgb.at<cv::Vec3b>(y, x);
        cloud.colors.emplace_back(c[0], c[1], c[2]);
      }
      cloud.confidences.push_back(confidence.empty() ? 1.f : confidence.at<float>(y, x));
    }
  return cloud;
}

StatusOr<InverseDepthMap> ProjectCloudToKeyframe(const PointCloud& cloud_in_world, const Sim3d& keyframe_from_world,
                                                 const PinholeCamera& camera, double default_variance) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (!cloud_in_world.IsConsistent()) return InvalidArgumentError("ProjectCloudToKeyframe: inconsistent cloud");
  if (!(default_variance > 0) || !std::isfinite(default_variance))
    return InvalidArgumentError("ProjectCloudToKeyframe: default_variance must be finite and > 0");
  InverseDepthMap out;
  out.inverse_depth = cv::Mat(camera.height, camera.width, CV_32F, cv::Scalar(0));
  out.variance = cv::Mat(camera.height, camera.width, CV_32F, cv::Scalar(0));
  for (size_t k = 0; k < cloud_in_world.size(); ++k) {
    const Eigen::Vector3d p = keyframe_from_world * cloud_in_world.positions[k].cast<double>();
    if (!(p.z() > 0) || !p.allFinite()) continue;
    const Eigen::Vector2d uv = camera.Project(p);
    if (!uv.allFinite()) continue;
    const long x = std::lround(uv.x()), y = std::lround(uv.y());
    if (x < 0 || y < 0 || x >= camera.width || y >= camera.height) continue;
    double variance = default_variance;
    if (cloud_in_world.HasConfidences()) {
      const float c = cloud_in_world.confidences[k];
      if (!(c > 0) || !std::isfinite(c)) continue;
      variance = 1.0 / c;
    }
    const float rho = static_cast<float>(1.0 / p.z());
    float& id = out.inverse_depth.at<float>(static_cast<int>(y), static_cast<int>(x));
    if (rho <= id) continue;  // keep the nearest point
    id = rho;
    out.variance.at<float>(static_cast<int>(y), static_cast<int>(x)) = static_cast<float>(variance);
  }
  return out;
}

}  // namespace prism
