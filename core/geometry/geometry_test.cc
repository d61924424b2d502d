#include <random>

#include <gtest/gtest.h>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"

namespace prism {
namespace {

TEST(Rigid3dTest, InverseAndCompositionAreConsistent) {
  std::mt19937 rng(7);
  std::normal_distribution<double> n(0, 1);
  const Rigid3d a(Eigen::Quaterniond(n(rng), n(rng), n(rng), n(rng)), Eigen::Vector3d(n(rng), n(rng), n(rng)));
  const Eigen::Vector3d p(0.3, -1.2, 2.0);
  EXPECT_LT(((a.Inverse() * a) * p - p).norm(), 1e-12);
  EXPECT_LT(((a.ToMatrix() * p.homogeneous()).head<3>() - a * p).norm(), 1e-12);
  EXPECT_LT((Rigid3d::FromMatrix(a.ToMatrix()) * p - a * p).norm(), 1e-12);
}

TEST(Sim3dTest, InverseAndPoseTransform) {
  const Sim3d s(2.5, Eigen::Quaterniond(Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized())),
                Eigen::Vector3d(1, -2, 0.5));
  const Eigen::Vector3d p(0.1, 0.2, 0.3);
  EXPECT_LT(((s.Inverse() * s) * p - p).norm(), 1e-12);
  EXPECT_LT(((s.ToMatrix() * p.homogeneous()).head<3>() - s * p).norm(), 1e-12);
  // A pose's camera centre maps like a point; its rotation composes.
  const Rigid3d pose(Eigen::Quaterniond(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitY())), p);
  const Rigid3d mapped = s.TransformPose(pose);
  EXPECT_LT((mapped.translation - s * p).norm(), 1e-12);
  EXPECT_NEAR(RotationAngle(mapped.rotation * (s.rotation * pose.rotation).conjugate()), 0, 1e-9);
}

TEST(LookAtTest, OpticalAxisPointsAtTarget) {
  const Eigen::Vector3d eye(1, 2, 3), target(0, 0, 0);
  const Rigid3d world_from_camera = LookAt(eye, target, Eigen::Vector3d::UnitZ());
  const Eigen::Vector3d target_in_camera = world_from_camera.Inverse() * target;
  EXPECT_NEAR(target_in_camera.x(), 0, 1e-12);
  EXPECT_NEAR(target_in_camera.y(), 0, 1e-12);
  EXPECT_NEAR(target_in_camera.z(), eye.norm(), 1e-12);
  // World up appears as image up (negative y) for a camera looking down at the target.
  EXPECT_LT((world_from_camera.rotation.conjugate() * Eigen::Vector3d::UnitZ()).y(), 0);
}

TEST(PinholeCameraTest, ProjectUnprojectRoundTripWithDistortion) {
  PinholeCamera cam = PinholeCamera::FromFov(640, 480, 60);
  cam.distortion = {-0.2, 0.05, 0.001, -0.002, 0.0};
  ASSERT_TRUE(cam.Check().ok());
  for (double u : {0.0, 100.5, 320.0, 639.0})
    for (double v : {0.0, 240.0, 479.0}) {
      const Eigen::Vector3d ray = cam.Unproject({u, v});
      const Eigen::Vector2d back = cam.Project(ray * 2.0);
      EXPECT_LT((back - Eigen::Vector2d(u, v)).norm(), 1e-6);
    }
}

TEST(PinholeCameraTest, CheckRejectsBadIntrinsics) {
  PinholeCamera cam = PinholeCamera::FromFov(640, 480, 60);
  cam.fx = -1;
  EXPECT_FALSE(cam.Check().ok());
  cam = PinholeCamera::FromFov(0, 480, 60);
  EXPECT_FALSE(cam.Check().ok());
}

}  // namespace
}  // namespace prism
