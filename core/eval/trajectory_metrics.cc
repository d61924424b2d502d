#include "core/eval/trajectory_metrics.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <sstream>

namespace prism {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

// Sorted by stamp; a repeated stamp keeps the pose that came last (Python dict semantics).
Trajectory SortedUnique(const Trajectory& trajectory) {
  Trajectory sorted = trajectory;
  std::stable_sort(sorted.begin(), sorted.end(),
                   [](const TimedPose& a, const TimedPose& b) { return a.timestamp_s < b.timestamp_s; });
  Trajectory out;
  out.reserve(sorted.size());
  for (const TimedPose& p : sorted) {
    if (!out.empty() && out.back().timestamp_s == p.timestamp_s) out.back() = p;
    else out.push_back(p);
  }
  return out;
}

std::vector<double> Stamps(const Trajectory& trajectory) {
  std::vector<double> stamps;
  stamps.reserve(trajectory.size());
  for (const TimedPose& p : trajectory) stamps.push_back(p.timestamp_s);
  return stamps;
}

Status CheckTrajectory(const Trajectory& trajectory, const char* what) {
  if (trajectory.empty()) return InvalidArgumentError(std::string(what) + " trajectory is empty");
  for (size_t i = 0; i < trajectory.size(); ++i) {
    const TimedPose& p = trajectory[i];
    if (!std::isfinite(p.timestamp_s) || !p.world_from_camera.translation.allFinite() ||
        !p.world_from_camera.rotation.coeffs().allFinite())
      return InvalidArgumentError(std::string(what) + " pose " + std::to_string(i) + " is not finite");
  }
  return Status::Ok();
}

// evaluate_rpe.py find_closest_index, ported literally (a bisection that remembers the closest element
// visited) so that ties resolve exactly as in the script.
size_t FindClosestIndex(const std::vector<double>& sorted, double t) {
  size_t begin = 0;
  size_t end = sorted.size();
  size_t best = 0;
  double difference = std::abs(sorted[0] - t);
  while (begin < end) {
    const size_t middle = (begin + end) / 2;
    if (std::abs(sorted[middle] - t) < difference) {
      difference = std::abs(sorted[middle] - t);
      best = middle;
    }
    if (t == sorted[middle]) return middle;
    if (sorted[middle] > t) end = middle;
    else begin = middle + 1;
  }
  return best;
}

// Rotation angle of a rotation matrix in [0, pi]. The script's arccos(clamp((trace(R) - 1) / 2, -1, 1))
// resolves angles near 0 only to ~2e-8 rad (1e-6 deg); atan2 of sin and cos, with sin from the
// antisymmetric part, is the same angle for a rotation matrix and exact near 0.
double RotationMatrixAngle(const Eigen::Matrix3d& r) {
  const double cos_angle = 0.5 * (r.trace() - 1.0);
  const double sin_angle = 0.5 * Eigen::Vector3d(r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1)).norm();
  return std::atan2(sin_angle, cos_angle);
}

// A rigid transform as rotation matrix and translation.
struct Motion {
  Eigen::Matrix3d rotation;
  Eigen::Vector3d translation;
};

// TUM's ominus(a, b) = inv(a) * b for rigid transforms, with the inverse taken in closed form
// (R^T, -R^T t) rather than numpy's general 4x4 inverse: the same value up to rounding, and identical
// inputs give bit-identical motions, hence an error of exactly zero.
Motion Ominus(const Motion& a, const Motion& b) {
  return {a.rotation.transpose() * b.rotation, a.rotation.transpose() * (b.translation - a.translation)};
}

}  // namespace

const char* RpeDeltaUnitName(RpeDeltaUnit unit) {
  switch (unit) {
    case RpeDeltaUnit::kFrames:
      return "f";
    case RpeDeltaUnit::kSeconds:
      return "s";
  }
  return "unknown";
}

StatusOr<RpeDeltaUnit> ParseRpeDeltaUnit(const std::string& name) {
  if (name == "f" || name == "frames") return RpeDeltaUnit::kFrames;
  if (name == "s" || name == "seconds") return RpeDeltaUnit::kSeconds;
  return InvalidArgumentError("unknown RPE delta unit '" + name + "' (expected f or s)");
}

Status TrajectoryEvalOptions::Check() const {
  std::ostringstream err;
  if (alignment != AlignmentModel::kNone && alignment != AlignmentModel::kSe3 && alignment != AlignmentModel::kSim3)
    err << "TrajectoryEvalOptions.alignment = " << static_cast<int>(alignment) << "; violated: none, se3 or sim3";
  else if (!(max_time_difference_s > 0.0) || !std::isfinite(max_time_difference_s))
    err << "TrajectoryEvalOptions.max_time_difference_s = " << max_time_difference_s << "; violated: in (0, inf)";
  else if (!(rpe_delta > 0.0) || !std::isfinite(rpe_delta))
    err << "TrajectoryEvalOptions.rpe_delta = " << rpe_delta << "; violated: in (0, inf)";
  else if (rpe_delta_unit != RpeDeltaUnit::kFrames && rpe_delta_unit != RpeDeltaUnit::kSeconds)
    err << "TrajectoryEvalOptions.rpe_delta_unit = " << static_cast<int>(rpe_delta_unit)
        << "; violated: frames or seconds";
  if (err.str().empty()) return Status::Ok();
  return InvalidArgumentError(err.str());
}

