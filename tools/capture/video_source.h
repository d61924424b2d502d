// A frame source for live capture: whatever cv::VideoCapture opens (a V4L2 device path or index, a
// video file, a GStreamer pipeline ending in appsink, an RTSP/HTTP URL). Frames come out as 8-bit RGB
// (OpenCV captures BGR) with a time stamp, and the camera's exposure and white balance can be set and
// locked where the driver lets OpenCV do so (docs/rig.md says why this method needs them locked).
#pragma once

#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/videoio.hpp>

#include "core/util/status.h"

namespace prism {

struct VideoSourceOptions {
  // "/dev/video0" or "0" (a V4L2 device), "clip.avi", "rtsp://host/stream", or a GStreamer pipeline
  // ("videotestsrc ! videoconvert ! appsink"; any text with " ! " is opened with CAP_GSTREAMER).
  std::string source;
  // Frame size asked of a live source, pixels (the rig calibration's); 0 = the driver's default.
  // Files and pipelines give what they hold; the caller checks the size of the first frame.
  int width = 0, height = 0;
  // Exposure to set and lock, in the driver's CAP_PROP_EXPOSURE units (V4L2: 100 us); NaN = not set.
  double exposure = std::nan("");
  // Turn automatic exposure off at the current exposure (implied by a set exposure).
  bool lock_exposure = false;
  // White balance to set and lock, kelvin (CAP_PROP_WB_TEMPERATURE), in [1000, 20000]; NaN = not set.
  double white_balance_k = std::nan("");
  // Turn automatic white balance off at the current setting (implied by a set white balance).
  bool lock_white_balance = false;
  Status Check() const;
};

class VideoSource {
 public:
  // Opens the source and applies the camera controls. NOT_FOUND / UNAVAILABLE with the source named
  // when OpenCV cannot open it. Controls the driver refuses are not an error: notes() says which.
  static StatusOr<std::unique_ptr<VideoSource>> Open(const VideoSourceOptions& options);

  // The next frame as CV_8UC3 RGB, and its time stamp in ns: for a live source the steady clock when
  // the frame was grabbed; for a video file the frame's index / the file's frame rate (its own time,
  // so that a file streams the same however fast it is read). OUT_OF_RANGE at the end of a file,
  // UNAVAILABLE when a live source stops delivering.
  Status Read(cv::Mat* rgb, int64_t* timestamp_ns);
  // Reads the first frame ahead (the next Read returns it) and gives its size, so that a source whose
  // frames do not match the calibration is refused before a session is opened.
  Status PeekSize(int* width, int* height);

  // A regular file (read at its own pace, nothing lost) rather than a live device, pipeline or URL.
  bool is_file() const { return is_file_; }
  // The source's frame rate (the file's, or what the driver reports), 0 when unknown.
  double frames_per_s() const { return frames_per_s_; }
  // What the camera controls did ("exposure locked at 120", "the driver refused ..."), in order.
  const std::vector<std::string>& notes() const { return notes_; }
  bool exposure_locked() const { return exposure_locked_; }
  bool white_balance_locked() const { return white_balance_locked_; }
  // OpenCV's backend name ("V4L2", "FFMPEG", "GSTREAMER", ...).
  std::string backend() const;

 private:
  VideoSource() = default;
  void ApplyControls(const VideoSourceOptions& options);
  void LockExposure(const VideoSourceOptions& options);
  void LockWhiteBalance(const VideoSourceOptions& options);

  cv::VideoCapture capture_;
  Status ReadNext(cv::Mat* rgb, int64_t* timestamp_ns);

  cv::Mat bgr_;         // reused between frames
  cv::Mat peeked_rgb_;  // the frame PeekSize read, until Read returns it
  int64_t peeked_ns_ = 0;
  bool is_file_ = false;
  double frames_per_s_ = 0;
  int64_t frames_read_ = 0;
  std::vector<std::string> notes_;
  bool exposure_locked_ = false, white_balance_locked_ = false;
};

}  // namespace prism
