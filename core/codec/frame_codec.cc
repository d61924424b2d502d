#include "core/codec/frame_codec.h"

#include <jpeglib.h>

#include <csetjmp>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace prism {
namespace {

std::string SizeText(int w, int h) { return std::to_string(w) + "x" + std::to_string(h); }

// libjpeg reports errors through error_exit (must not return): jump back with the message kept.
// Warnings (e.g. "premature end of data", which libjpeg pads over) are counted and treated as
// corruption by the decoder.
struct JpegErrorManager {
  jpeg_error_mgr mgr;
  std::jmp_buf jump;
  char message[JMSG_LENGTH_MAX];
};

void JpegErrorExit(j_common_ptr cinfo) {
  auto* err = reinterpret_cast<JpegErrorManager*>(cinfo->err);
  (*cinfo->err->format_message)(cinfo, err->message);
  std::longjmp(err->jump, 1);
}

void JpegOutputMessage(j_common_ptr cinfo) {
  auto* err = reinterpret_cast<JpegErrorManager*>(cinfo->err);
  (*cinfo->err->format_message)(cinfo, err->message);  // kept, never printed
}

void InstallErrorManager(j_common_ptr cinfo, JpegErrorManager* err) {
  cinfo->err = jpeg_std_error(&err->mgr);
  err->mgr.error_exit = JpegErrorExit;
  err->mgr.output_message = JpegOutputMessage;
  err->message[0] = '\0';
}

// Returns false with err->message set on a libjpeg error. No C++ object with a destructor lives in
// this frame across setjmp.
bool JpegEncode(const cv::Mat& rgb, int quality, unsigned char** buffer, unsigned long* length, JpegErrorManager* err) {
  jpeg_compress_struct cinfo;
  InstallErrorManager(reinterpret_cast<j_common_ptr>(&cinfo), err);
  if (setjmp(err->jump)) {
    jpeg_destroy_compress(&cinfo);
    return false;
  }
  jpeg_create_compress(&cinfo);
  jpeg_mem_dest(&cinfo, buffer, length);
  cinfo.image_width = static_cast<JDIMENSION>(rgb.cols);
  cinfo.image_height = static_cast<JDIMENSION>(rgb.rows);
  cinfo.input_components = 3;
  cinfo.in_color_space = JCS_RGB;
  jpeg_set_defaults(&cinfo);
  jpeg_set_quality(&cinfo, quality, TRUE);
  // 4:4:4: every component at full resolution (libjpeg's default is 2x2 for chroma, i.e. 4:2:0).
  for (int c = 0; c < cinfo.num_components; ++c) {
    cinfo.comp_info[c].h_samp_factor = 1;
    cinfo.comp_info[c].v_samp_factor = 1;
  }
  jpeg_start_compress(&cinfo, TRUE);
  while (cinfo.next_scanline < cinfo.image_height) {
    JSAMPROW row = const_cast<JSAMPROW>(rgb.ptr<uint8_t>(static_cast<int>(cinfo.next_scanline)));
    jpeg_write_scanlines(&cinfo, &row, 1);
  }
  jpeg_finish_compress(&cinfo);
  jpeg_destroy_compress(&cinfo);
  return true;
}

enum class JpegDecodeResult { kOk, kError, kWrongSize, kNotColour, kSubsampled, kWarning };

JpegDecodeResult JpegDecode(const uint8_t* data, size_t size, int expected_width, int expected_height, cv::Mat* rgb,
                            JpegErrorManager* err, int* width, int* height) {
  jpeg_decompress_struct cinfo;
  InstallErrorManager(reinterpret_cast<j_common_ptr>(&cinfo), err);
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

const char* FrameCodecName(FrameCodec codec) {
  switch (codec) {
    case FrameCodec::kPng:
      return "png";
    case FrameCodec::kJpeg:
      return "jpeg";
    case FrameCodec::kRaw:
      return "raw";
  }
  return "?";
}

StatusOr<FrameCodec> ParseFrameCodec(const std::string& name) {
  if (name == "png") return FrameCodec::kPng;
  if (name == "jpeg" || name == "jpg") return FrameCodec::kJpeg;
  if (name == "raw") return FrameCodec::kRaw;
  return InvalidArgumentError("unknown frame codec '" + name + "' (png, jpeg or raw)");
}

Status FrameEncodeOptions::Check() const {
  if (jpeg_quality < 1 || jpeg_quality > 100)
    return InvalidArgumentError("FrameEncodeOptions.jpeg_quality = " + std::to_string(jpeg_quality) +
                                "; violated: in [1, 100]");
  if (png_compression < 0 || png_compression > 9)
    return InvalidArgumentError("FrameEncodeOptions.png_compression = " + std::to_string(png_compression) +
                                "; violated: in [0, 9]");
  return Status::Ok();
}

Status EncodeFrame(const cv::Mat& rgb, const FrameEncodeOptions& options, std::vector<uint8_t>* out) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (rgb.empty() || rgb.type() != CV_8UC3) return InvalidArgumentError("EncodeFrame: image must be non-empty CV_8UC3");
  const cv::Mat image = rgb.isContinuous() ? rgb : rgb.clone();
  switch (options.codec) {
    case FrameCodec::kRaw: {
      out->assign(image.data, image.data + image.total() * 3);
      return Status::Ok();
    }
    case FrameCodec::kPng: {
      cv::Mat bgr;
      cv::cvtColor(image, bgr, cv::COLOR_RGB2BGR);
      if (!cv::imencode(".png", bgr, *out, {cv::IMWRITE_PNG_COMPRESSION, options.png_compression}))
        return InternalError("PNG encoding failed");
      return Status::Ok();
    }
    case FrameCodec::kJpeg: {
      JpegErrorManager err;
      unsigned char* buffer = nullptr;
      unsigned long length = 0;
      const bool ok = JpegEncode(image, options.jpeg_quality, &buffer, &length, &err);
      if (ok) out->assign(buffer, buffer + length);
      std::free(buffer);
      if (!ok) return InternalError(std::string("JPEG encoding failed: ") + err.message);
      return Status::Ok();
    }
  }
  return InvalidArgumentError("EncodeFrame: unknown codec");
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
