// Exact nearest-neighbour queries on a fixed 3D point set with uniform voxel grids (no PCL): points are
// bucketed in cubic cells of the given size (level 0), and coarser levels (4x the cell size each) list
// the occupied cells of the level below, up to a level with a few dozen cells. A best-first search over
// the cell boxes answers queries in a few cells near the points, and stays fast far from them (outliers
// of a reconstruction), where a single uniform grid would have to scan shell after shell of empty cells.
// Occupied cells are kept sorted by key instead of hashed: the search walks the levels top-down, so no
// cell is ever looked up by key.
#pragma once

#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

namespace prism {

class NearestNeighborGrid {
 public:
  // Largest |coordinate| / cell_size_m the grid accepts (cell indices stay exact in int64 and double).
  static constexpr double kMaxCellIndex = 1e12;

  // Indexes `points`. Every coordinate must be finite with |coordinate| / cell_size_m <= kMaxCellIndex,
  // and cell_size_m > 0 (PRISM_CHECK: callers validate untrusted data first).
  NearestNeighborGrid(const std::vector<Eigen::Vector3f>& points, double cell_size_m);

  size_t size() const { return points_.size(); }
  double cell_size_m() const { return cell_size_m_; }

  // Exact Euclidean distance from `query` to the nearest indexed point when it is <= max_distance_m;
  // +infinity otherwise (and when the grid is empty). A finite max_distance_m makes the search cheaper.
  double NearestDistance(const Eigen::Vector3f& query,
                         double max_distance_m = std::numeric_limits<double>::infinity()) const;

 private:
  struct Key {
    int64_t x, y, z;
    bool operator==(const Key& o) const { return x == o.x && y == o.y && z == o.z; }
  };
  // One occupied cell: at level 0 a range of points_, above a range of the level's child list.
  struct Node {
    Key key;
    uint32_t begin;
    uint32_t end;
  };
  struct Level {
    double cell_size_m = 0.0;
    std::vector<Node> nodes;
    std::vector<uint32_t> children;  // node indices in the level below (empty at level 0)
  };

  double BoxDistanceSquared(const Eigen::Vector3d& query, const Key& key, double cell_size_m) const;

  double cell_size_m_;
  std::vector<Eigen::Vector3f> points_;  // grouped by level-0 cell
  std::vector<Level> levels_;            // levels_[0] finest; the last has few nodes
};

}  // namespace prism
