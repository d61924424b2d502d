// Frame codecs for the uplink: PNG (lossless), JPEG with 4:4:4 chroma sampling only (subsampled
// chroma halves the colour resolution, and photometric stereo reads its normals from the colour
// ratios), and raw RGB. Images in memory are CV_8UC3 in RGB order (core/io/image_io.h).
//
// Decoding validates untrusted bytes: the size in the header is checked against the expected size
// before anything is decompressed, and every failure is a Status, never a crash or a CHECK.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

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

// rgb: CV_8UC3, RGB. INVALID_ARGUMENT on another type or an empty image. `out` is overwritten (its
// capacity is reused across calls).
Status EncodeFrame(const cv::Mat& rgb, const FrameEncodeOptions& options, std::vector<uint8_t>* out);

// Decodes `size` bytes into *rgb (CV_8UC3, RGB, reallocated only when its size or type differs).
// INVALID_ARGUMENT when the data is corrupt or truncated, is not of `codec`, has another size than
// expected_width x expected_height, is not 8-bit colour, or (JPEG) uses chroma subsampling.
Status DecodeFrame(const uint8_t* data, size_t size, FrameCodec codec, int expected_width, int expected_height,
                   cv::Mat* rgb);

}  // namespace prism
