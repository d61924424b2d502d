// Map chunks on the wire: Draco point clouds with positions, normals and colours.
//
// Positions lie on a fixed per-session grid aligned with the map's voxels: each voxel of edge
// voxel_m is split into subdivisions^3 cells, and a point is stored as the centre of its cell inside
// its own voxel. So floor(position / voxel_m) of a decoded point is exactly the voxel it came from:
// a client keys its running map by voxel (VoxelOfDecodedPoint) and a later chunk replaces the voxel.
// Points are sorted in Morton order of their grid cell and coded with Draco's sequential encoder
// (which keeps the point order, so neighbours in space are neighbours in the stream and the position
// deltas stay small). Normals use Draco's octahedral quantisation; colours are stored as 8-bit RGB.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "core/geometry/point_cloud.h"
#include "core/util/status.h"

namespace prism {

struct MapChunkCodecOptions {
  // Edge of the map's voxels, metres, in [1e-5, 10] (MapOptions::voxel_m of the session).
  double voxel_m = 0.002;
  // Grid cells per voxel edge, in [1, 64]; the grid step is voxel_m / subdivisions (8: 0.25 mm at a
  // 2 mm voxel, under 0.08 mm RMS position error).
  int subdivisions = 8;
  // Grid cells per axis = 2^position_bits, centred on the origin, in [8, 21]; points beyond are
  // dropped and counted (21 bits at 0.25 mm: +-262 m). Draco works in float: beyond 21 bits the grid
  // values far from the origin would no longer be exact.
  int position_bits = 21;
  // Octahedral normal quantisation bits, in [4, 16] (10: ~0.1 degree).
  int normal_bits = 10;
  // Draco compression level, in [0, 10] (Draco speed = 10 - level).
  int compression_level = 7;

  double grid_step_m() const { return voxel_m / subdivisions; }
  Status Check() const;
};

struct EncodedMapChunk {
  std::vector<uint8_t> bytes;  // a Draco point cloud (.drc)
  size_t num_points = 0;       // points encoded
  // Points left out: non-finite position or outside the grid.
  size_t dropped_points = 0;
  // order[k] = index in the input cloud of encoded point k (Morton order).
  std::vector<uint32_t> order;
};

// Encodes the cloud's positions and, when present, normals and colours. INVALID_ARGUMENT on bad
// options or an inconsistent cloud; FAILED_PRECONDITION when no point is left to encode (Draco cannot
// decode a point cloud without points: an empty chunk is not sent).
StatusOr<EncodedMapChunk> EncodeMapChunk(const PointCloud& cloud, const MapChunkCodecOptions& options);

// Decodes a chunk: positions, plus normals and colours when the chunk has them. DATA_LOSS when the
// bytes are not a Draco point cloud (corrupt or truncated); INVALID_ARGUMENT when it lacks a 3D
// position attribute or its attributes have unexpected shapes.
StatusOr<PointCloud> DecodeMapChunk(const uint8_t* data, size_t size);

// The voxel a decoded point belongs to (floor(position / voxel_m)).
Eigen::Vector3i VoxelOfDecodedPoint(const Eigen::Vector3f& position, double voxel_m);

// 63-bit Morton code interleaving the low 21 bits of each coordinate (x in the lowest bit).
uint64_t MortonCode(uint32_t x, uint32_t y, uint32_t z);

}  // namespace prism
