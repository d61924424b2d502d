#include "core/eval/trajectory_metrics.h"

#include <cmath>
#include <filesystem>
#include <random>

#include <gtest/gtest.h>

#include "core/io/trajectory_io.h"

namespace prism {
namespace {

// ---------------------------------------------------------------------------------------------------
// Against the public tools, on real data (README.md of the data set lists how the values were made).

const std::string kReferenceDir = std::string(PRISM_SHARED_DATA_DIR) + "/traj-eval-reference";
// The reference values are printed with 6 decimals (4 for degrees).
constexpr double kReferenceTolerance = 1e-4;

class TrajectoryReferenceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!std::filesystem::is_directory(kReferenceDir))
      GTEST_SKIP() << "reference trajectories not found at " << kReferenceDir
                   << " (set PRISM_SHARED_DATA_DIR to the shared data directory)";
  }
  static Trajectory Read(const std::string& name) {
    auto t = ReadTrajectoryAutoDetect(kReferenceDir + "/" + name);
    PRISM_CHECK(t.ok()) << t.status();
    return *t;
  }
};

TEST_F(TrajectoryReferenceTest, Fr1XyzRgbdslamMatchesTumScripts) {
  const Trajectory gt = Read("freiburg1_xyz-groundtruth.txt");
  const Trajectory est = Read("freiburg1_xyz-rgbdslam.txt");
  TrajectoryEvalOptions options;  // SE(3), 0.02 s, delta 1 frame: the TUM scripts' settings
  const auto result = EvaluateTrajectory(gt, est, options);
  ASSERT_TRUE(result.ok()) << result.status();
  // evaluate_ate.py: 0.013473 m over 786 pairs.
  EXPECT_EQ(result->ate.pairs, 786u);
  EXPECT_NEAR(result->ate.error_m.rmse, 0.013473, kReferenceTolerance);
  EXPECT_EQ(result->ate.gt_from_est.scale, 1.0);
  // evaluate_rpe.py --fixed_delta --delta 1 --delta_unit f: 0.005763 m, 0.3530 deg.
  EXPECT_NEAR(result->rpe.trans_error_m.rmse, 0.005763, kReferenceTolerance);
  EXPECT_NEAR(result->rpe.rot_error_deg.rmse, 0.3530, kReferenceTolerance);
}

TEST_F(TrajectoryReferenceTest, Fr1XyzRgbdslamOneSecondRpeAndUnaligned) {
  const Trajectory gt = Read("freiburg1_xyz-groundtruth.txt");
  const Trajectory est = Read("freiburg1_xyz-rgbdslam.txt");
  TrajectoryEvalOptions options;
  options.rpe_delta_unit = RpeDeltaUnit::kSeconds;
  const auto rpe = ComputeRpe(gt, est, options);
  ASSERT_TRUE(rpe.ok()) << rpe.status();
  // evaluate_rpe.py --fixed_delta --delta 1 --delta_unit s: 753 pairs, 0.021217 m, 0.934480 deg.
  EXPECT_EQ(rpe->pairs, 753u);
  EXPECT_NEAR(rpe->trans_error_m.rmse, 0.021217, kReferenceTolerance);
  EXPECT_NEAR(rpe->rot_error_deg.rmse, 0.934480, kReferenceTolerance);

  // evo_ape without alignment (max difference 0.01 s): 0.020079 m.
  options.alignment = AlignmentModel::kNone;
  options.max_time_difference_s = 0.01;
  const auto ate = ComputeAte(gt, est, options);
  ASSERT_TRUE(ate.ok()) << ate.status();
  EXPECT_NEAR(ate->error_m.rmse, 0.020079, kReferenceTolerance);
}

TEST_F(TrajectoryReferenceTest, Fr1XyzOrbMonoSim3MatchesEvo) {
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kSim3;
  options.max_time_difference_s = 0.01;  // evo's default
  const auto ate = ComputeAte(Read("freiburg1_xyz-groundtruth.txt"), Read("freiburg1_xyz-ORB_kf_mono.txt"), options);
  ASSERT_TRUE(ate.ok()) << ate.status();
  EXPECT_NEAR(ate->error_m.rmse, 0.009755, kReferenceTolerance);
}

