// Sim(3) pose-graph optimisation of the keyframe graph (LSD-SLAM §3.4 in spirit): nodes are
// world_from_keyframe similarities, edges relative similarities measured by tracking (consecutive
// keyframes) or by direct alignment of a loop closure. Monocular scale drift is what Sim(3) adds over
// SE(3): a loop edge says how much the scale drifted around the loop, and the optimisation spreads
// the correction over the keyframes in between.
//
// Gauss-Newton (Levenberg-Marquardt damping) on a sparse system, one 7-vector (rotation, translation,
// log-scale) per free node; node 0 (or the nodes marked fixed) holds the gauge.
#pragma once

#include <vector>

#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

struct PoseGraphEdge {
  int from = 0, to = 0;
  // Measured from_from_to: the pose of node `to` in node `from`'s frame and units.
  Sim3d from_from_to;
  // Standard deviations of the error from_from_to^-1 * (world_from_from^-1 * world_from_to):
  // rotation (radians), translation (in `to`'s units) and log-scale, all > 0.
  double rotation_sigma = 0.01;
  double translation_sigma = 0.01;
  double log_scale_sigma = 0.01;
};

struct PoseGraphOptions {
  // Gauss-Newton iterations, in [1, 1000].
  int max_iterations = 30;
  // Stop when the relative decrease of the cost falls below this, in (0, 1).
  double relative_tolerance = 1e-8;
  Status Check() const;
};

struct PoseGraphSummary {
  int iterations = 0;
  double initial_cost = 0;  // 0.5 * sum of squared whitened residuals
  double final_cost = 0;
};

// Optimises `world_from_node` in place. Nodes with fixed[i] (default: node 0 only when `fixed` is
// empty) keep their value. INVALID_ARGUMENT on edges naming missing nodes, non-positive sigmas or
// scales, or an empty graph.
StatusOr<PoseGraphSummary> OptimisePoseGraph(const std::vector<PoseGraphEdge>& edges, const PoseGraphOptions& options,
                                             std::vector<Sim3d>* world_from_node, const std::vector<bool>& fixed = {});

}  // namespace prism
