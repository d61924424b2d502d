// Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE), reproducing the
// TUM RGB-D benchmark tools (associate.py, evaluate_ate.py, evaluate_rpe.py by J. Sturm et al.)
// number for number, so results are comparable with published tables.
//
// Poses are world_from_camera (TUM convention). Trajectories may come in any order; stamps are sorted
// and, as in the TUM scripts (which key poses by stamp in a dict), a repeated stamp keeps its last pose.
#pragma once

#include <string>
#include <vector>

#include "core/eval/alignment.h"
#include "core/eval/statistics.h"
#include "core/geometry/rigid3.h"
#include "core/io/trajectory_io.h"
#include "core/util/status.h"

namespace prism {

// Unit of the RPE step between the two poses of a pair.
enum class RpeDeltaUnit {
  kFrames,   // estimate poses (TUM --delta_unit f)
  kSeconds,  // seconds of estimate time (TUM --delta_unit s)
};

// "f", "s".
const char* RpeDeltaUnitName(RpeDeltaUnit unit);
// Parses "f" | "frames" | "s" | "seconds"; INVALID_ARGUMENT otherwise.
StatusOr<RpeDeltaUnit> ParseRpeDeltaUnit(const std::string& name);

struct TrajectoryEvalOptions {
  // Alignment of the estimate onto the ground truth before the ATE (Umeyama on associated positions).
  AlignmentModel alignment = AlignmentModel::kSe3;
  // Maximum |t_gt - t_est| in seconds for associating poses, exclusive (TUM associate.py default
  // 0.02; evo uses 0.01). In (0, inf). KITTI files read without times carry index stamps 0, 1, 2...,
  // so any value below 0.5 associates them by index.
  double max_time_difference_s = 0.02;
  // RPE step between the two poses of a pair, in rpe_delta_unit. > 0.
  double rpe_delta = 1.0;
  // Unit of rpe_delta.
  RpeDeltaUnit rpe_delta_unit = RpeDeltaUnit::kFrames;

  Status Check() const;  // "TrajectoryEvalOptions.rpe_delta = 0; violated: in (0, inf)"
};

// Indices of one associated pair: first_stamps[first] <-> second_stamps[second].
struct TimestampPair {
  size_t first = 0;
  size_t second = 0;
};

// TUM associate.py: every candidate (a, b) with |a - (b + second_offset_s)| < max_difference_s, sorted by
// (difference, a, b), taken greedily when neither stamp is used yet; the result is sorted by first stamp.
// Stamps must be unique within each list (they need not be sorted).
std::vector<TimestampPair> AssociateTimestamps(const std::vector<double>& first_stamps,
                                               const std::vector<double>& second_stamps, double max_difference_s,
                                               double second_offset_s = 0.0);

struct AteResult {
  size_t pairs = 0;                  // associated pose pairs
  ErrorStatistics error_m;           // |gt position - aligned estimate position| per pair, metres
  Sim3d gt_from_est;                 // alignment applied to the estimate (identity for kNone)
  double trajectory_length_m = 0.0;  // ground-truth path length over the associated poses
  // Not in the TUM scripts (the ATE above sees positions only). Per pair, the angle between the
  // ground-truth orientation and the estimate's turned by the alignment's rotation (gt_from_est, found
  // from the positions), degrees: a trajectory can sit on the right path and still look the wrong way.
  // On a nearly straight path the positions leave the alignment's roll about the path free, and this
  // error with it (KITTI 06's first 51 frames: 28 degrees at a net rotation of 1.3); the net rotation
  // below and the RPE do not depend on the alignment.
  ErrorStatistics orientation_error_deg;
  // The angle between the orientations of the first and the last associated pose, degrees, in the
  // ground truth and in the estimate: an orbit rotated too little shows as estimate < ground truth.
  double net_rotation_deg_gt = 0.0;
  double net_rotation_deg_est = 0.0;
};

struct RpeResult {
  size_t pairs = 0;               // evaluated pose pairs
  ErrorStatistics trans_error_m;  // translational part of each relative error, metres
  ErrorStatistics rot_error_deg;  // rotation angle of each relative error, degrees
};

struct TrajectoryEvalResult {
  AteResult ate;
  RpeResult rpe;
};

// ATE as evaluate_ate.py: associate (gt first), align the estimate's positions onto the ground truth's,
// per-pair position error. FAILED_PRECONDITION when fewer than 2 pairs associate (3 with alignment).
StatusOr<AteResult> ComputeAte(const Trajectory& groundtruth, const Trajectory& estimate,
                               const TrajectoryEvalOptions& options);

// RPE as evaluate_rpe.py --fixed_delta (without its random subsampling above 10000 pairs): for every
// estimate index i, j = the index whose delta coordinate (frame index, or stamp for seconds) is closest to
// i's + delta, and the pair is dropped when j is the last index (as the script does). Each estimate stamp
// takes the ground-truth pose of the closest stamp; the pair is skipped when either is further than
// 2 x the median ground-truth interval. With 4x4 world_from_camera poses, the error is the script's
//   error = inv(inv(E_j) E_i) * (inv(G_j) G_i)
// with the estimate's relative translation multiplied by `estimate_scale` (TUM --scale); translational
// error = |translation(error)|, rotational error = the angle of its rotation (the script's
// arccos((trace(R) - 1) / 2), computed as atan2(sin, cos) so that it stays exact near 0).
// (inv(inv(E_i) E_j) * inv(G_i) G_j, evo's form up to inversion, has the same angle but a slightly
// different translation norm: 0.0057597 instead of the script's 0.0057634 m on fr1/xyz rgbdslam.)
// FAILED_PRECONDITION when no pair survives.
StatusOr<RpeResult> ComputeRpe(const Trajectory& groundtruth, const Trajectory& estimate,
                               const TrajectoryEvalOptions& options, double estimate_scale = 1.0);

// ATE and RPE. With Sim(3) alignment the RPE uses the ATE's scale for the estimate.
StatusOr<TrajectoryEvalResult> EvaluateTrajectory(const Trajectory& groundtruth, const Trajectory& estimate,
                                                  const TrajectoryEvalOptions& options);

}  // namespace prism
