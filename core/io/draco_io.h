// Point clouds as Draco files (.drc, Google's compressed geometry; Debian's draco_decoder, Open3D's
// and three.js' loaders read them). Positions, normals and colours; quantised (lossy) by default.
#pragma once

#include <string>

#include "core/geometry/point_cloud.h"
#include "core/util/status.h"

namespace prism {

struct DracoFileOptions {
  // Position quantisation bits per axis over the cloud's bounding box, in [1, 30]; 0 = no quantisation
  // (lossless float positions, larger files). 14 bits on a 1 m object = 0.06 mm steps.
  int position_bits = 14;
  // Normal quantisation bits (octahedral), in [1, 30]; 0 = lossless floats.
  int normal_bits = 10;
  // Draco's speed/compression trade-off, in [0 (best compression), 10 (fastest)].
  int speed = 5;
  // Sequential coding keeps the point order (a round trip restores it); false uses the kd-tree coder,
  // smaller but reordered.
  bool keep_order = true;

  Status Check() const;
};

StatusOr<PointCloud> ReadPointCloudDraco(const std::string& path);
Status WritePointCloudDraco(const std::string& path, const PointCloud& cloud, const DracoFileOptions& options = {});

}  // namespace prism
