#include "core/synth/mesh_bvh.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/util/check.h"

namespace prism::synth {
namespace {

constexpr int kLeafSize = 4;
constexpr int kBins = 12;

struct Box {
  Eigen::Vector3d min = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d max = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  void Grow(const Eigen::Vector3d& p) {
    min = min.cwiseMin(p);
    max = max.cwiseMax(p);
  }
  void Grow(const Box& b) {
    min = min.cwiseMin(b.min);
    max = max.cwiseMax(b.max);
  }
  double Area() const {
    const Eigen::Vector3d e = max - min;
    if (e.x() < 0) return 0;
    return 2 * (e.x() * e.y() + e.y() * e.z() + e.z() * e.x());
  }
};

// Slab test; returns entry distance or +inf.
inline double HitBox(const Eigen::Vector3d& min, const Eigen::Vector3d& max, const Eigen::Vector3d& origin,
                     const Eigen::Vector3d& inv_dir, double t_min, double t_max) {
  double t0 = t_min, t1 = t_max;
  for (int a = 0; a < 3; ++a) {
    double n = (min[a] - origin[a]) * inv_dir[a];
    double f = (max[a] - origin[a]) * inv_dir[a];
    if (n > f) std::swap(n, f);
    t0 = n > t0 ? n : t0;
    t1 = f < t1 ? f : t1;
    if (t0 > t1) return std::numeric_limits<double>::infinity();
  }
  return t0;
}

}  // namespace

MeshBvh::MeshBvh(TriangleMesh mesh) : mesh_(std::move(mesh)) {
  if (mesh_.vertex_normals.size() != mesh_.vertices.size()) mesh_.ComputeVertexNormals();
  const int n = static_cast<int>(mesh_.faces.size());
  order_.resize(n);
  std::vector<Eigen::Vector3d> centroids(n);
  for (int i = 0; i < n; ++i) {
    order_[i] = i;
    const Eigen::Vector3i& f = mesh_.faces[i];
    centroids[i] = (mesh_.vertices[f[0]] + mesh_.vertices[f[1]] + mesh_.vertices[f[2]]) / 3.0;
  }
  nodes_.reserve(2 * n / kLeafSize + 2);
  if (n > 0) Build(0, n, centroids);
  packed_.resize(n);
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3i& f = mesh_.faces[order_[i]];
    const Eigen::Vector3d& v0 = mesh_.vertices[f[0]];
    packed_[i] = {v0, mesh_.vertices[f[1]] - v0, mesh_.vertices[f[2]] - v0};
  }
}

int MeshBvh::Build(int first, int count, std::vector<Eigen::Vector3d>& centroids) {
  const int index = static_cast<int>(nodes_.size());
  nodes_.emplace_back();
  Box bounds, cbounds;
  for (int i = first; i < first + count; ++i) {
    const Eigen::Vector3i& f = mesh_.faces[order_[i]];
    for (int k = 0; k < 3; ++k) bounds.Grow(mesh_.vertices[f[k]]);
    cbounds.Grow(centroids[order_[i]]);
  }
  nodes_[index].min = bounds.min;
  nodes_[index].max = bounds.max;
  if (count <= kLeafSize) {
    nodes_[index].left_or_first = first;
    nodes_[index].count = count;
    return index;
  }
  // Binned SAH over the axis of largest centroid extent.
  const Eigen::Vector3d extent = cbounds.max - cbounds.min;
  int axis = 0;
  if (extent.y() > extent[axis]) axis = 1;
  if (extent.z() > extent[axis]) axis = 2;
  int mid = first + count / 2;
  if (extent[axis] > 1e-12) {
    Box bin_box[kBins];
    int bin_count[kBins] = {0};
    const double scale = kBins / extent[axis];
    auto bin_of = [&](int tri) {
      return std::min(kBins - 1, static_cast<int>((centroids[tri][axis] - cbounds.min[axis]) * scale));
    };
    for (int i = first; i < first + count; ++i) {
      const int b = bin_of(order_[i]);
      bin_count[b]++;
      const Eigen::Vector3i& f = mesh_.faces[order_[i]];
      for (int k = 0; k < 3; ++k) bin_box[b].Grow(mesh_.vertices[f[k]]);
    }
    double best_cost = std::numeric_limits<double>::infinity();
    int best_split = -1;
    for (int s = 1; s < kBins; ++s) {
      Box l, r;
      int nl = 0, nr = 0;
      for (int b = 0; b < s; ++b) {
        if (bin_count[b]) l.Grow(bin_box[b]);
        nl += bin_count[b];
      }
      for (int b = s; b < kBins; ++b) {
        if (bin_count[b]) r.Grow(bin_box[b]);
        nr += bin_count[b];
      }
      if (nl == 0 || nr == 0) continue;
      const double cost = nl * l.Area() + nr * r.Area();
      if (cost < best_cost) {
        best_cost = cost;
        best_split = s;
      }
    }
    if (best_split > 0) {
      auto it = std::partition(order_.begin() + first, order_.begin() + first + count,
                               [&](int tri) { return bin_of(tri) < best_split; });
      mid = static_cast<int>(it - order_.begin());
    }
  }
  if (mid == first || mid == first + count) {
    std::nth_element(order_.begin() + first, order_.begin() + first + count / 2, order_.begin() + first + count,
                     [&](int a, int b) { return centroids[a][axis] < centroids[b][axis]; });
    mid = first + count / 2;
  }
  const int left = Build(first, mid - first, centroids);
  const int right = Build(mid, first + count - mid, centroids);
  nodes_[index].left_or_first = left;
  nodes_[index].count = 0;
  nodes_[index].right = right;
  return index;
}

