#include "core/eval/nearest_neighbor_grid.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <queue>
#include <tuple>

#include "core/util/check.h"

namespace prism {
namespace {

// Each coarser level groups kBranch^3 cells of the level below.
constexpr int64_t kBranch = 4;
// The search starts from the top level, built up until it has at most this many cells.
constexpr size_t kMaxTopNodes = 64;
constexpr int kMaxLevels = 32;

int64_t FloorDiv(int64_t a, int64_t b) {
  int64_t q = a / b;
  if ((a % b != 0) && ((a < 0) != (b < 0))) --q;
  return q;
}

}  // namespace

NearestNeighborGrid::NearestNeighborGrid(const std::vector<Eigen::Vector3f>& points, double cell_size_m)
    : cell_size_m_(cell_size_m) {
  PRISM_CHECK(cell_size_m > 0.0 && std::isfinite(cell_size_m)) << "cell size " << cell_size_m;
  PRISM_CHECK_LT(points.size(), size_t{std::numeric_limits<uint32_t>::max()});
  const size_t n = points.size();
  std::vector<Key> keys(n);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3f& p = points[i];
    PRISM_CHECK(p.allFinite()) << "point " << i << " is not finite";
    const Eigen::Vector3d c = (p.cast<double>() / cell_size_m).array().floor();
    PRISM_CHECK(c.cwiseAbs().maxCoeff() <= kMaxCellIndex) << "point " << i << " is too far for the cell size";
    keys[i] = {static_cast<int64_t>(c.x()), static_cast<int64_t>(c.y()), static_cast<int64_t>(c.z())};
  }
  auto key_less = [](const Key& a, const Key& b) { return std::tie(a.x, a.y, a.z) < std::tie(b.x, b.y, b.z); };

  // Level 0: points grouped by cell.
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return key_less(keys[a], keys[b]); });
  points_.resize(n);
  Level level0;
  level0.cell_size_m = cell_size_m;
  for (size_t k = 0; k < n; ++k) {
    points_[k] = points[order[k]];
    const Key& key = keys[order[k]];
    if (level0.nodes.empty() || !(level0.nodes.back().key == key))
      level0.nodes.push_back({key, static_cast<uint32_t>(k), static_cast<uint32_t>(k)});
    level0.nodes.back().end = static_cast<uint32_t>(k + 1);
  }
  cell_index_.reserve(level0.nodes.size());
  for (size_t i = 0; i < level0.nodes.size(); ++i) cell_index_.emplace(level0.nodes[i].key, static_cast<uint32_t>(i));
  levels_.push_back(std::move(level0));

  // Coarser levels until few cells remain.
  while (levels_.back().nodes.size() > kMaxTopNodes && static_cast<int>(levels_.size()) < kMaxLevels) {
    const Level& below = levels_.back();
    std::vector<std::pair<Key, uint32_t>> parents(below.nodes.size());
    for (size_t i = 0; i < below.nodes.size(); ++i) {
      const Key& k = below.nodes[i].key;
      parents[i] = {{FloorDiv(k.x, kBranch), FloorDiv(k.y, kBranch), FloorDiv(k.z, kBranch)}, static_cast<uint32_t>(i)};
    }
    std::sort(parents.begin(), parents.end(), [&](const auto& a, const auto& b) {
      if (!(a.first == b.first)) return key_less(a.first, b.first);
      return a.second < b.second;
    });
    Level level;
    level.cell_size_m = below.cell_size_m * kBranch;
    level.children.resize(parents.size());
    for (size_t k = 0; k < parents.size(); ++k) {
      level.children[k] = parents[k].second;
      if (level.nodes.empty() || !(level.nodes.back().key == parents[k].first))
        level.nodes.push_back({parents[k].first, static_cast<uint32_t>(k), static_cast<uint32_t>(k)});
      level.nodes.back().end = static_cast<uint32_t>(k + 1);
    }
    levels_.push_back(std::move(level));
  }
}

double NearestNeighborGrid::BoxDistanceSquared(const Eigen::Vector3d& query, const Key& key, double cell_size_m) const {
  const double lo[3] = {key.x * cell_size_m, key.y * cell_size_m, key.z * cell_size_m};
  double d2 = 0.0;
  for (int a = 0; a < 3; ++a) {
    const double below = lo[a] - query[a];
    const double above = query[a] - (lo[a] + cell_size_m);
    const double d = std::max({below, above, 0.0});
    d2 += d * d;
  }
  return d2;
}