TEST_F(TrajectoryReferenceTest, Kitti00OrbMatchesEvo) {
  // KITTI files without times carry index stamps, so poses associate by index as evo's kitti mode does.
  const Trajectory gt = Read("KITTI_00_gt.txt");
  const Trajectory est = Read("KITTI_00_ORB.txt");
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kSim3;
  auto ate = ComputeAte(gt, est, options);
  ASSERT_TRUE(ate.ok()) << ate.status();
  EXPECT_EQ(ate->pairs, gt.size());
  EXPECT_NEAR(ate->error_m.rmse, 0.937709, kReferenceTolerance);
  options.alignment = AlignmentModel::kSe3;
  ate = ComputeAte(gt, est, options);
  ASSERT_TRUE(ate.ok()) << ate.status();
  EXPECT_NEAR(ate->error_m.rmse, 1.303450, kReferenceTolerance);
}

// ---------------------------------------------------------------------------------------------------
// Synthetic truth.

class TrajectoryMetricsTest : public ::testing::Test {
 protected:
  void SetUp() override { rng_.seed(11); }

  // A smooth random walk at 30 Hz.
  Trajectory RandomTrajectory(int n) {
    std::normal_distribution<double> normal(0.0, 1.0);
    Trajectory traj;
    Rigid3d pose;
    Eigen::Vector3d velocity(0.05, 0.0, 0.0);
    for (int i = 0; i < n; ++i) {
      traj.push_back({100.0 + i / 30.0, pose});
      velocity += 0.01 * Eigen::Vector3d(normal(rng_), normal(rng_), normal(rng_));
      const Eigen::Quaterniond turn(
          Eigen::AngleAxisd(0.02, Eigen::Vector3d(normal(rng_), normal(rng_), normal(rng_)).normalized()));
      pose = Rigid3d(pose.rotation * turn, pose.translation + velocity);
    }
    return traj;
  }

  std::mt19937 rng_;
};

TEST_F(TrajectoryMetricsTest, IdenticalTrajectoriesGiveZeroError) {
  const Trajectory traj = RandomTrajectory(200);
  for (AlignmentModel alignment : {AlignmentModel::kNone, AlignmentModel::kSe3, AlignmentModel::kSim3}) {
    TrajectoryEvalOptions options;
    options.alignment = alignment;
    const auto result = EvaluateTrajectory(traj, traj, options);
    ASSERT_TRUE(result.ok()) << result.status();
    EXPECT_EQ(result->ate.pairs, traj.size());
    // Exactly zero without alignment, and for the RPE whenever the scale is exactly 1; the SVD of an
    // alignment leaves rounding.
    constexpr double kRounding = 1e-12;
    if (alignment == AlignmentModel::kNone) {
      EXPECT_EQ(result->ate.error_m.max, 0.0);
    }
    if (alignment != AlignmentModel::kSim3) {
      EXPECT_EQ(result->rpe.trans_error_m.max, 0.0);
      EXPECT_EQ(result->rpe.rot_error_deg.max, 0.0);
    }
    EXPECT_LE(result->ate.error_m.max, kRounding);
    EXPECT_LE(result->rpe.trans_error_m.max, kRounding);
    EXPECT_LE(result->rpe.rot_error_deg.max, kRounding);
    EXPECT_EQ(result->rpe.pairs, traj.size() - 2);  // j = last index is dropped, as in evaluate_rpe.py
  }
}

TEST_F(TrajectoryMetricsTest, Sim3OfTrajectoryIsRecovered) {
  constexpr double kMaxParameterError = 1e-9;
  const Trajectory gt = RandomTrajectory(300);
  const Sim3d est_from_gt(0.37,
                          Eigen::Quaterniond(Eigen::AngleAxisd(1.1, Eigen::Vector3d(0.2, -0.5, 0.8).normalized())),
                          Eigen::Vector3d(3.0, -2.0, 0.5));
  Trajectory est;
  for (const TimedPose& p : gt) est.push_back({p.timestamp_s, est_from_gt.TransformPose(p.world_from_camera)});
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kSim3;
  const auto result = EvaluateTrajectory(gt, est, options);
  ASSERT_TRUE(result.ok()) << result.status();
  const Sim3d gt_from_est = est_from_gt.Inverse();
  EXPECT_NEAR(result->ate.gt_from_est.scale, gt_from_est.scale, kMaxParameterError);
  EXPECT_LT(RotationAngle(result->ate.gt_from_est.rotation * gt_from_est.rotation.conjugate()), kMaxParameterError);
  EXPECT_LT((result->ate.gt_from_est.translation - gt_from_est.translation).norm(), kMaxParameterError);
  EXPECT_LT(result->ate.error_m.max, /*max_ate_m=*/1e-9);
  // The RPE uses the recovered scale, so the relative motions match too.
  EXPECT_LT(result->rpe.trans_error_m.max, /*max_rpe_m=*/1e-9);
  EXPECT_LT(result->rpe.rot_error_deg.max, /*max_rpe_deg=*/1e-9);
}

