#include "core/geometry/triangle_mesh.h"

namespace prism {

void TriangleMesh::ComputeVertexNormals() {
  vertex_normals.assign(vertices.size(), Eigen::Vector3d::Zero());
  for (const Eigen::Vector3i& f : faces) {
    const Eigen::Vector3d n = (vertices[f[1]] - vertices[f[0]]).cross(vertices[f[2]] - vertices[f[0]]);
    for (int k = 0; k < 3; ++k) vertex_normals[f[k]] += n;  // |n| = 2 * area: area weighting
  }
  for (Eigen::Vector3d& n : vertex_normals) {
    const double len = n.norm();
    n = len > 0 ? Eigen::Vector3d(n / len) : Eigen::Vector3d::UnitZ();
  }
}

bool TriangleMesh::Bounds(Eigen::Vector3d* min, Eigen::Vector3d* max) const {
  if (vertices.empty()) return false;
  *min = *max = vertices[0];
  for (const Eigen::Vector3d& v : vertices) {
    *min = min->cwiseMin(v);
    *max = max->cwiseMax(v);
  }
  return true;
}

}  // namespace prism
