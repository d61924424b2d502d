#include "core/geometry/point_cloud.h"

namespace prism {

bool PointCloud::IsConsistent() const {
  const size_t n = positions.size();
  return (normals.empty() || normals.size() == n) && (colors.empty() || colors.size() == n) &&
         (confidences.empty() || confidences.size() == n);
}

}  // namespace prism
