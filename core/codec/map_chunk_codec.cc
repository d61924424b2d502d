#include "core/codec/map_chunk_codec.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <string>

#include <draco/compression/config/compression_shared.h>
#include <draco/compression/encode.h>
#include <draco/point_cloud/point_cloud_builder.h>

#include "core/codec/draco_cloud.h"

namespace prism {
namespace {

Status Violated(const std::string& field, double value, const std::string& rule) {
  return InvalidArgumentError("MapChunkCodecOptions." + field + " = " + std::to_string(value) + "; violated: " + rule);
}

// Spreads the low 21 bits of v so that there are two zero bits between each.
uint64_t Spread21(uint32_t v) {
  uint64_t x = v & 0x1FFFFFu;
  x = (x | (x << 32)) & 0x1F00000000FFFFull;
  x = (x | (x << 16)) & 0x1F0000FF0000FFull;
  x = (x | (x << 8)) & 0x100F00F00F00F00Full;
  x = (x | (x << 4)) & 0x10C30C30C30C30C3ull;
  x = (x | (x << 2)) & 0x1249249249249249ull;
  return x;
}

}  // namespace

uint64_t MortonCode(uint32_t x, uint32_t y, uint32_t z) {
  return Spread21(x) | (Spread21(y) << 1) | (Spread21(z) << 2);
}

Status MapChunkCodecOptions::Check() const {
  if (!(voxel_m >= 1e-5 && voxel_m <= 10)) return Violated("voxel_m", voxel_m, "in [1e-5, 10]");
  if (subdivisions < 1 || subdivisions > 64) return Violated("subdivisions", subdivisions, "in [1, 64]");
  if (position_bits < 8 || position_bits > 21) return Violated("position_bits", position_bits, "in [8, 21]");
  if (normal_bits < 4 || normal_bits > 16) return Violated("normal_bits", normal_bits, "in [4, 16]");
  if (compression_level < 0 || compression_level > 10)
    return Violated("compression_level", compression_level, "in [0, 10]");
  return Status::Ok();
}

Eigen::Vector3i VoxelOfDecodedPoint(const Eigen::Vector3f& position, double voxel_m) {
  return Eigen::Vector3i(static_cast<int>(std::floor(position.x() / voxel_m)),
                         static_cast<int>(std::floor(position.y() / voxel_m)),
                         static_cast<int>(std::floor(position.z() / voxel_m)));
}

StatusOr<EncodedMapChunk> EncodeMapChunk(const PointCloud& cloud, const MapChunkCodecOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!cloud.IsConsistent()) return InvalidArgumentError("EncodeMapChunk: attribute arrays do not match positions");
  const double step = options.grid_step_m();
  const int64_t half = int64_t{1} << (options.position_bits - 1);
  const int k = options.subdivisions;

  // Grid cell of every point: its voxel, then the cell inside the voxel (clamped, so that rounding
  // never moves a point into a neighbouring voxel).
  EncodedMapChunk out;
  std::vector<std::array<uint32_t, 3>> cells;
  std::vector<uint64_t> codes;
  std::vector<uint32_t> kept;
  cells.reserve(cloud.size());
  codes.reserve(cloud.size());
  kept.reserve(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f& p = cloud.positions[i];
    if (!p.allFinite()) {
      ++out.dropped_points;
      continue;
    }
    std::array<uint32_t, 3> u{};
    bool inside = true;
    for (int a = 0; a < 3; ++a) {
      const double voxel = std::floor(p[a] / options.voxel_m);
      const double in_voxel = p[a] - voxel * options.voxel_m;
      const double cell = std::clamp(std::floor(in_voxel / step), 0.0, static_cast<double>(k - 1));
      const double g = voxel * k + cell;
      if (!(g > -static_cast<double>(half) && g < static_cast<double>(half - 1))) {
        inside = false;
        break;
      }
      u[a] = static_cast<uint32_t>(static_cast<int64_t>(g) + half);
    }
    if (!inside) {
      ++out.dropped_points;
      continue;
    }
    kept.push_back(static_cast<uint32_t>(i));
    cells.push_back(u);
    codes.push_back(MortonCode(u[0], u[1], u[2]));
  }
  std::vector<uint32_t> sorted(kept.size());
  std::iota(sorted.begin(), sorted.end(), 0u);
  std::sort(sorted.begin(), sorted.end(), [&](uint32_t a, uint32_t b) { return codes[a] < codes[b]; });

