// Frame encoding for the uplink, without OpenCV (the client SDK's encoder; core/codec/frame_codec.h adds
// cv::Mat and decoding): PNG (lossless, libpng), JPEG with 4:4:4 chroma sampling only (libjpeg;
// subsampled chroma halves the colour resolution, and photometric stereo reads its normals from the
// colour ratios), and raw RGB.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/util/status.h"

namespace prism {

enum class FrameCodec {
  kPng,   // lossless
  kJpeg,  // baseline JPEG, 4:4:4 (no chroma subsampling)
  kRaw,   // width * height * 3 bytes, RGB, row-major
};
const char* FrameCodecName(FrameCodec codec);  // "png", "jpeg", "raw"
// INVALID_ARGUMENT for anything but "png", "jpeg" or "raw".
StatusOr<FrameCodec> ParseFrameCodec(const std::string& name);

struct FrameEncodeOptions {
  FrameCodec codec = FrameCodec::kPng;
  // JPEG quality in [1, 100].
  int jpeg_quality = 95;
  // PNG compression level in [0, 9]; 1 is several times faster than 6 and ~10% larger.
  int png_compression = 1;

  Status Check() const;
};

// Encodes an 8-bit RGB image (R first) whose rows are `stride_bytes` apart (>= width * 3). `out` is
// overwritten (its capacity is reused across calls). INVALID_ARGUMENT on a null image, a size outside
// [1, 65535] or a short stride.
Status EncodeRgbFrame(const uint8_t* rgb, int width, int height, size_t stride_bytes, const FrameEncodeOptions& options,
                      std::vector<uint8_t>* out);

}  // namespace prism