TEST_F(TrajectoryMetricsTest, OrientationErrorIsTheTurnLeftAfterTheAlignment) {
  constexpr double kRoundingDeg = 1e-7;
  const Trajectory gt = RandomTrajectory(200);
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kSim3;
  // A similarity of the truth: nothing left.
  const Sim3d est_from_gt(2.5, Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, -1).normalized())),
                          Eigen::Vector3d(0.3, 1.0, -2.0));
  Trajectory similar;
  for (const TimedPose& p : gt) similar.push_back({p.timestamp_s, est_from_gt.TransformPose(p.world_from_camera)});
  auto result = ComputeAte(gt, similar, options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_LT(result->orientation_error_deg.max, kRoundingDeg);
  EXPECT_GT(result->net_rotation_deg_gt, 1.0);
  EXPECT_NEAR(result->net_rotation_deg_est, result->net_rotation_deg_gt, kRoundingDeg);
  // The same positions, every camera turned by 2 degrees about its own axis: the ATE cannot see it.
  constexpr double kTurnDeg = 2.0;
  Trajectory turned = gt;
  for (TimedPose& p : turned)
    p.world_from_camera.rotation = p.world_from_camera.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(
                                                                      kTurnDeg * M_PI / 180, Eigen::Vector3d::UnitZ()));
  result = ComputeAte(gt, turned, options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_LT(result->error_m.max, 1e-9);
  EXPECT_NEAR(result->orientation_error_deg.min, kTurnDeg, kRoundingDeg);
  EXPECT_NEAR(result->orientation_error_deg.max, kTurnDeg, kRoundingDeg);
}

TEST_F(TrajectoryMetricsTest, AnOrbitRotatedTooLittleShowsInTheNetRotation) {
  // 120 degrees around a point, looking at it; the estimate has the positions but turns 0.9 as far.
  constexpr double kArcDeg = 120.0, kRotationRatio = 0.9, kRoundingDeg = 1e-7;
  const Eigen::Quaterniond look(Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitX()));
  Trajectory gt, est;
  for (int i = 0; i <= 120; ++i) {
    const double a = kArcDeg * M_PI / 180 * i / 120;
    const Eigen::Vector3d centre(std::cos(a), std::sin(a), 0.3);
    const Eigen::Quaterniond yaw(Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()));
    const Eigen::Quaterniond yaw_est(Eigen::AngleAxisd(kRotationRatio * a, Eigen::Vector3d::UnitZ()));
    gt.push_back({10.0 + i / 30.0, Rigid3d(yaw * look, centre)});
    est.push_back({10.0 + i / 30.0, Rigid3d(yaw_est * look, centre)});
  }
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kSim3;
  const auto result = ComputeAte(gt, est, options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_LT(result->error_m.max, 1e-9);
  EXPECT_NEAR(result->net_rotation_deg_gt, kArcDeg, kRoundingDeg);
  EXPECT_NEAR(result->net_rotation_deg_est, kRotationRatio * kArcDeg, kRoundingDeg);
  EXPECT_NEAR(result->orientation_error_deg.max, (1 - kRotationRatio) * kArcDeg, kRoundingDeg);
}

TEST_F(TrajectoryMetricsTest, ConstantOffsetShowsUpWithoutAlignmentOnly) {
  const Trajectory gt = RandomTrajectory(100);
  const Eigen::Vector3d offset(0.006, 0.0, 0.008);  // 1 cm
  Trajectory est = gt;
  for (TimedPose& p : est) p.world_from_camera.translation += offset;
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kNone;
  auto result = EvaluateTrajectory(gt, est, options);
  ASSERT_TRUE(result.ok()) << result.status();
  constexpr double kRoundingTolerance = 1e-12;
  EXPECT_NEAR(result->ate.error_m.rmse, 0.01, kRoundingTolerance);
  EXPECT_NEAR(result->ate.error_m.min, 0.01, kRoundingTolerance);
  EXPECT_NEAR(result->ate.error_m.max, 0.01, kRoundingTolerance);
  // A world-frame offset cancels in relative motions.
  EXPECT_LT(result->rpe.trans_error_m.max, kRoundingTolerance);
  // SE(3) alignment removes it.
  options.alignment = AlignmentModel::kSe3;
  result = EvaluateTrajectory(gt, est, options);
  ASSERT_TRUE(result.ok());
  EXPECT_LT(result->ate.error_m.max, kRoundingTolerance);
}