void NearestNeighborGrid::ScanNode(const Node& node, const Eigen::Vector3d& query, double* best_sq, bool* found) const {
  for (uint32_t k = node.begin; k < node.end; ++k) {
    const double d2 = (points_[k].cast<double>() - query).squaredNorm();
    if (d2 <= *best_sq) {
      *best_sq = d2;
      *found = true;
    }
  }
}

double NearestNeighborGrid::NearestDistance(const Eigen::Vector3f& query, double max_distance_m) const {
  constexpr double kInfinity = std::numeric_limits<double>::infinity();
  if (points_.empty()) return kInfinity;
  const Eigen::Vector3d q = query.cast<double>();
  double best_sq = max_distance_m * max_distance_m;
  bool found = false;

  // 1. The 3x3x3 cells around the query. Any point outside them is at least one cell size away (up to
  // rounding at cell borders, hence the slack), so a hit within that distance is the answer.
  const Eigen::Vector3d c = (q / cell_size_m_).array().floor();
  if (c.cwiseAbs().maxCoeff() <= kMaxCellIndex) {
    const Key center{static_cast<int64_t>(c.x()), static_cast<int64_t>(c.y()), static_cast<int64_t>(c.z())};
    // Squared distance from the query to the neighbour slab on each side, per axis (index d + 1).
    double axis_sq[3][3];
    for (int a = 0; a < 3; ++a) {
      const double below = std::max(0.0, q[a] - c[a] * cell_size_m_);
      const double above = std::max(0.0, (c[a] + 1.0) * cell_size_m_ - q[a]);
      axis_sq[a][0] = below * below;
      axis_sq[a][1] = 0.0;
      axis_sq[a][2] = above * above;
    }
    // The query's own cell first, then the neighbours that can still hold a closer point.
    auto scan = [&](int64_t dx, int64_t dy, int64_t dz) {
      const double lower_bound_sq = axis_sq[0][dx + 1] + axis_sq[1][dy + 1] + axis_sq[2][dz + 1];
      if (lower_bound_sq * (1.0 - 1e-9) > best_sq) return;
      const auto it = cell_index_.find({center.x + dx, center.y + dy, center.z + dz});
      if (it != cell_index_.end()) ScanNode(levels_[0].nodes[it->second], q, &best_sq, &found);
    };
    scan(0, 0, 0);
    for (int64_t dz = -1; dz <= 1; ++dz)
      for (int64_t dy = -1; dy <= 1; ++dy)
        for (int64_t dx = -1; dx <= 1; ++dx)
          if (dx != 0 || dy != 0 || dz != 0) scan(dx, dy, dz);
    const double settled = cell_size_m_ * (1.0 - 1e-9);
    if (best_sq <= settled * settled) return found ? std::sqrt(best_sq) : kInfinity;
  }

  // 2. Best-first search over the levels, from the coarsest, pruning cells farther than the best so far.
  // Cell boxes are computed from integer keys while points were binned with floor(p / cell); shrink the
  // lower bounds by a hair so rounding can never prune the cell that holds the nearest point.
  const double slack = 1e-9 * cell_size_m_;
  struct Entry {
    double lower_bound_sq;
    int level;
    uint32_t node;
    bool operator>(const Entry& o) const { return lower_bound_sq > o.lower_bound_sq; }
  };
  std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> queue;
  auto push = [&](int level, uint32_t node) {
    const Level& l = levels_[static_cast<size_t>(level)];
    const double d = std::max(0.0, std::sqrt(BoxDistanceSquared(q, l.nodes[node].key, l.cell_size_m)) - slack);
    if (d * d <= best_sq) queue.push({d * d, level, node});
  };
  const int top = static_cast<int>(levels_.size()) - 1;
  for (uint32_t i = 0; i < levels_.back().nodes.size(); ++i) push(top, i);
  while (!queue.empty()) {
    const Entry e = queue.top();
    queue.pop();
    if (e.lower_bound_sq > best_sq) break;
    const Level& l = levels_[static_cast<size_t>(e.level)];
    const Node& node = l.nodes[e.node];
    if (e.level == 0) ScanNode(node, q, &best_sq, &found);
    else
      for (uint32_t k = node.begin; k < node.end; ++k) push(e.level - 1, l.children[k]);
  }
  return found ? std::sqrt(best_sq) : kInfinity;
}

}  // namespace prism
