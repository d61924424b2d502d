// Frame codecs for the uplink on cv::Mat: the encoders of core/codec/frame_encoder.h (PNG, JPEG 4:4:4,
// raw) and the server's decoders. Images in memory are CV_8UC3 in RGB order (core/io/image_io.h).
//
// Decoding validates untrusted bytes: the size in the header is checked against the expected size
// before anything is decompressed, and every failure is a Status, never a crash or a CHECK.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "core/codec/frame_encoder.h"
#include "core/util/status.h"

namespace prism {

// rgb: CV_8UC3, RGB. INVALID_ARGUMENT on another type or an empty image. `out` is overwritten (its
// capacity is reused across calls).
Status EncodeFrame(const cv::Mat& rgb, const FrameEncodeOptions& options, std::vector<uint8_t>* out);

// Decodes `size` bytes into *rgb (CV_8UC3, RGB, reallocated only when its size or type differs).
// INVALID_ARGUMENT when the data is corrupt or truncated, is not of `codec`, has another size than
// expected_width x expected_height, is not 8-bit colour, or (JPEG) uses chroma subsampling.
Status DecodeFrame(const uint8_t* data, size_t size, FrameCodec codec, int expected_width, int expected_height,
                   cv::Mat* rgb);

}  // namespace prism
