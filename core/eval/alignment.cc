#include "core/eval/alignment.h"

#include <cmath>

#include <Eigen/SVD>

namespace prism {
namespace {

Status CheckSets(const std::vector<Eigen::Vector3d>& source, const std::vector<Eigen::Vector3d>& target,
                 size_t min_points) {
  if (source.size() != target.size())
    return InvalidArgumentError("alignment: " + std::to_string(source.size()) + " source points but " +
                                std::to_string(target.size()) + " target points");
  if (source.size() < min_points)
    return InvalidArgumentError("alignment: needs at least " + std::to_string(min_points) +
                                " corresponding points, got " + std::to_string(source.size()));
  for (size_t i = 0; i < source.size(); ++i)
    if (!source[i].allFinite() || !target[i].allFinite())
      return InvalidArgumentError("alignment: point " + std::to_string(i) + " is not finite");
  return Status::Ok();
}

// True when the points have no spread relative to their magnitude (all coincident up to rounding).
bool IsCoincident(double variance, const Eigen::Vector3d& mean) {
  const double magnitude = 1.0 + mean.squaredNorm();
  return !(variance > 1e-24 * magnitude);
}

}  // namespace

const char* AlignmentModelName(AlignmentModel model) {
  switch (model) {
    case AlignmentModel::kNone:
      return "none";
    case AlignmentModel::kSe3:
      return "se3";
    case AlignmentModel::kSim3:
      return "sim3";
  }
  return "unknown";
}

StatusOr<AlignmentModel> ParseAlignmentModel(const std::string& name) {
  if (name == "none") return AlignmentModel::kNone;
  if (name == "se3") return AlignmentModel::kSe3;
  if (name == "sim3") return AlignmentModel::kSim3;
  return InvalidArgumentError("unknown alignment '" + name + "' (expected none, se3 or sim3)");
}

StatusOr<Sim3d> UmeyamaAlignment(const std::vector<Eigen::Vector3d>& source_points,
                                 const std::vector<Eigen::Vector3d>& target_points, bool estimate_scale) {
  PRISM_RETURN_IF_ERROR(CheckSets(source_points, target_points, /*min_points=*/3));
  const size_t n = source_points.size();
  const double inv_n = 1.0 / static_cast<double>(n);

  Eigen::Vector3d mean_source = Eigen::Vector3d::Zero();
  Eigen::Vector3d mean_target = Eigen::Vector3d::Zero();
  for (size_t i = 0; i < n; ++i) {
    mean_source += source_points[i];
    mean_target += target_points[i];
  }
  mean_source *= inv_n;
  mean_target *= inv_n;

  // Cross-covariance (target x source) and the source variance (Umeyama eqs. 36-38).
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();
  double variance_source = 0.0;
  double variance_target = 0.0;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d s = source_points[i] - mean_source;
    const Eigen::Vector3d t = target_points[i] - mean_target;
    covariance += t * s.transpose();
    variance_source += s.squaredNorm();
    variance_target += t.squaredNorm();
  }
  covariance *= inv_n;
  variance_source *= inv_n;
  variance_target *= inv_n;
  if (IsCoincident(variance_source, mean_source))
    return InvalidArgumentError("alignment: the source points are all coincident");
  if (IsCoincident(variance_target, mean_target))
    return InvalidArgumentError("alignment: the target points are all coincident");

  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(covariance, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Vector3d signs = Eigen::Vector3d::Ones();
  if (svd.matrixU().determinant() * svd.matrixV().determinant() < 0.0) signs(2) = -1.0;
  const Eigen::Matrix3d rotation = svd.matrixU() * signs.asDiagonal() * svd.matrixV().transpose();
  const double scale = estimate_scale ? svd.singularValues().dot(signs) / variance_source : 1.0;
  if (!(scale > 0.0) || !std::isfinite(scale))
    return InvalidArgumentError("alignment: degenerate configuration (scale " + std::to_string(scale) + ")");
  const Eigen::Vector3d translation = mean_target - scale * (rotation * mean_source);
  return Sim3d(scale, Eigen::Quaterniond(rotation), translation);
}

StatusOr<Sim3d> AlignPoints(const std::vector<Eigen::Vector3d>& source_points,
                            const std::vector<Eigen::Vector3d>& target_points, AlignmentModel model) {
  switch (model) {
    case AlignmentModel::kNone:
      PRISM_RETURN_IF_ERROR(CheckSets(source_points, target_points, /*min_points=*/1));
      return Sim3d();
    case AlignmentModel::kSe3:
      return UmeyamaAlignment(source_points, target_points, /*estimate_scale=*/false);
    case AlignmentModel::kSim3:
      return UmeyamaAlignment(source_points, target_points, /*estimate_scale=*/true);
  }
  return InvalidArgumentError("alignment: unknown model");
}

}  // namespace prism