std::vector<TimestampPair> AssociateTimestamps(const std::vector<double>& first_stamps,
                                               const std::vector<double>& second_stamps, double max_difference_s,
                                               double second_offset_s) {
  struct Candidate {
    double difference;
    double a;
    double b;
    size_t first;
    size_t second;
  };
  // Second stamps sorted (with their indices) so each first stamp scans only its window.
  std::vector<size_t> order(second_stamps.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::sort(order.begin(), order.end(), [&](size_t x, size_t y) { return second_stamps[x] < second_stamps[y]; });
  std::vector<double> sorted_second(order.size());
  for (size_t k = 0; k < order.size(); ++k) sorted_second[k] = second_stamps[order[k]];

  std::vector<Candidate> candidates;
  for (size_t i = 0; i < first_stamps.size(); ++i) {
    const double a = first_stamps[i];
    // The window is twice as wide as needed; the exact test below is the script's.
    const double low = a - second_offset_s - 2.0 * max_difference_s;
    const double high = a - second_offset_s + 2.0 * max_difference_s;
    for (auto it = std::lower_bound(sorted_second.begin(), sorted_second.end(), low);
         it != sorted_second.end() && *it <= high; ++it) {
      const double b = *it;
      const double difference = std::abs(a - (b + second_offset_s));
      if (difference < max_difference_s)
        candidates.push_back({difference, a, b, i, order[static_cast<size_t>(it - sorted_second.begin())]});
    }
  }
  // Python sorts the tuples (difference, a, b).
  std::sort(candidates.begin(), candidates.end(), [](const Candidate& x, const Candidate& y) {
    if (x.difference != y.difference) return x.difference < y.difference;
    if (x.a != y.a) return x.a < y.a;
    return x.b < y.b;
  });
  std::vector<bool> first_used(first_stamps.size(), false);
  std::vector<bool> second_used(second_stamps.size(), false);
  std::vector<TimestampPair> matches;
  for (const Candidate& c : candidates) {
    if (first_used[c.first] || second_used[c.second]) continue;
    first_used[c.first] = true;
    second_used[c.second] = true;
    matches.push_back({c.first, c.second});
  }
  std::sort(matches.begin(), matches.end(), [&](const TimestampPair& x, const TimestampPair& y) {
    if (first_stamps[x.first] != first_stamps[y.first]) return first_stamps[x.first] < first_stamps[y.first];
    return second_stamps[x.second] < second_stamps[y.second];
  });
  return matches;
}

StatusOr<AteResult> ComputeAte(const Trajectory& groundtruth, const Trajectory& estimate,
                               const TrajectoryEvalOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(CheckTrajectory(groundtruth, "ground-truth"));
  PRISM_RETURN_IF_ERROR(CheckTrajectory(estimate, "estimated"));
  const Trajectory gt = SortedUnique(groundtruth);
  const Trajectory est = SortedUnique(estimate);
  const std::vector<TimestampPair> matches =
      AssociateTimestamps(Stamps(gt), Stamps(est), options.max_time_difference_s);
  const size_t min_pairs = options.alignment == AlignmentModel::kNone ? 2 : 3;
  if (matches.size() < min_pairs) {
    std::ostringstream msg;
    msg << "only " << matches.size() << " ground-truth/estimate pose pairs within " << options.max_time_difference_s
        << " s (need " << min_pairs << "); do the timestamps belong to the same sequence?";
    return FailedPreconditionError(msg.str());
  }

  std::vector<Eigen::Vector3d> gt_positions;
  std::vector<Eigen::Vector3d> est_positions;
  gt_positions.reserve(matches.size());
  est_positions.reserve(matches.size());
  for (const TimestampPair& m : matches) {
    gt_positions.push_back(gt[m.first].world_from_camera.translation);
    est_positions.push_back(est[m.second].world_from_camera.translation);
  }

  AteResult result;
  result.pairs = matches.size();
  PRISM_ASSIGN_OR_RETURN(result.gt_from_est, AlignPoints(est_positions, gt_positions, options.alignment));
  std::vector<double> errors(matches.size());
  for (size_t k = 0; k < matches.size(); ++k)
    errors[k] = (result.gt_from_est * est_positions[k] - gt_positions[k]).norm();
  result.error_m = ComputeErrorStatistics(errors);
  for (size_t k = 1; k < gt_positions.size(); ++k)
    result.trajectory_length_m += (gt_positions[k] - gt_positions[k - 1]).norm();
  std::vector<double> angles(matches.size());
  for (size_t k = 0; k < matches.size(); ++k) {
    const Eigen::Quaterniond& q_gt = gt[matches[k].first].world_from_camera.rotation;
    const Eigen::Quaterniond& q_est = est[matches[k].second].world_from_camera.rotation;
    angles[k] = RotationAngle(q_gt.conjugate() * (result.gt_from_est.rotation * q_est)) * kRadToDeg;
  }
  result.orientation_error_deg = ComputeErrorStatistics(angles);
  const TimestampPair& first = matches.front();
  const TimestampPair& last = matches.back();
  result.net_rotation_deg_gt = RotationAngle(gt[first.first].world_from_camera.rotation.conjugate() *
                                             gt[last.first].world_from_camera.rotation) *
                               kRadToDeg;
  result.net_rotation_deg_est = RotationAngle(est[first.second].world_from_camera.rotation.conjugate() *
                                              est[last.second].world_from_camera.rotation) *
                                kRadToDeg;
  return result;
}

StatusOr<RpeResult> ComputeRpe(const Trajectory& groundtruth, const Trajectory& estimate,
                               const TrajectoryEvalOptions& options, double estimate_scale) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(CheckTrajectory(groundtruth, "ground-truth"));
  PRISM_RETURN_IF_ERROR(CheckTrajectory(estimate, "estimated"));
  if (!(estimate_scale > 0.0) || !std::isfinite(estimate_scale))
    return InvalidArgumentError("RPE: estimate scale must be finite and > 0");
  const Trajectory gt = SortedUnique(groundtruth);
  const Trajectory est = SortedUnique(estimate);
  if (gt.size() < 2) return FailedPreconditionError("RPE: the ground truth needs at least 2 poses");
  if (est.size() < 2) return FailedPreconditionError("RPE: the estimate needs at least 2 poses");
  const std::vector<double> gt_stamps = Stamps(gt);
  const std::vector<double> est_stamps = Stamps(est);

  // The coordinate the delta is measured in: frame index or stamp.
  std::vector<double> delta_coordinate(est.size());
  for (size_t i = 0; i < est.size(); ++i)
    delta_coordinate[i] = options.rpe_delta_unit == RpeDeltaUnit::kFrames ? static_cast<double>(i) : est_stamps[i];
  std::vector<std::pair<size_t, size_t>> pairs;
  for (size_t i = 0; i < est.size(); ++i) {
    const size_t j = FindClosestIndex(delta_coordinate, delta_coordinate[i] + options.rpe_delta);
    if (j != est.size() - 1) pairs.emplace_back(i, j);
  }

  std::vector<double> intervals(gt_stamps.size() - 1);
  for (size_t k = 1; k < gt_stamps.size(); ++k) intervals[k - 1] = gt_stamps[k] - gt_stamps[k - 1];
  const double gt_max_time_difference_s = 2.0 * Median(intervals);

  auto to_motion = [](const Rigid3d& pose) { return Motion{pose.RotationMatrix(), pose.translation}; };
  std::vector<Motion> est_poses(est.size());
  std::vector<Motion> gt_poses(gt.size());
  for (size_t i = 0; i < est.size(); ++i) est_poses[i] = to_motion(est[i].world_from_camera);
  for (size_t i = 0; i < gt.size(); ++i) gt_poses[i] = to_motion(gt[i].world_from_camera);

  std::vector<double> trans_errors;
  std::vector<double> rot_errors;
  for (const auto& [i, j] : pairs) {
    const size_t gi = FindClosestIndex(gt_stamps, est_stamps[i]);
    const size_t gj = FindClosestIndex(gt_stamps, est_stamps[j]);
    if (std::abs(gt_stamps[gi] - est_stamps[i]) > gt_max_time_difference_s ||
        std::abs(gt_stamps[gj] - est_stamps[j]) > gt_max_time_difference_s)
      continue;
    // evaluate_rpe.py: ominus(scale(ominus(E_j, E_i), s), ominus(G_j, G_i)).
    Motion est_motion = Ominus(est_poses[j], est_poses[i]);
    est_motion.translation *= estimate_scale;
    const Motion gt_motion = Ominus(gt_poses[gj], gt_poses[gi]);
    const Motion error = Ominus(est_motion, gt_motion);
    trans_errors.push_back(error.translation.norm());
    rot_errors.push_back(RotationMatrixAngle(error.rotation) * kRadToDeg);
  }
  if (trans_errors.empty())
    return FailedPreconditionError("RPE: no pose pair has ground truth within " +
                                   std::to_string(gt_max_time_difference_s) + " s of both estimate stamps");
  RpeResult result;
  result.pairs = trans_errors.size();
  result.trans_error_m = ComputeErrorStatistics(trans_errors);
  result.rot_error_deg = ComputeErrorStatistics(rot_errors);
  return result;
}

StatusOr<TrajectoryEvalResult> EvaluateTrajectory(const Trajectory& groundtruth, const Trajectory& estimate,
                                                  const TrajectoryEvalOptions& options) {
  TrajectoryEvalResult result;
  PRISM_ASSIGN_OR_RETURN(result.ate, ComputeAte(groundtruth, estimate, options));
  PRISM_ASSIGN_OR_RETURN(result.rpe, ComputeRpe(groundtruth, estimate, options, result.ate.gt_from_est.scale));
  return result;
}

}  // namespace prism
