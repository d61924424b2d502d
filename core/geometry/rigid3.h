// Rigid and similarity transforms, named target_from_source (COLMAP's Rigid3d / Sim3d):
// `Rigid3d world_from_camera; Vector3d point_in_world = world_from_camera * point_in_camera;`
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace prism {

struct Rigid3d {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();

  Rigid3d() = default;
  Rigid3d(const Eigen::Quaterniond& r, const Eigen::Vector3d& t) : rotation(r.normalized()), translation(t) {}
  static Rigid3d FromMatrix(const Eigen::Matrix4d& m);

  Eigen::Matrix4d ToMatrix() const;
  Eigen::Matrix3d RotationMatrix() const { return rotation.toRotationMatrix(); }
  Rigid3d Inverse() const;
  Eigen::Vector3d operator*(const Eigen::Vector3d& p) const { return rotation * p + translation; }
  Rigid3d operator*(const Rigid3d& o) const {
    return Rigid3d(rotation * o.rotation, rotation * o.translation + translation);
  }
};

struct Sim3d {
  double scale = 1.0;
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();

  Sim3d() = default;
  Sim3d(double s, const Eigen::Quaterniond& r, const Eigen::Vector3d& t)
      : scale(s), rotation(r.normalized()), translation(t) {}

  Eigen::Matrix4d ToMatrix() const;
  Sim3d Inverse() const;
  Eigen::Vector3d operator*(const Eigen::Vector3d& p) const { return scale * (rotation * p) + translation; }
  Sim3d operator*(const Sim3d& o) const {
    return Sim3d(scale * o.scale, rotation * o.rotation, scale * (rotation * o.translation) + translation);
  }
  // Applies to a camera pose world_from_camera: rotation composes, the camera centre is mapped.
  Rigid3d TransformPose(const Rigid3d& pose) const {
    return Rigid3d(rotation * pose.rotation, (*this) * pose.translation);
  }
};

// The motion from keyframe a's camera to keyframe b's, given their Sim(3) poses world_from_a and
// world_from_b, in a's unit: a point X of a (in a's depth unit) is at R_b^T R_a X + R_b^T (c_a - c_b) / s_a
// in b's camera, still in a's unit.
Rigid3d BFromAInUnitsOfA(const Sim3d& world_from_a, const Sim3d& world_from_b);

// Angle of a rotation in radians, in [0, pi].
double RotationAngle(const Eigen::Quaterniond& q);

// Rotation of the rotation vector w (axis * angle in radians), the exponential map of SO(3).
Eigen::Quaterniond ExpSo3(const Eigen::Vector3d& w);

// Rotation whose z axis points from `eye` to `target`, with x roughly perpendicular to `up`
// (OpenCV camera: x right, y down, z forward). Returns world_from_camera.
Rigid3d LookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, const Eigen::Vector3d& up);

}  // namespace prism
