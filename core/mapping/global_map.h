// The global map (paper §3.4): registered keyframe clouds merged into a sparse voxel grid (voxel
// hashing, no PCL). Each voxel keeps the confidence-weighted mean of the positions, normals and
// colours merged into it, the summed confidence, the number of observations and the last keyframe
// that touched it. TakeChanges() hands out the voxels created or changed since its last call, so the
// map reaches clients as incremental chunks.
//
// Thread safety: not internally synchronised. One writer at a time (Insert, TakeChanges); const
// methods may run concurrently with each other but not with a writer. The pipeline's map stage owns
// the map; other threads get copies (ToPointCloud, MapChunk).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

struct MapOptions {
  // Edge of the cubic voxels, metres, in [1e-5, 10]. About the pixel footprint or coarser: a 512x512
  // keyframe of a 0.2 m object at 0.6 m has ~1 mm pixels, so 2 mm merges ~4 pixels per keyframe.
  double voxel_m = 0.002;
  // A voxel enters the map's output (ToPointCloud, TakeChanges) once points of at least this many
  // keyframes were merged into it, in [1, 1000]. A surface is seen by several keyframes; a stray point
  // (a flying pixel, a wrong depth) by one, each in a voxel of its own, so their share of the map grows
  // with every keyframe. 1 = every voxel.
  int min_keyframes = 1;

  Status Check() const;
};

// A voxel's integer coordinates: voxel (i, j, k) covers [i, i+1) x [j, j+1) x [k, k+1) * voxel_m.
// Keys pack 21 bits per axis (two's complement), so |coordinate| < 2^20 voxels (2 km at 2 mm).
using VoxelKey = uint64_t;
constexpr int64_t kMaxVoxelCoordinate = (int64_t{1} << 20) - 1;
constexpr int64_t kMinVoxelCoordinate = -(int64_t{1} << 20);
// PRISM_CHECK that every coordinate is in [kMinVoxelCoordinate, kMaxVoxelCoordinate].
VoxelKey PackVoxelKey(const Eigen::Vector3i& voxel);
Eigen::Vector3i UnpackVoxelKey(VoxelKey key);

// Voxels created or changed since the previous TakeChanges() that have at least MapOptions::min_keyframes
// keyframes, one point per voxel in the order they were first touched. cloud holds each voxel's current state (as in
// ToPointCloud); keys[i] and observations[i] belong to cloud point i.
struct MapChunk {
  uint64_t sequence = 0;  // 1 for the first chunk of a map, then 2, 3, ...
  PointCloud cloud;
  std::vector<VoxelKey> keys;
  std::vector<uint32_t> observations;
  // The map was cleared (GlobalMap::Clear) before these changes: every voxel of earlier chunks is void,
  // and this chunk with the ones after it is the whole map.
  bool replaces_map = false;

  size_t size() const { return keys.size(); }
  bool empty() const { return keys.empty(); }
};

// What one Insert did. Skipped points change nothing.
struct MapInsertStats {
  size_t merged_points = 0;           // points merged into a voxel
  size_t new_voxels = 0;              // voxels created by this insert
  size_t skipped_non_finite = 0;      // position with a NaN or infinite coordinate
  size_t skipped_bad_confidence = 0;  // confidence <= 0 or not finite (zero weight: no information)
  size_t skipped_out_of_range = 0;    // beyond the voxel key range (kMaxVoxelCoordinate)

  size_t skipped() const { return skipped_non_finite + skipped_bad_confidence + skipped_out_of_range; }
  MapInsertStats& operator+=(const MapInsertStats& o);
};

class GlobalMap {
 public:
  // PRISM_CHECK on invalid options: validate them (Check) where they enter the process.
  explicit GlobalMap(const MapOptions& options = MapOptions());

  // Merges every point of a cloud given in the world frame into its voxel. Weight = the point's
  // confidence (1 when the cloud has none). Positions: weighted running mean. Normals: weighted sum,
  // renormalised on output; missing normals (zero or non-finite) do not vote, so a voxel gets a normal
  // from any keyframe that had one. Colours: weighted mean. Bad points are skipped and counted.
  // INVALID_ARGUMENT (map unchanged) when the cloud's attribute arrays do not match its positions.
  StatusOr<MapInsertStats> Insert(const PointCloud& cloud_in_world, uint64_t keyframe_id);
  // Same for a cloud in another frame (a keyframe): positions are mapped and normals rotated by
  // world_from_cloud on the fly, without a transformed copy.
  StatusOr<MapInsertStats> Insert(const PointCloud& cloud, const Rigid3d& world_from_cloud, uint64_t keyframe_id);

