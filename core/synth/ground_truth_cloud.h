// A dense coloured cloud with normals from a sequence's ground truth (depth, normals, colour, poses):
// what a perfect reconstruction would give. Used by the demo and as a fusion target to look at.
#pragma once

#include "core/geometry/point_cloud.h"
#include "core/io/sequence.h"
#include "core/util/status.h"

namespace prism::synth {

struct GroundTruthCloudOptions {
  // Back-project every k-th frame, >= 1.
  int frame_step = 10;
  // Voxel size of the merged cloud, metres (points in a voxel are averaged), > 0.
  double voxel_m = 0.002;
  // Keep only object pixels (mask 255).
  bool object_only = false;
  Status Check() const;
};

StatusOr<PointCloud> GroundTruthCloud(const Sequence& sequence, const GroundTruthCloudOptions& options);

}  // namespace prism::synth
