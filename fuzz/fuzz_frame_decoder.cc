// libFuzzer target: the frame decoders (PNG, JPEG 4:4:4, raw) with the size checks before decoding.
// Input: [codec byte][width byte][height byte][image bytes]; width and height in [1, 256].
#include <cstdint>

#include <opencv2/core.hpp>

#include "core/codec/frame_codec.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 3) return 0;
  const prism::FrameCodec codec = data[0] % 3 == 0   ? prism::FrameCodec::kPng
                                  : data[0] % 3 == 1 ? prism::FrameCodec::kJpeg
                                                     : prism::FrameCodec::kRaw;
  const int width = 1 + data[1], height = 1 + data[2];
  cv::Mat rgb;
  const prism::Status s = prism::DecodeFrame(data + 3, size - 3, codec, width, height, &rgb);
  if (s.ok() && (rgb.cols != width || rgb.rows != height || rgb.type() != CV_8UC3)) __builtin_trap();
  return 0;
}
