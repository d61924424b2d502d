// An indexed triangle mesh with optional per-vertex normals.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace prism {

struct TriangleMesh {
  std::vector<Eigen::Vector3d> vertices;
  std::vector<Eigen::Vector3d> vertex_normals;  // empty or vertices.size()
  std::vector<Eigen::Vector3i> faces;           // counter-clockwise seen from outside

  // Area-weighted vertex normals from the faces (overwrites vertex_normals).
  void ComputeVertexNormals();
  // Axis-aligned bounds; returns false for an empty mesh.
  bool Bounds(Eigen::Vector3d* min, Eigen::Vector3d* max) const;
};

}  // namespace prism
