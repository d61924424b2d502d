#include "core/io/draco_io.h"

#include <fstream>
#include <iterator>
#include <vector>

#include <draco/compression/config/compression_shared.h>
#include <draco/compression/encode.h>
#include <draco/point_cloud/point_cloud_builder.h>

#include "core/codec/draco_cloud.h"

namespace prism {

Status DracoFileOptions::Check() const {
  auto bad = [](const std::string& field, int v, const std::string& rule) {
    return InvalidArgumentError("DracoFileOptions." + field + " = " + std::to_string(v) + "; violated: " + rule);
  };
  if (position_bits < 0 || position_bits > 30) return bad("position_bits", position_bits, "in [0, 30]");
  if (normal_bits < 0 || normal_bits > 30) return bad("normal_bits", normal_bits, "in [0, 30]");
  if (speed < 0 || speed > 10) return bad("speed", speed, "in [0, 10]");
  return Status::Ok();
}

Status WritePointCloudDraco(const std::string& path, const PointCloud& cloud, const DracoFileOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!cloud.IsConsistent()) return InvalidArgumentError("point cloud attributes do not match its size");
  if (cloud.empty()) return InvalidArgumentError("Draco cannot store an empty point cloud");
  draco::PointCloudBuilder builder;
  builder.Start(static_cast<draco::PointIndex::ValueType>(cloud.size()));
  const int position_att = builder.AddAttribute(draco::GeometryAttribute::POSITION, 3, draco::DT_FLOAT32);
  const int normal_att =
      cloud.HasNormals() ? builder.AddAttribute(draco::GeometryAttribute::NORMAL, 3, draco::DT_FLOAT32) : -1;
  const int color_att =
      cloud.HasColors() ? builder.AddAttribute(draco::GeometryAttribute::COLOR, 3, draco::DT_UINT8) : -1;
  for (size_t i = 0; i < cloud.size(); ++i) {
    const draco::PointIndex pi(static_cast<uint32_t>(i));
    builder.SetAttributeValueForPoint(position_att, pi, cloud.positions[i].data());
    if (normal_att >= 0) builder.SetAttributeValueForPoint(normal_att, pi, cloud.normals[i].data());
    if (color_att >= 0) builder.SetAttributeValueForPoint(color_att, pi, cloud.colors[i].data());
  }
  std::unique_ptr<draco::PointCloud> pc = builder.Finalize(/*deduplicate_points=*/false);
  if (!pc) return InternalError("Draco could not build the point cloud");
  draco::Encoder encoder;
  encoder.SetEncodingMethod(options.keep_order ? draco::POINT_CLOUD_SEQUENTIAL_ENCODING
                                               : draco::POINT_CLOUD_KD_TREE_ENCODING);
  encoder.SetSpeedOptions(options.speed, options.speed);
  // The kd-tree coder needs quantised positions.
  const int position_bits = options.position_bits == 0 && !options.keep_order ? 30 : options.position_bits;
  if (position_bits > 0) encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, position_bits);
  if (normal_att >= 0 && options.normal_bits > 0)
    encoder.SetAttributeQuantization(draco::GeometryAttribute::NORMAL, options.normal_bits);
  draco::EncoderBuffer buffer;
  const draco::Status st = encoder.EncodePointCloudToBuffer(*pc, &buffer);
  if (!st.ok()) return InternalError(std::string("Draco encoding failed: ") + st.error_msg());
  std::ofstream out(path, std::ios::binary);
  if (!out) return UnavailableError("cannot write '" + path + "'");
  out.write(buffer.data(), static_cast<std::streamsize>(buffer.size()));
  if (!out) return UnavailableError("write failed: '" + path + "'");
  return Status::Ok();
}

StatusOr<PointCloud> ReadPointCloudDraco(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return NotFoundError("cannot open '" + path + "'");
  const std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (bytes.empty()) return DataLossError(path + ": empty file");
  // A mesh file decodes as a point cloud too (its vertices).
  return DecodeDracoPointCloud(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), DracoAttributes::kLenient,
                               path);
}

}  // namespace prism
