// Closed-form alignment of corresponding 3D point sets (Umeyama, "Least-squares estimation of
// transformation parameters between two point patterns", PAMI 1991). With the scale fixed to 1 it is
// the same solution as Horn's method used by the TUM RGB-D benchmark's evaluate_ate.py.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

// How an estimate is brought into the frame of the ground truth before comparing positions.
enum class AlignmentModel {
  kNone,  // identity: compare in the estimate's own frame
  kSe3,   // rotation + translation, scale fixed to 1
  kSim3,  // rotation + translation + scale (monocular estimates)
};

// "none", "se3", "sim3".
const char* AlignmentModelName(AlignmentModel model);
// Parses "none" | "se3" | "sim3" (case-sensitive); INVALID_ARGUMENT otherwise.
StatusOr<AlignmentModel> ParseAlignmentModel(const std::string& name);

// Returns target_from_source minimising sum_i |target_i - (s R source_i + t)|^2, with s = 1 unless
// `estimate_scale`. Errors (INVALID_ARGUMENT): sizes differ, fewer than 3 points, a non-finite
// coordinate, or either set coincident (no spread, so rotation and scale are undetermined).
// Collinear sets are accepted: the rotation about their common line is then arbitrary, which does
// not change the aligned positions of those points.
StatusOr<Sim3d> UmeyamaAlignment(const std::vector<Eigen::Vector3d>& source_points,
                                 const std::vector<Eigen::Vector3d>& target_points, bool estimate_scale);

// UmeyamaAlignment for kSe3 / kSim3; for kNone the identity (needs equal sizes, at least 1 point).
StatusOr<Sim3d> AlignPoints(const std::vector<Eigen::Vector3d>& source_points,
                            const std::vector<Eigen::Vector3d>& target_points, AlignmentModel model);

}  // namespace prism
