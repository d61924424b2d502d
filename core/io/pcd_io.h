// Point clouds in PCL's PCD format (v0.7), the format PCL tools and ROS use.
// Writing: fields x y z [normal_x normal_y normal_z curvature] [rgb], rgb packed as PCL 1.13 writes it
// (TYPE U, 0x00RRGGBB); binary (default) or ASCII. Reading: ASCII and binary (not binary_compressed), any
// field order and scalar type/size, unknown fields skipped; rgb or rgba packed, or separate r g b.
#pragma once

#include <string>

#include "core/geometry/point_cloud.h"
#include "core/util/status.h"

namespace prism {

enum class PcdEncoding { kBinary, kAscii };

StatusOr<PointCloud> ReadPointCloudPcd(const std::string& path);
Status WritePointCloudPcd(const std::string& path, const PointCloud& cloud,
                          PcdEncoding encoding = PcdEncoding::kBinary);

}  // namespace prism
