#include "core/geometry/point_cloud.h"

namespace prism {

bool PointCloud::IsConsistent() const {
  const size_t n = positions.size();
  return (normals.empty() || normals.size() == n) && (colors.empty() || colors.size() == n) &&
         (confidences.empty() || confidences.size() == n);
}

namespace {

PointCloud Transformed(const PointCloud& cloud, const Eigen::Matrix3f& scaled_rotation, const Eigen::Matrix3f& rotation,
                       const Eigen::Vector3f& translation) {
  PointCloud out = cloud;
  for (Eigen::Vector3f& p : out.positions) p = scaled_rotation * p + translation;
  for (Eigen::Vector3f& n : out.normals) n = rotation * n;
  return out;
}

}  // namespace

PointCloud TransformCloud(const PointCloud& cloud, const Rigid3d& target_from_source) {
  const Eigen::Matrix3f r = target_from_source.RotationMatrix().cast<float>();
  return Transformed(cloud, r, r, target_from_source.translation.cast<float>());
}

PointCloud TransformCloud(const PointCloud& cloud, const Sim3d& target_from_source) {
  const Eigen::Matrix3f r = target_from_source.rotation.toRotationMatrix().cast<float>();
  return Transformed(cloud, static_cast<float>(target_from_source.scale) * r, r,
                     target_from_source.translation.cast<float>());
}

}  // namespace prism
