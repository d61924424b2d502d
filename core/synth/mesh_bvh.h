// Bounding-volume hierarchy over a triangle mesh for ray casting (binned SAH build, flattened nodes,
// Moller-Trumbore intersection). Shading normals are interpolated vertex normals.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/geometry/triangle_mesh.h"

namespace prism::synth {

struct RayHit {
  double t = 0;
  Eigen::Vector3d normal;            // shading normal (unit), same frame as the ray
  Eigen::Vector3d geometric_normal;  // unit
};

class MeshBvh {
 public:
  // The mesh must have vertex normals (ComputeVertexNormals) or they are computed here.
  explicit MeshBvh(TriangleMesh mesh);

  // Closest hit with t in (t_min, t_max); false when none.
  bool Intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                 RayHit* hit) const;
  // Any hit with t in (t_min, t_max): for shadow rays.
  bool Occluded(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max) const;

  const TriangleMesh& mesh() const { return mesh_; }
  Eigen::Vector3d bounds_min() const { return nodes_.empty() ? Eigen::Vector3d::Zero() : nodes_[0].min; }
  Eigen::Vector3d bounds_max() const { return nodes_.empty() ? Eigen::Vector3d::Zero() : nodes_[0].max; }

 private:
  struct Node {
    Eigen::Vector3d min, max;
    int left_or_first = 0;  // inner: index of left child (right = left + 1); leaf: first triangle
    int count = 0;          // 0 for inner nodes
    int right = 0;          // inner: index of the right child
  };
  int Build(int first, int count, std::vector<Eigen::Vector3d>& centroids);
  template <bool kAnyHit>
  bool Traverse(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                RayHit* hit) const;

  // Triangles in leaf order with precomputed edges (v0, v1 - v0, v2 - v0): contiguous for traversal.
  struct PackedTriangle {
    Eigen::Vector3d v0, e1, e2;
  };
  std::vector<PackedTriangle> packed_;
  TriangleMesh mesh_;
  std::vector<int> order_;  // triangle indices in leaf order
  std::vector<Node> nodes_;
};

}  // namespace prism::synth
