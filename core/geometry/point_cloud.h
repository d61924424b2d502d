// A point cloud with optional per-point normals, colours and confidences (parallel arrays).
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "core/geometry/rigid3.h"

namespace prism {

struct PointCloud {
  std::vector<Eigen::Vector3f> positions;
  std::vector<Eigen::Vector3f> normals;              // empty or positions.size()
  std::vector<Eigen::Matrix<uint8_t, 3, 1>> colors;  // empty or positions.size(), RGB
  std::vector<float> confidences;                    // empty or positions.size()

  size_t size() const { return positions.size(); }
  bool empty() const { return positions.empty(); }
  bool HasNormals() const { return !normals.empty(); }
  bool HasColors() const { return !colors.empty(); }
  bool HasConfidences() const { return !confidences.empty(); }
  // True when every present attribute array matches positions in length.
  bool IsConsistent() const;
};

// Applies target_from_source to positions and rotates normals (other attributes are copied).
PointCloud TransformCloud(const PointCloud& cloud, const Rigid3d& target_from_source);
// The same with a similarity: positions scaled, rotated and moved; normals rotated.
PointCloud TransformCloud(const PointCloud& cloud, const Sim3d& target_from_source);

}  // namespace prism