  const size_t n = kept.size();
  if (n == 0)
    return FailedPreconditionError("EncodeMapChunk: no point to encode (" + std::to_string(out.dropped_points) +
                                   " dropped: non-finite or outside the grid)");
  draco::PointCloudBuilder builder;
  builder.Start(static_cast<draco::PointIndex::ValueType>(n));
  const int position_att = builder.AddAttribute(draco::GeometryAttribute::POSITION, 3, draco::DT_FLOAT32);
  const int normal_att =
      cloud.HasNormals() ? builder.AddAttribute(draco::GeometryAttribute::NORMAL, 3, draco::DT_FLOAT32) : -1;
  const int color_att =
      cloud.HasColors() ? builder.AddAttribute(draco::GeometryAttribute::COLOR, 3, draco::DT_UINT8) : -1;
  // Grid value of cell u: origin + u * step, origin = (-half + 0.5) * step (cell centres).
  const double origin = (-static_cast<double>(half) + 0.5) * step;
  out.order.resize(n);
  for (size_t j = 0; j < n; ++j) {
    const uint32_t s = sorted[j];
    const uint32_t i = kept[s];
    out.order[j] = i;
    const draco::PointIndex pi(static_cast<uint32_t>(j));
    float position[3];
    for (int a = 0; a < 3; ++a) position[a] = static_cast<float>(origin + static_cast<double>(cells[s][a]) * step);
    builder.SetAttributeValueForPoint(position_att, pi, position);
    if (normal_att >= 0) {
      Eigen::Vector3f nrm = cloud.normals[i];
      if (!nrm.allFinite() || nrm.squaredNorm() < 1e-12f) nrm.setZero();
      else nrm.normalize();
      builder.SetAttributeValueForPoint(normal_att, pi, nrm.data());
    }
    if (color_att >= 0) builder.SetAttributeValueForPoint(color_att, pi, cloud.colors[i].data());
  }
  std::unique_ptr<draco::PointCloud> pc = builder.Finalize(/*deduplicate_points=*/false);
  if (!pc) return InternalError("EncodeMapChunk: Draco point cloud builder failed");

  draco::Encoder encoder;
  encoder.SetEncodingMethod(draco::POINT_CLOUD_SEQUENTIAL_ENCODING);
  const int speed = 10 - options.compression_level;
  encoder.SetSpeedOptions(speed, speed);
  const float draco_origin[3] = {static_cast<float>(origin), static_cast<float>(origin), static_cast<float>(origin)};
  const float range = static_cast<float>(step * static_cast<double>((int64_t{1} << options.position_bits) - 1));
  encoder.SetAttributeExplicitQuantization(draco::GeometryAttribute::POSITION, options.position_bits, 3, draco_origin,
                                           range);
  if (normal_att >= 0) encoder.SetAttributeQuantization(draco::GeometryAttribute::NORMAL, options.normal_bits);
  draco::EncoderBuffer buffer;
  const draco::Status st = encoder.EncodePointCloudToBuffer(*pc, &buffer);
  if (!st.ok()) return InternalError(std::string("Draco encoding failed: ") + st.error_msg());
  out.bytes.assign(buffer.data(), buffer.data() + buffer.size());
  out.num_points = n;
  return out;
}

StatusOr<PointCloud> DecodeMapChunk(const uint8_t* data, size_t size) {
  if (data == nullptr || size == 0) return DataLossError("empty map chunk");
  // Draco sizes its attribute buffers from the point count the stream claims, before reading them: 15
  // bytes could ask for gigabytes (found by fuzz/fuzz_draco_chunk). A map chunk is a Draco 2.x point
  // cloud without metadata, so the int32 point count follows the 11-byte header; it is bounded by the
  // bytes that would have to carry the points (>= 1 bit each; real chunks use ~35) and kMaxChunkPoints.
  constexpr size_t kHeaderBytes = 11;
  constexpr int64_t kMaxChunkPoints = int64_t{1} << 24;
  if (size < kHeaderBytes + 4 || std::memcmp(data, "DRACO", 5) != 0)
    return DataLossError("corrupt map chunk: no Draco header");
  // Version 2.2+ (what EncodeMapChunk writes), a point cloud, sequential coding: fuzzing found older
  // versions and the kd-tree decoder asking for tens of GB, so nothing else is handed to Draco.
  if (data[5] != 2 || data[6] < 2)
    return DataLossError("corrupt map chunk: Draco version " + std::to_string(data[5]) + "." + std::to_string(data[6]) +
                         ", expected 2.2 or later");
  if (data[7] != 0) return InvalidArgumentError("map chunk is a Draco mesh, not a point cloud");
  if (data[8] != 0)
    return InvalidArgumentError("map chunk is not sequentially coded (Draco method " + std::to_string(data[8]) + ")");
  if ((data[9] | (data[10] << 8)) & 0x8000) return InvalidArgumentError("map chunk carries Draco metadata");
  int32_t claimed_points = 0;
  std::memcpy(&claimed_points, data + kHeaderBytes, sizeof(claimed_points));
  if (claimed_points < 0 || claimed_points > kMaxChunkPoints ||
      static_cast<uint64_t>(claimed_points) > 8 * static_cast<uint64_t>(size) + 64)
    return DataLossError("corrupt map chunk: claims " + std::to_string(claimed_points) + " points in " +
                         std::to_string(size) + " bytes");
  return DecodeDracoPointCloud(data, size, DracoAttributes::kStrict, "map chunk");
}

}  // namespace prism
