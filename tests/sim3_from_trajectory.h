// The Sim(3) that maps an estimated trajectory onto the ground truth, as roundtrip_test aligns it:
// rotation from the camera orientations (a near-straight path leaves a positions-only alignment free
// to turn about it), then scale and translation from the camera centres. For suites that score a
// streamed map in the ground-truth frame.
#pragma once

#include <cmath>
#include <vector>

#include <Eigen/SVD>

#include "core/geometry/rigid3.h"
#include "core/io/trajectory_io.h"

namespace prism::test {

struct TrajectoryAlignment {
  bool ok = false;
  Sim3d gt_from_est;
  size_t pairs = 0;
  double ate_rmse_m = 0, path_m = 0;
};

// Poses are paired by timestamp (within 1 ms).
inline TrajectoryAlignment AlignTrajectory(const Trajectory& est, const Trajectory& gt) {
  TrajectoryAlignment a;
  std::vector<Eigen::Vector3d> source, target;
  Eigen::Matrix3d rotation_sum = Eigen::Matrix3d::Zero();
  for (const TimedPose& p : est)
    for (const TimedPose& g : gt)
      if (std::abs(g.timestamp_s - p.timestamp_s) < 1e-3) {
        source.push_back(p.world_from_camera.translation);
        target.push_back(g.world_from_camera.translation);
        rotation_sum += g.world_from_camera.RotationMatrix() * p.world_from_camera.RotationMatrix().transpose();
        break;
      }
  a.pairs = source.size();
  if (source.size() < 3) return a;
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(rotation_sum, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  if ((svd.matrixU() * svd.matrixV().transpose()).determinant() < 0) d(2, 2) = -1;
  const Eigen::Matrix3d rotation = svd.matrixU() * d * svd.matrixV().transpose();
  Eigen::Vector3d mean_source = Eigen::Vector3d::Zero(), mean_target = Eigen::Vector3d::Zero();
  for (size_t i = 0; i < source.size(); ++i) {
    mean_source += source[i] / source.size();
    mean_target += target[i] / source.size();
  }
  double num = 0, den = 0;
  for (size_t i = 0; i < source.size(); ++i) {
    num += (rotation * (source[i] - mean_source)).dot(target[i] - mean_target);
    den += (source[i] - mean_source).squaredNorm();
  }
  if (!(den > 0) || !(num > 0)) return a;
  const double scale = num / den;
  a.gt_from_est = Sim3d(scale, Eigen::Quaterniond(rotation), mean_target - scale * (rotation * mean_source));
  double sq = 0;
  for (size_t i = 0; i < source.size(); ++i) {
    sq += (a.gt_from_est * source[i] - target[i]).squaredNorm();
    if (i) a.path_m += (target[i] - target[i - 1]).norm();
  }
  a.ate_rmse_m = std::sqrt(sq / source.size());
  a.ok = true;
  return a;
}

}  // namespace prism::test
