// Whether two images hold the same pixels, byte for byte: how the SLAM recognises a keyframe image it
// has already processed (the tracker's pyramid, the depth filter's image parts) without keeping track
// of where each image came from.
#pragma once

#include <cstddef>
#include <cstring>

#include <opencv2/core.hpp>

namespace prism {

// Same size, same type and the same bytes in every row (strides may differ).
inline bool SameImageBytes(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  const size_t row_bytes = static_cast<size_t>(a.cols) * a.elemSize();
  for (int y = 0; y < a.rows; ++y)
    if (std::memcmp(a.ptr(y), b.ptr(y), row_bytes) != 0) return false;
  return true;
}

}  // namespace prism