TEST_F(TrajectoryMetricsTest, KnownRelativeErrors) {
  // Ground truth moves 10 cm per frame along x without turning; the estimate moves 11 cm and turns 1
  // degree about z per frame. Every 1-frame relative error is then 1 cm and 1 degree.
  Trajectory gt, est;
  for (int i = 0; i < 50; ++i) {
    const double t = 10.0 + 0.1 * i;
    gt.push_back({t, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.10 * i, 0, 0))});
    Rigid3d e = i == 0 ? Rigid3d()
                       : est.back().world_from_camera *
                             Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 180.0, Eigen::Vector3d::UnitZ())),
                                     Eigen::Vector3d(0.11, 0, 0));
    est.push_back({t, e});
  }
  // The estimate's step in its own frame is 11 cm forward; the error relates it to the ground truth.
  TrajectoryEvalOptions options;
  options.alignment = AlignmentModel::kNone;
  const auto rpe = ComputeRpe(gt, est, options);
  ASSERT_TRUE(rpe.ok()) << rpe.status();
  EXPECT_EQ(rpe->pairs, 48u);
  constexpr double kTolerance = 1e-9;
  // error = inv(inv(E_j) E_i) inv(G_j) G_i = (step_est) * (step_gt)^-1: translation 0.11 - R * 0.10
  // rotated... with R = 1 degree about z: |(0.11, 0) - R (0.10, 0)|.
  const double c = std::cos(M_PI / 180.0), s = std::sin(M_PI / 180.0);
  const double expected = std::hypot(0.11 - 0.10 * c, 0.10 * s);
  EXPECT_NEAR(rpe->trans_error_m.rmse, expected, kTolerance);
  EXPECT_NEAR(rpe->trans_error_m.min, expected, kTolerance);
  EXPECT_NEAR(rpe->rot_error_deg.rmse, 1.0, 1e-6);

  // Two-frame delta: 22 cm against 20 cm with a 2 degree turn inside.
  options.rpe_delta = 2;
  const auto rpe2 = ComputeRpe(gt, est, options);
  ASSERT_TRUE(rpe2.ok());
  EXPECT_EQ(rpe2->pairs, 47u);
  EXPECT_NEAR(rpe2->rot_error_deg.rmse, 2.0, 1e-6);
}

TEST_F(TrajectoryMetricsTest, RpeSkipsPairsWithoutNearbyGroundTruth) {
  // Ground truth at 100 Hz with a 1 s hole; the estimate at 10 Hz across it.
  Trajectory gt, est;
  for (int i = 0; i < 500; ++i) {
    if (i >= 200 && i < 300) continue;
    const double t = i * 0.01;
    gt.push_back({t, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(t, 0, 0))});
  }
  for (int k = 0; k < 50; ++k) {
    const double t = k * 0.1 + 0.05;
    est.push_back({t, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(t, 0, 0))});
  }
  TrajectoryEvalOptions options;
  const auto rpe = ComputeRpe(gt, est, options);
  ASSERT_TRUE(rpe.ok()) << rpe.status();
  // 48 candidate pairs (k, k+1), k < 48. Estimate stamps 2.05 .. 2.95 (k = 20 .. 29) have no ground truth
  // within 2 x 0.01 s, so the pairs touching them (k = 19 .. 29, 11 pairs) are skipped.
  EXPECT_EQ(rpe->pairs, 48u - 11u);
  EXPECT_LT(rpe->trans_error_m.max, 1e-12);
}

TEST_F(TrajectoryMetricsTest, RpeInSecondsPicksTheClosestStamp) {
  Trajectory traj = RandomTrajectory(90);  // 3 s at 30 Hz
  TrajectoryEvalOptions options;
  options.rpe_delta_unit = RpeDeltaUnit::kSeconds;
  options.rpe_delta = 1.0;
  const auto rpe = ComputeRpe(traj, traj, options);
  ASSERT_TRUE(rpe.ok()) << rpe.status();
  // j = i + 30 while that exists and is not the last index (89): i in [0, 58].
  EXPECT_EQ(rpe->pairs, 59u);
}

