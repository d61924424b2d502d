#include "core/codec/draco_cloud.h"

#include <draco/compression/decode.h>

namespace prism {

StatusOr<PointCloud> DecodeDracoPointCloud(const uint8_t* data, size_t size, DracoAttributes attributes,
                                           const std::string& what) {
  if (data == nullptr || size == 0) return DataLossError(what + ": empty");
  const bool strict = attributes == DracoAttributes::kStrict;
  draco::DecoderBuffer buffer;
  buffer.Init(reinterpret_cast<const char*>(data), size);
  draco::Decoder decoder;
  auto decoded = decoder.DecodePointCloudFromBuffer(&buffer);
  if (!decoded.ok())
    return DataLossError(what + ": not a readable Draco point cloud (" + decoded.status().error_msg() + ")");
  const draco::PointCloud& pc = *decoded.value();
  const draco::PointAttribute* position = pc.GetNamedAttribute(draco::GeometryAttribute::POSITION);
  if (position == nullptr || position->num_components() != 3 || (strict && position->data_type() != draco::DT_FLOAT32))
    return InvalidArgumentError(what + ": no 3D " + (strict ? "float " : "") + "positions");
  const draco::PointAttribute* normal = pc.GetNamedAttribute(draco::GeometryAttribute::NORMAL);
  const draco::PointAttribute* color = pc.GetNamedAttribute(draco::GeometryAttribute::COLOR);
  // Strict: the attribute types EncodeMapChunk writes; anything else (e.g. DT_BOOL, whose conversion
  // reads arbitrary bytes as bool: undefined behaviour found by fuzzing) is refused.
  const bool normal_ok =
      normal == nullptr || (normal->num_components() == 3 && (!strict || normal->data_type() == draco::DT_FLOAT32));
  const bool color_ok = color == nullptr || (color->num_components() >= 3 && color->num_components() <= 4 &&
                                             (!strict || color->data_type() == draco::DT_UINT8));
  if (strict && !normal_ok) return InvalidArgumentError(what + ": normals are not 3 floats");
  if (strict && !color_ok) return InvalidArgumentError(what + ": colours are not 3 or 4 bytes");
  if (!normal_ok) normal = nullptr;
  if (!color_ok) color = nullptr;
  const size_t n = pc.num_points();
  PointCloud cloud;
  cloud.positions.resize(n);
  if (normal) cloud.normals.resize(n);
  if (color) cloud.colors.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const draco::PointIndex pi(static_cast<uint32_t>(i));
    if (!position->ConvertValue<float, 3>(position->mapped_index(pi), cloud.positions[i].data()))
      return DataLossError(what + ": unreadable position " + std::to_string(i));
    if (normal && !normal->ConvertValue<float, 3>(normal->mapped_index(pi), cloud.normals[i].data()))
      return DataLossError(what + ": unreadable normal " + std::to_string(i));
    if (color) {
      uint8_t rgba[4] = {0, 0, 0, 0};
      if (!color->ConvertValue<uint8_t>(color->mapped_index(pi), color->num_components(), rgba))
        return DataLossError(what + ": unreadable colour " + std::to_string(i));
      cloud.colors[i] = Eigen::Matrix<uint8_t, 3, 1>(rgba[0], rgba[1], rgba[2]);
    }
  }
  return cloud;
}

}  // namespace prism