  // The voxels created or changed since the previous call (all of them the first time), then forgets
  // them: the next call returns only later changes.
  MapChunk TakeChanges();
  // Removes every voxel (a map rebuilt from moved keyframes). The chunk sequence goes on, and the next
  // TakeChanges() returns replaces_map = true. totals() start again from zero.
  void Clear();
  // Voxels changed since the last TakeChanges().
  size_t pending_changes() const { return changed_.size(); }

  // One point per voxel with at least MapOptions::min_keyframes keyframes, summed confidence >=
  // min_confidence and >= min_observations observations:
  // mean position, unit normal (zero = none; the normals array is present once any inserted point had
  // a normal), mean colour (present once any inserted cloud had colours; zero for voxels without
  // colour), summed confidence. Order: voxel creation order.
  PointCloud ToPointCloud(double min_confidence = 0.0, int min_observations = 1) const;

  // Number of voxels, and of those with at least MapOptions::min_keyframes keyframes (the output).
  size_t size() const { return voxels_.size(); }
  size_t output_size() const { return output_voxels_; }
  bool empty() const { return voxels_.empty(); }
  const MapOptions& options() const { return options_; }
  // Everything Insert did since construction or the last Clear().
  const MapInsertStats& totals() const { return totals_; }

  // Voxel of a point (floor(p / voxel_m)); false when a coordinate is not finite or out of key range.
  bool VoxelOf(const Eigen::Vector3f& point, Eigen::Vector3i* voxel) const;
  // Observations of the voxel holding `key`, 0 when it does not exist.
  uint32_t Observations(VoxelKey key) const;
  // Distinct keyframes merged into the voxel holding `key`, 0 when it does not exist.
  uint32_t Keyframes(VoxelKey key) const;
  // Last keyframe merged into the voxel holding `key`; false when it does not exist.
  bool LastKeyframe(VoxelKey key, uint64_t* keyframe_id) const;

 private:
  static constexpr uint32_t kEmptySlot = 0xFFFFFFFFu;

  struct Voxel {
    Eigen::Vector3f position = Eigen::Vector3f::Zero();    // weighted mean
    Eigen::Vector3f normal_sum = Eigen::Vector3f::Zero();  // weighted sum of unit normals
    Eigen::Vector3f color_sum = Eigen::Vector3f::Zero();   // weighted sum of RGB
    float weight = 0.0f;                                   // summed confidence
    float color_weight = 0.0f;
    uint32_t observations = 0;
    uint32_t keyframes = 0;  // distinct keyframes merged (consecutive inserts of one keyframe count once)
    bool changed = false;    // listed in changed_
    uint64_t last_keyframe_id = 0;
    VoxelKey key = 0;
  };

  template <typename Transform>
  StatusOr<MapInsertStats> InsertImpl(const PointCloud& cloud, const Transform& to_world, uint64_t keyframe_id);
  // Index into voxels_ of `key`, creating the voxel when absent (*created = true).
  uint32_t FindOrCreate(VoxelKey key, bool* created);
  // Index into voxels_, or kEmptySlot.
  uint32_t Find(VoxelKey key) const;
  void Rehash(size_t capacity);
  // Sizes the output arrays for n voxels (normals and colours only when the map has them).
  void PrepareOutput(size_t n, PointCloud* cloud) const;
  void WriteVoxel(const Voxel& v, size_t i, PointCloud* cloud) const;

  MapOptions options_;
  double inv_voxel_m_;
  std::vector<Voxel> voxels_;
  struct Slot {
    VoxelKey key = 0;
    uint32_t index = kEmptySlot;  // into voxels_
  };
  // Open-addressing hash table: linear probing, power-of-two size, load <= 1/2.
  std::vector<Slot> slots_;
  // Direct-mapped cache of recently used voxels, indexed by the low kRecentBits bits of each voxel
  // coordinate: the next image row revisits the voxels of the last one, and a hit here avoids a cache
  // miss in slots_. Voxels are removed only all at once (Clear, which empties it too), so entries never
  // go stale.
  static constexpr int kRecentBits = 4;
  static size_t RecentSlot(const Eigen::Vector3i& v) {
    constexpr int kMask = (1 << kRecentBits) - 1;
    return static_cast<size_t>((v.x() & kMask) | ((v.y() & kMask) << kRecentBits) |
                               ((v.z() & kMask) << (2 * kRecentBits)));
  }
  std::vector<Slot> recent_;
  std::vector<uint32_t> changed_;  // voxel indices changed since the last TakeChanges
  uint64_t chunk_sequence_ = 0;
  size_t output_voxels_ = 0;  // voxels with at least min_keyframes keyframes
  bool cleared_ = false;      // Clear() since the last TakeChanges()
  bool has_normals_ = false;
  bool has_colors_ = false;
  MapInsertStats totals_;
};

}  // namespace prism