TEST_F(TrajectoryMetricsTest, OrderAndDuplicatesDoNotMatter) {
  const Trajectory gt = RandomTrajectory(60);
  Trajectory est = gt;
  std::reverse(est.begin(), est.end());
  est.push_back(est.front());  // a repeated stamp keeps its last pose: identical here
  const auto result = EvaluateTrajectory(gt, est, TrajectoryEvalOptions());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->ate.pairs, gt.size());
  EXPECT_LT(result->ate.error_m.max, 1e-12);
}

TEST(AssociateTimestampsTest, GreedyByDifferenceLikeAssociatePy) {
  // 1.00 is closest to 1.005 (0.005) but 1.005 is taken first by 1.004 (0.001): 1.00 then pairs with 0.99.
  const std::vector<double> first = {1.004, 1.00, 5.0};
  const std::vector<double> second = {0.99, 1.005, 3.0};
  const auto matches = AssociateTimestamps(first, second, 0.02);
  ASSERT_EQ(matches.size(), 2u);
  // Sorted by first stamp: 1.00 <-> 0.99, then 1.004 <-> 1.005.
  EXPECT_EQ(matches[0].first, 1u);
  EXPECT_EQ(matches[0].second, 0u);
  EXPECT_EQ(matches[1].first, 0u);
  EXPECT_EQ(matches[1].second, 1u);
}

TEST(AssociateTimestampsTest, MaxDifferenceIsExclusiveAndOffsetApplies) {
  EXPECT_TRUE(AssociateTimestamps({1.0}, {1.5}, 0.5).empty());
  EXPECT_EQ(AssociateTimestamps({1.0}, {1.25}, 0.5).size(), 1u);
  // The offset is added to the second stamps.
  EXPECT_EQ(AssociateTimestamps({11.0}, {1.0}, 0.02, /*second_offset_s=*/10.0).size(), 1u);
  EXPECT_TRUE(AssociateTimestamps({11.0}, {1.0}, 0.02).empty());
  EXPECT_TRUE(AssociateTimestamps({}, {1.0}, 0.02).empty());
}

TEST(TrajectoryEvalOptionsTest, CheckRejectsBadValues) {
  EXPECT_TRUE(TrajectoryEvalOptions().Check().ok());
  TrajectoryEvalOptions o;
  o.max_time_difference_s = 0.0;
  EXPECT_FALSE(o.Check().ok());
  o = TrajectoryEvalOptions();
  o.rpe_delta = -1.0;
  EXPECT_FALSE(o.Check().ok());
  o.rpe_delta = std::nan("");
  EXPECT_FALSE(o.Check().ok());
  EXPECT_FALSE(ParseRpeDeltaUnit("m").ok());
  EXPECT_EQ(*ParseRpeDeltaUnit("s"), RpeDeltaUnit::kSeconds);
}

TEST(TrajectoryEvalErrorsTest, TooFewPairsIsAnError) {
  Trajectory gt = {{0.0, Rigid3d()}, {1.0, Rigid3d()}};
  Trajectory est = {{5.0, Rigid3d()}, {6.0, Rigid3d()}};
  EXPECT_EQ(ComputeAte(gt, est, TrajectoryEvalOptions()).status().code(), StatusCode::kFailedPrecondition);
  EXPECT_EQ(ComputeAte(gt, {}, TrajectoryEvalOptions()).status().code(), StatusCode::kInvalidArgument);
  EXPECT_FALSE(ComputeRpe(gt, est, TrajectoryEvalOptions()).ok());
}

TEST(ErrorStatisticsTest, NumpyConventions) {
  const ErrorStatistics odd = ComputeErrorStatistics({3.0, 1.0, 2.0});
  EXPECT_EQ(odd.median, 2.0);
  EXPECT_DOUBLE_EQ(odd.rmse, std::sqrt(14.0 / 3.0));
  EXPECT_DOUBLE_EQ(odd.std_dev, std::sqrt(2.0 / 3.0));  // population std
  const ErrorStatistics even = ComputeErrorStatistics({4.0, 1.0, 3.0, 2.0});
  EXPECT_EQ(even.median, 2.5);
  EXPECT_EQ(even.min, 1.0);
  EXPECT_EQ(even.max, 4.0);
  EXPECT_EQ(ComputeErrorStatistics({}).count, 0u);
}

}  // namespace
}  // namespace prism