template <bool kAnyHit>
bool MeshBvh::Traverse(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                       RayHit* hit) const {
  if (nodes_.empty()) return false;
  const Eigen::Vector3d inv_dir(1.0 / dir.x(), 1.0 / dir.y(), 1.0 / dir.z());
  int stack[128];
  int sp = 0;
  stack[sp++] = 0;
  bool found = false;
  int best_tri = -1;
  double best_u = 0, best_v = 0;
  double closest = t_max;
  while (sp > 0) {
    const Node& node = nodes_[stack[--sp]];
    if (HitBox(node.min, node.max, origin, inv_dir, t_min, closest) == std::numeric_limits<double>::infinity())
      continue;
    if (node.count > 0) {
      for (int i = node.left_or_first; i < node.left_or_first + node.count; ++i) {
        const PackedTriangle& pt = packed_[i];
        const Eigen::Vector3d& v0 = pt.v0;
        const Eigen::Vector3d& e1 = pt.e1;
        const Eigen::Vector3d& e2 = pt.e2;
        const Eigen::Vector3d p = dir.cross(e2);
        const double det = e1.dot(p);
        if (std::abs(det) < 1e-14) continue;
        const double inv_det = 1.0 / det;
        const Eigen::Vector3d s = origin - v0;
        const double u = s.dot(p) * inv_det;
        if (u < 0 || u > 1) continue;
        const Eigen::Vector3d q = s.cross(e1);
        const double v = dir.dot(q) * inv_det;
        if (v < 0 || u + v > 1) continue;
        const double t = e2.dot(q) * inv_det;
        if (t <= t_min || t >= closest) continue;
        if (kAnyHit) return true;
        closest = t;
        best_tri = order_[i];
        best_u = u;
        best_v = v;
        found = true;
      }
    } else {
      // Visit the nearer child first.
      const int l = node.left_or_first, r = node.right;
      const double tl = HitBox(nodes_[l].min, nodes_[l].max, origin, inv_dir, t_min, closest);
      const double tr = HitBox(nodes_[r].min, nodes_[r].max, origin, inv_dir, t_min, closest);
      if (tl < tr) {
        if (tr != std::numeric_limits<double>::infinity()) stack[sp++] = r;
        stack[sp++] = l;
      } else {
        if (tl != std::numeric_limits<double>::infinity()) stack[sp++] = l;
        if (tr != std::numeric_limits<double>::infinity()) stack[sp++] = r;
      }
      PRISM_CHECK_LE(sp, 126) << "BVH deeper than the traversal stack";
    }
  }
  if (!found) return false;
  if (hit) {
    const Eigen::Vector3i& f = mesh_.faces[best_tri];
    const Eigen::Vector3d& v0 = mesh_.vertices[f[0]];
    hit->t = closest;
    hit->geometric_normal = (mesh_.vertices[f[1]] - v0).cross(mesh_.vertices[f[2]] - v0).normalized();
    const Eigen::Vector3d n = (1 - best_u - best_v) * mesh_.vertex_normals[f[0]] + best_u * mesh_.vertex_normals[f[1]] +
                              best_v * mesh_.vertex_normals[f[2]];
    hit->normal = n.normalized();
  }
  return true;
}

bool MeshBvh::Intersect(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max,
                        RayHit* hit) const {
  return Traverse<false>(origin, dir, t_min, t_max, hit);
}

bool MeshBvh::Occluded(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, double t_min, double t_max) const {
  return Traverse<true>(origin, dir, t_min, t_max, nullptr);
}

}  // namespace prism::synth
