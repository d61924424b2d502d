// The one Draco point-cloud decoder: map chunks (core/codec/map_chunk_codec.h) and .drc files
// (core/io/draco_io.h) both read their points here. Positions, and normals and colours when present.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "core/geometry/point_cloud.h"
#include "core/util/status.h"

namespace prism {

enum class DracoAttributes {
  // Positions must be 3 floats, normals 3 floats and colours 3 or 4 bytes; anything else is refused
  // (INVALID_ARGUMENT). Untrusted input: map chunks from the network.
  kStrict,
  // Positions of any numeric type with 3 components; normals or colours of another shape are left out.
  // Files from other tools (Open3D, draco_encoder), meshes too (their vertices).
  kLenient,
};

// Decodes `size` bytes of a Draco point cloud or mesh. `what` names the source in messages (a path,
// "map chunk"). DATA_LOSS when Draco cannot read the bytes or an attribute value; INVALID_ARGUMENT when
// there are no 3D positions (or, kStrict, an attribute of an unexpected type or shape).
StatusOr<PointCloud> DecodeDracoPointCloud(const uint8_t* data, size_t size, DracoAttributes attributes,
                                           const std::string& what);

}  // namespace prism
