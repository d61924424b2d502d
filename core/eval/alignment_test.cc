#include "core/eval/alignment.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace prism {
namespace {

class AlignmentTest : public ::testing::Test {
 protected:
  void SetUp() override { rng_.seed(7); }

  std::vector<Eigen::Vector3d> RandomPoints(int n, double spread) {
    std::normal_distribution<double> normal(0.0, spread);
    std::vector<Eigen::Vector3d> points(static_cast<size_t>(n));
    for (auto& p : points) p = Eigen::Vector3d(normal(rng_), normal(rng_), normal(rng_));
    return points;
  }
  Sim3d RandomSim3() {
    std::normal_distribution<double> normal(0.0, 1.0);
    std::uniform_real_distribution<double> log_scale(std::log(0.1), std::log(10.0));
    return Sim3d(std::exp(log_scale(rng_)), Eigen::Quaterniond(normal(rng_), normal(rng_), normal(rng_), normal(rng_)),
                 Eigen::Vector3d(normal(rng_), normal(rng_), normal(rng_)) * 5.0);
  }
  static std::vector<Eigen::Vector3d> Apply(const Sim3d& t, const std::vector<Eigen::Vector3d>& points) {
    std::vector<Eigen::Vector3d> out;
    for (const auto& p : points) out.push_back(t * p);
    return out;
  }

  std::mt19937 rng_;
};

TEST_F(AlignmentTest, RecoversRandomSim3) {
  constexpr double kMaxParameterError = 1e-9;
  for (int trial = 0; trial < 20; ++trial) {
    const std::vector<Eigen::Vector3d> source = RandomPoints(50, 2.0);
    const Sim3d truth = RandomSim3();
    const auto estimate = UmeyamaAlignment(source, Apply(truth, source), /*estimate_scale=*/true);
    ASSERT_TRUE(estimate.ok()) << estimate.status();
    EXPECT_NEAR(estimate->scale, truth.scale, kMaxParameterError);
    EXPECT_LT(RotationAngle(estimate->rotation * truth.rotation.conjugate()), kMaxParameterError);
    EXPECT_LT((estimate->translation - truth.translation).norm(), kMaxParameterError);
  }
}

TEST_F(AlignmentTest, Se3KeepsUnitScaleAndRecoversRigidMotion) {
  constexpr double kMaxParameterError = 1e-9;
  const std::vector<Eigen::Vector3d> source = RandomPoints(30, 1.0);
  Sim3d truth = RandomSim3();
  truth.scale = 1.0;
  const auto estimate = AlignPoints(source, Apply(truth, source), AlignmentModel::kSe3);
  ASSERT_TRUE(estimate.ok()) << estimate.status();
  EXPECT_EQ(estimate->scale, 1.0);
  EXPECT_LT(RotationAngle(estimate->rotation * truth.rotation.conjugate()), kMaxParameterError);
  EXPECT_LT((estimate->translation - truth.translation).norm(), kMaxParameterError);

  // With a true scale of 2, SE(3) still returns scale 1 while Sim(3) finds 2.
  truth.scale = 2.0;
  const auto se3 = AlignPoints(source, Apply(truth, source), AlignmentModel::kSe3);
  const auto sim3 = AlignPoints(source, Apply(truth, source), AlignmentModel::kSim3);
  ASSERT_TRUE(se3.ok() && sim3.ok());
  EXPECT_EQ(se3->scale, 1.0);
  EXPECT_NEAR(sim3->scale, 2.0, kMaxParameterError);
}

TEST_F(AlignmentTest, PlanarPointsGiveARotationNotAReflection) {
  // Coplanar points make the cross-covariance rank 2, where a naive SVD solution may be a reflection.
  std::vector<Eigen::Vector3d> source = RandomPoints(20, 1.0);
  for (auto& p : source) p.z() = 0.0;
  const Sim3d truth(1.5, Eigen::Quaterniond(Eigen::AngleAxisd(2.0, Eigen::Vector3d(1, 2, 3).normalized())),
                    Eigen::Vector3d(0.3, -1.0, 2.0));
  const auto estimate = UmeyamaAlignment(source, Apply(truth, source), true);
  ASSERT_TRUE(estimate.ok()) << estimate.status();
  EXPECT_GT(estimate->rotation.toRotationMatrix().determinant(), 0.0);
  EXPECT_LT(RotationAngle(estimate->rotation * truth.rotation.conjugate()), /*max_rotation_error_rad=*/1e-9);
}

TEST_F(AlignmentTest, NoneIsIdentity) {
  const std::vector<Eigen::Vector3d> source = RandomPoints(2, 1.0);
  const auto estimate = AlignPoints(source, RandomPoints(2, 1.0), AlignmentModel::kNone);
  ASSERT_TRUE(estimate.ok()) << estimate.status();
  EXPECT_EQ(estimate->scale, 1.0);
  EXPECT_EQ(estimate->translation, Eigen::Vector3d::Zero());
  EXPECT_EQ(estimate->rotation.coeffs(), Eigen::Quaterniond::Identity().coeffs());
}

TEST_F(AlignmentTest, DegenerateInputIsAnError) {
  const std::vector<Eigen::Vector3d> two = RandomPoints(2, 1.0);
  EXPECT_EQ(UmeyamaAlignment(two, two, false).status().code(), StatusCode::kInvalidArgument);
  const std::vector<Eigen::Vector3d> coincident(10, Eigen::Vector3d(1.0, 2.0, 3.0));
  const std::vector<Eigen::Vector3d> spread = RandomPoints(10, 1.0);
  EXPECT_EQ(UmeyamaAlignment(coincident, spread, true).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(UmeyamaAlignment(spread, coincident, false).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(UmeyamaAlignment(spread, RandomPoints(9, 1.0), false).status().code(), StatusCode::kInvalidArgument);
  std::vector<Eigen::Vector3d> with_nan = spread;
  with_nan[3].y() = std::nan("");
  EXPECT_EQ(UmeyamaAlignment(with_nan, spread, false).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(AlignPoints({}, {}, AlignmentModel::kNone).status().code(), StatusCode::kInvalidArgument);
}

TEST_F(AlignmentTest, CollinearPointsAlignTheirPositions) {
  // The rotation about the line is free, but every aligned point must land on its target.
  std::vector<Eigen::Vector3d> source;
  for (int i = 0; i < 10; ++i) source.emplace_back(0.1 * i, 0.2 * i, -0.05 * i);
  const Sim3d truth = RandomSim3();
  const std::vector<Eigen::Vector3d> target = Apply(truth, source);
  const auto estimate = UmeyamaAlignment(source, target, true);
  ASSERT_TRUE(estimate.ok()) << estimate.status();
  for (size_t i = 0; i < source.size(); ++i)
    EXPECT_LT(((*estimate) * source[i] - target[i]).norm(), /*max_position_error_m=*/1e-9);
}

TEST(AlignmentModelTest, ParsesNames) {
  for (AlignmentModel m : {AlignmentModel::kNone, AlignmentModel::kSe3, AlignmentModel::kSim3}) {
    const auto parsed = ParseAlignmentModel(AlignmentModelName(m));
    ASSERT_TRUE(parsed.ok());
    EXPECT_EQ(*parsed, m);
  }
  EXPECT_FALSE(ParseAlignmentModel("SE3").ok());
}

}  // namespace
}  // namespace prism
