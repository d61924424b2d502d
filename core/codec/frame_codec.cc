#include "core/codec/frame_codec.h"

#include <jpeglib.h>

#include <csetjmp>
#include <cstdio>
#include <cstring>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/codec/jpeg_errors.h"

namespace prism {
namespace {

std::string SizeText(int w, int h) { return std::to_string(w) + "x" + std::to_string(h); }

using internal::InstallJpegErrorManager;
using internal::JpegErrorManager;

enum class JpegDecodeResult { kOk, kError, kWrongSize, kNotColour, kSubsampled, kWarning };

JpegDecodeResult JpegDecode(const uint8_t* data, size_t size, int expected_width, int expected_height, cv::Mat* rgb,
                            JpegErrorManager* err, int* width, int* height) {
  jpeg_decompress_struct cinfo;
  InstallJpegErrorManager(reinterpret_cast<j_common_ptr>(&cinfo), err);
  if (setjmp(err->jump)) {
    jpeg_destroy_decompress(&cinfo);
    return JpegDecodeResult::kError;
  }
  jpeg_create_decompress(&cinfo);
  jpeg_mem_src(&cinfo, data, static_cast<unsigned long>(size));
  if (jpeg_read_header(&cinfo, TRUE) != JPEG_HEADER_OK) {
    jpeg_destroy_decompress(&cinfo);
    return JpegDecodeResult::kError;
  }
  *width = static_cast<int>(cinfo.image_width);
  *height = static_cast<int>(cinfo.image_height);
  JpegDecodeResult verdict = JpegDecodeResult::kOk;
  if (*width != expected_width || *height != expected_height) verdict = JpegDecodeResult::kWrongSize;
  else if (cinfo.num_components != 3 || cinfo.data_precision != 8) verdict = JpegDecodeResult::kNotColour;
  else
    for (int c = 0; c < 3; ++c)
      if (cinfo.comp_info[c].h_samp_factor != cinfo.max_h_samp_factor ||
          cinfo.comp_info[c].v_samp_factor != cinfo.max_v_samp_factor)
        verdict = JpegDecodeResult::kSubsampled;
  if (verdict != JpegDecodeResult::kOk) {
    jpeg_destroy_decompress(&cinfo);
    return verdict;
  }
  cinfo.out_color_space = JCS_RGB;
  jpeg_start_decompress(&cinfo);
  rgb->create(expected_height, expected_width, CV_8UC3);
  while (cinfo.output_scanline < cinfo.output_height) {
    JSAMPROW row = rgb->ptr<uint8_t>(static_cast<int>(cinfo.output_scanline));
    jpeg_read_scanlines(&cinfo, &row, 1);
  }
  jpeg_finish_decompress(&cinfo);
  const bool warned = cinfo.err->num_warnings > 0;
  jpeg_destroy_decompress(&cinfo);
  return warned ? JpegDecodeResult::kWarning : JpegDecodeResult::kOk;
}

uint32_t ReadBigEndian32(const uint8_t* p) {
  return (uint32_t{p[0]} << 24) | (uint32_t{p[1]} << 16) | (uint32_t{p[2]} << 8) | uint32_t{p[3]};
}

Status DecodePng(const uint8_t* data, size_t size, int expected_width, int expected_height, cv::Mat* rgb) {
  static constexpr uint8_t kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  // Signature, IHDR length and type, width, height, bit depth, colour type.
  if (size < 26 || std::memcmp(data, kSignature, 8) != 0 || std::memcmp(data + 12, "IHDR", 4) != 0)
    return InvalidArgumentError("corrupt PNG: no PNG signature and IHDR header (" + std::to_string(size) + " bytes)");
  const uint32_t width = ReadBigEndian32(data + 16), height = ReadBigEndian32(data + 20);
  if (width != static_cast<uint32_t>(expected_width) || height != static_cast<uint32_t>(expected_height))
    return InvalidArgumentError("PNG is " + std::to_string(width) + "x" + std::to_string(height) +
                                ", the session's camera is " + SizeText(expected_width, expected_height));
  const int bit_depth = data[24], colour_type = data[25];
  if (bit_depth != 8 || colour_type != 2)
    return InvalidArgumentError("PNG must be 8-bit RGB (bit depth 8, colour type 2); got bit depth " +
                                std::to_string(bit_depth) + ", colour type " + std::to_string(colour_type));
  const cv::Mat encoded(1, static_cast<int>(size), CV_8U, const_cast<uint8_t*>(data));
  cv::Mat bgr;
  try {
    bgr = cv::imdecode(encoded, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    return InvalidArgumentError(std::string("corrupt PNG: ") + e.what());
  }
  if (bgr.empty()) return InvalidArgumentError("corrupt or truncated PNG (" + std::to_string(size) + " bytes)");
  if (bgr.type() != CV_8UC3 || bgr.cols != expected_width || bgr.rows != expected_height)
    return InvalidArgumentError("PNG did not decode to 8-bit RGB of " + SizeText(expected_width, expected_height));
  cv::cvtColor(bgr, *rgb, cv::COLOR_BGR2RGB);
  return Status::Ok();
}

}  // namespace

Status EncodeFrame(const cv::Mat& rgb, const FrameEncodeOptions& options, std::vector<uint8_t>* out) {
  if (rgb.empty() || rgb.type() != CV_8UC3) return InvalidArgumentError("EncodeFrame: image must be non-empty CV_8UC3");
  return EncodeRgbFrame(rgb.data, rgb.cols, rgb.rows, rgb.step, options, out);
}

Status DecodeFrame(const uint8_t* data, size_t size, FrameCodec codec, int expected_width, int expected_height,
                   cv::Mat* rgb) {
  if (expected_width <= 0 || expected_height <= 0)
    return InvalidArgumentError("DecodeFrame: expected size must be positive, got " +
                                SizeText(expected_width, expected_height));
  if (data == nullptr || size == 0)
    return InvalidArgumentError(std::string("empty ") + FrameCodecName(codec) + " frame");
  switch (codec) {
    case FrameCodec::kRaw: {
      const size_t expected = static_cast<size_t>(expected_width) * expected_height * 3;
      if (size != expected)
        return InvalidArgumentError("raw frame has " + std::to_string(size) + " bytes; " +
                                    SizeText(expected_width, expected_height) + " RGB needs " +
                                    std::to_string(expected));
      rgb->create(expected_height, expected_width, CV_8UC3);
      std::memcpy(rgb->data, data, size);
      return Status::Ok();
    }
    case FrameCodec::kPng:
      return DecodePng(data, size, expected_width, expected_height, rgb);
    case FrameCodec::kJpeg: {
      JpegErrorManager err;
      int width = 0, height = 0;
      switch (JpegDecode(data, size, expected_width, expected_height, rgb, &err, &width, &height)) {
        case JpegDecodeResult::kOk:
          return Status::Ok();
        case JpegDecodeResult::kError:
          return InvalidArgumentError(std::string("corrupt JPEG: ") + (err.message[0] ? err.message : "bad header"));
        case JpegDecodeResult::kWarning:
          return InvalidArgumentError(std::string("corrupt or truncated JPEG: ") + err.message);
        case JpegDecodeResult::kWrongSize:
          return InvalidArgumentError("JPEG is " + SizeText(width, height) + ", the session's camera is " +
                                      SizeText(expected_width, expected_height));
        case JpegDecodeResult::kNotColour:
          return InvalidArgumentError("JPEG must be 8-bit, 3 components");
        case JpegDecodeResult::kSubsampled:
          return InvalidArgumentError(
              "JPEG uses chroma subsampling; only 4:4:4 is accepted (subsampled chroma destroys the photometric "
              "signal)");
      }
      break;
    }
  }
  return InvalidArgumentError("DecodeFrame: unknown codec");
}

}  // namespace prism
