#include "core/codec/frame_encoder.h"

#include <jpeglib.h>
#include <png.h>
#include <zlib.h>

#include <csetjmp>
#include <cstdlib>
#include <cstring>

#include "core/codec/jpeg_errors.h"

namespace prism {
namespace {

using internal::JpegErrorManager;

// Returns false with err->message set on a libjpeg error. No C++ object with a destructor lives in
// this frame across setjmp.
bool JpegEncode(const uint8_t* rgb, int width, int height, size_t stride, int quality, unsigned char** buffer,
                unsigned long* length, JpegErrorManager* err) {
  jpeg_compress_struct cinfo;
  internal::InstallJpegErrorManager(reinterpret_cast<j_common_ptr>(&cinfo), err);
  if (setjmp(err->jump)) {
    jpeg_destroy_compress(&cinfo);
    return false;
  }
  jpeg_create_compress(&cinfo);
  jpeg_mem_dest(&cinfo, buffer, length);
  cinfo.image_width = static_cast<JDIMENSION>(width);
  cinfo.image_height = static_cast<JDIMENSION>(height);
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
    JSAMPROW row = const_cast<JSAMPROW>(rgb + cinfo.next_scanline * stride);
    jpeg_write_scanlines(&cinfo, &row, 1);
  }
  jpeg_finish_compress(&cinfo);
  jpeg_destroy_compress(&cinfo);
  return true;
}

// libpng: errors longjmp back to PngEncode; output appends to the vector.
void PngWrite(png_structp png, png_bytep data, png_size_t length) {
  auto* out = static_cast<std::vector<uint8_t>*>(png_get_io_ptr(png));
  out->insert(out->end(), data, data + length);
}

void PngFlush(png_structp) {}

void PngError(png_structp png, png_const_charp message) {
  auto* text = static_cast<std::string*>(png_get_error_ptr(png));
  if (text) *text = message;
  png_longjmp(png, 1);
}

void PngWarning(png_structp, png_const_charp) {}

// The settings OpenCV's PNG encoder used with IMWRITE_PNG_COMPRESSION (what the tools had before):
// the given zlib level, the default strategy and libpng's adaptive filters.
bool PngEncode(const uint8_t* rgb, int width, int height, size_t stride, int level, std::vector<uint8_t>* out,
               std::string* error) {
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, error, PngError, PngWarning);
  if (!png) return false;
  png_infop info = png_create_info_struct(png);
  if (!info || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, info ? &info : nullptr);
    return false;
  }
  png_set_write_fn(png, out, PngWrite, PngFlush);
  png_set_compression_level(png, level);
  png_set_compression_strategy(png, Z_DEFAULT_STRATEGY);
  png_set_IHDR(png, info, static_cast<png_uint_32>(width), static_cast<png_uint_32>(height), 8, PNG_COLOR_TYPE_RGB,
               PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_BASE, PNG_FILTER_TYPE_BASE);
  png_write_info(png, info);
  for (int y = 0; y < height; ++y) png_write_row(png, const_cast<png_bytep>(rgb + y * stride));
  png_write_end(png, info);
  png_destroy_write_struct(&png, &info);
  return true;
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

Status EncodeRgbFrame(const uint8_t* rgb, int width, int height, size_t stride_bytes, const FrameEncodeOptions& options,
                      std::vector<uint8_t>* out) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (rgb == nullptr || width < 1 || height < 1 || width > 65535 || height > 65535)
    return InvalidArgumentError("EncodeRgbFrame: need a non-null image of 1 to 65535 pixels a side, got " +
                                std::to_string(width) + "x" + std::to_string(height));
  const size_t row_bytes = static_cast<size_t>(width) * 3;
  if (stride_bytes < row_bytes)
    return InvalidArgumentError("EncodeRgbFrame: rows " + std::to_string(stride_bytes) + " bytes apart, less than " +
                                std::to_string(row_bytes));
  out->clear();
  switch (options.codec) {
    case FrameCodec::kRaw: {
      out->resize(row_bytes * height);
      for (int y = 0; y < height; ++y) std::memcpy(out->data() + y * row_bytes, rgb + y * stride_bytes, row_bytes);
      return Status::Ok();
    }
    case FrameCodec::kPng: {
      std::string error;
      if (!PngEncode(rgb, width, height, stride_bytes, options.png_compression, out, &error))
        return InternalError("PNG encoding failed: " + error);
      return Status::Ok();
    }
    case FrameCodec::kJpeg: {
      JpegErrorManager err;
      unsigned char* buffer = nullptr;
      unsigned long length = 0;
      const bool ok = JpegEncode(rgb, width, height, stride_bytes, options.jpeg_quality, &buffer, &length, &err);
      if (ok) out->assign(buffer, buffer + length);
      std::free(buffer);
      if (!ok) return InternalError(std::string("JPEG encoding failed: ") + err.message);
      return Status::Ok();
    }
  }
  return InvalidArgumentError("EncodeRgbFrame: unknown codec");
}

}  // namespace prism
