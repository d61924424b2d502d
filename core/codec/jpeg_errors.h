// libjpeg's error handling for the frame encoder and decoder: error_exit (which must not return) jumps
// back with the message kept; warnings are kept (the decoder treats them as corruption), never printed.
#pragma once

#include <jpeglib.h>

#include <csetjmp>

namespace prism::internal {

struct JpegErrorManager {
  jpeg_error_mgr mgr;
  std::jmp_buf jump;
  char message[JMSG_LENGTH_MAX];
};

inline void JpegErrorExit(j_common_ptr cinfo) {
  auto* err = reinterpret_cast<JpegErrorManager*>(cinfo->err);
  (*cinfo->err->format_message)(cinfo, err->message);
  std::longjmp(err->jump, 1);
}

inline void JpegOutputMessage(j_common_ptr cinfo) {
  auto* err = reinterpret_cast<JpegErrorManager*>(cinfo->err);
  (*cinfo->err->format_message)(cinfo, err->message);
}

// Makes `err` the error manager of `cinfo` (call before jpeg_create_*; then setjmp(err->jump)).
inline void InstallJpegErrorManager(j_common_ptr cinfo, JpegErrorManager* err) {
  cinfo->err = jpeg_std_error(&err->mgr);
  err->mgr.error_exit = JpegErrorExit;
  err->mgr.output_message = JpegOutputMessage;
  err->message[0] = '\0';
}

}  // namespace prism::internal
