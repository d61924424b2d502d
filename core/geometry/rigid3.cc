#include "core/geometry/rigid3.h"

#include <algorithm>
#include <cmath>

namespace prism {

Rigid3d Rigid3d::FromMatrix(const Eigen::Matrix4d& m) {
  Eigen::Matrix3d r = m.block<3, 3>(0, 0);
  // Re-orthonormalise (file formats carry a few digits only).
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(r, Eigen::ComputeFullU | Eigen::ComputeFullV);
  r = svd.matrixU() * svd.matrixV().transpose();
  return Rigid3d(Eigen::Quaterniond(r), m.block<3, 1>(0, 3));
}

Eigen::Matrix4d Rigid3d::ToMatrix() const {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.block<3, 3>(0, 0) = rotation.toRotationMatrix();
  m.block<3, 1>(0, 3) = translation;
  return m;
}

Rigid3d Rigid3d::Inverse() const {
  const Eigen::Quaterniond inv = rotation.conjugate();
  return Rigid3d(inv, -(inv * translation));
}

Eigen::Matrix4d Sim3d::ToMatrix() const {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.block<3, 3>(0, 0) = scale * rotation.toRotationMatrix();
  m.block<3, 1>(0, 3) = translation;
  return m;
}

Sim3d Sim3d::Inverse() const {
  const Eigen::Quaterniond inv = rotation.conjugate();
  return Sim3d(1.0 / scale, inv, -(inv * translation) / scale);
}

Eigen::Quaterniond ExpSo3(const Eigen::Vector3d& w) {
  const double angle = w.norm();
  if (angle < 1e-12) return Eigen::Quaterniond(1, 0.5 * w.x(), 0.5 * w.y(), 0.5 * w.z()).normalized();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, w / angle));
}

Rigid3d BFromAInUnitsOfA(const Sim3d& world_from_a, const Sim3d& world_from_b) {
  const Eigen::Matrix3d rb_t = world_from_b.rotation.toRotationMatrix().transpose();
  return Rigid3d(Eigen::Quaterniond(rb_t * world_from_a.rotation.toRotationMatrix()),
                 rb_t * (world_from_a.translation - world_from_b.translation) / world_from_a.scale);
}

double RotationAngle(const Eigen::Quaterniond& q) {
  const Eigen::Quaterniond n = q.normalized();
  const double v = n.vec().norm();
  return 2.0 * std::atan2(v, std::abs(n.w()));
}

Rigid3d LookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, const Eigen::Vector3d& up) {
  const Eigen::Vector3d z = (target - eye).normalized();
  Eigen::Vector3d x = z.cross(up);
  if (x.norm() < 1e-9) x = z.unitOrthogonal();
  x.normalize();
  const Eigen::Vector3d y = z.cross(x);
  Eigen::Matrix3d r;
  r.col(0) = x;
  r.col(1) = y;
  r.col(2) = z;
  return Rigid3d(Eigen::Quaterniond(r), eye);
}

}  // namespace prism
