// PLY point clouds and meshes, and mesh files in OFF and OBJ.
// Reading: ASCII, binary little- and big-endian; vertex properties x y z, nx ny nz, red green blue
// (uchar), confidence (float), any scalar type; faces as a list property vertex_indices/vertex_index
// (polygons are fan-triangulated). Writing: binary little-endian, float positions.
#pragma once

#include <string>

#include "core/geometry/point_cloud.h"
#include "core/geometry/triangle_mesh.h"
#include "core/util/status.h"

namespace prism {

StatusOr<PointCloud> ReadPointCloudPly(const std::string& path);
Status WritePointCloudPly(const std::string& path, const PointCloud& cloud);

// Reads .off, .ply or .obj (by extension, case-insensitive).
StatusOr<TriangleMesh> ReadTriangleMesh(const std::string& path);
Status WriteTriangleMeshPly(const std::string& path, const TriangleMesh& mesh);

}  // namespace prism
