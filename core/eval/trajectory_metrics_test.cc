#include "core/eval/trajectory_metrics.h"

#include <cmath>
#include <filesystem>
#include <random>

#include <gtest/gtest.h>

#include "core/io/trajectory_io.h"

namespace prism {
namespace {

const std::string kRefDir = std::string(PRISM_SHARED_DATA_DIR) + "/traj-eval-reference";

void PrintRef(const char* name, const TrajectoryEvalResult& r) {
  std::printf("%s: ate_rmse=%.6f pairs=%zu scale=%.6f rpe_trans=%.6f rpe_rot=%.6f rpe_pairs=%zu\n", name,
              r.ate.error_m.rmse, r.ate.pairs, r.ate.gt_from_est.scale, r.rpe.trans_error_m.rmse,
              r.rpe.rot_error_deg.rmse, r.rpe.pairs);
}

TEST(TrajectoryReference, Fr1XyzRgbdslam) {
  if (!std::filesystem::is_directory(kRefDir)) GTEST_SKIP() << "reference data not found at " << kRefDir;
  auto gt = ReadTrajectoryAutoDetect(kRefDir + "/freiburg1_xyz-groundtruth.txt");
  auto est = ReadTrajectoryAutoDetect(kRefDir + "/freiburg1_xyz-rgbdslam.txt");
  ASSERT_TRUE(gt.ok() && est.ok());
  TrajectoryEvalOptions o;
  auto r = EvaluateTrajectory(*gt, *est, o);
  ASSERT_TRUE(r.ok()) << r.status();
  PrintRef("fr1 rgbdslam se3", *r);
  o.alignment = AlignmentModel::kNone;
  o.max_time_difference_s = 0.01;
  r = EvaluateTrajectory(*gt, *est, o);
  PrintRef("fr1 rgbdslam none 0.01", *r);
  o.rpe_delta_unit = RpeDeltaUnit::kSeconds;
  o.max_time_difference_s = 0.02;
  r = EvaluateTrajectory(*gt, *est, o);
  PrintRef("fr1 rgbdslam 1s", *r);
}

TEST(TrajectoryReference, Fr1XyzOrb) {
  if (!std::filesystem::is_directory(kRefDir)) GTEST_SKIP() << "reference data not found at " << kRefDir;
  auto gt = ReadTrajectoryAutoDetect(kRefDir + "/freiburg1_xyz-groundtruth.txt");
  auto est = ReadTrajectoryAutoDetect(kRefDir + "/freiburg1_xyz-ORB_kf_mono.txt");
  ASSERT_TRUE(gt.ok() && est.ok());
  TrajectoryEvalOptions o;
  o.alignment = AlignmentModel::kSim3;
  o.max_time_difference_s = 0.01;
  auto r = EvaluateTrajectory(*gt, *est, o);
  ASSERT_TRUE(r.ok()) << r.status();
  PrintRef("fr1 orb sim3", *r);
}

TEST(TrajectoryReference, Kitti) {
  if (!std::filesystem::is_directory(kRefDir)) GTEST_SKIP() << "reference data not found at " << kRefDir;
  auto gt = ReadTrajectoryAutoDetect(kRefDir + "/KITTI_00_gt.txt");
  auto est = ReadTrajectoryAutoDetect(kRefDir + "/KITTI_00_ORB.txt");
  ASSERT_TRUE(gt.ok() && est.ok());
  TrajectoryEvalOptions o;
  o.alignment = AlignmentModel::kSim3;
  auto r = EvaluateTrajectory(*gt, *est, o);
  ASSERT_TRUE(r.ok()) << r.status();
  PrintRef("kitti sim3", *r);
  o.alignment = AlignmentModel::kSe3;
  r = EvaluateTrajectory(*gt, *est, o);
  PrintRef("kitti se3", *r);
}

}  // namespace
}  // namespace prism
