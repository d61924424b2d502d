#include "tools/capture/video_source.h"

#include <chrono>
#include <cmath>
#include <filesystem>
#include <sstream>

#include <opencv2/imgproc.hpp>

namespace prism {
namespace {

namespace fs = std::filesystem;

// V4L2's V4L2_EXPOSURE_MANUAL, which OpenCV's V4L2 backend passes through; some backends and old
// drivers take 0.25 for "manual" instead (OpenCV's historical convention), tried second.
constexpr double kAutoExposureManual = 1.0;
constexpr double kAutoExposureManualLegacy = 0.25;
// A file that reports no frame rate is taken at this rate for its time stamps.
constexpr double kDefaultFileFramesPerS = 30.0;

bool IsIndex(const std::string& s) {
  if (s.empty() || s.size() > 3) return false;
  for (char c : s)
    if (c < '0' || c > '9') return false;
  return true;
}

std::string Number(double v) {
  std::ostringstream o;
  o << v;
  return o.str();
}

}  // namespace

Status VideoSourceOptions::Check() const {
  if (source.empty())
    return InvalidArgumentError("VideoSourceOptions.source is empty; violated: a device, file or URL");
  if (width < 0 || height < 0 || width > 16384 || height > 16384)
    return InvalidArgumentError("VideoSourceOptions.width x height = " + std::to_string(width) + "x" +
                                std::to_string(height) + "; violated: in [0, 16384]");
  if (!std::isnan(exposure) && !(std::isfinite(exposure) && exposure > 0))
    return InvalidArgumentError("VideoSourceOptions.exposure = " + Number(exposure) + "; violated: > 0");
  if (!std::isnan(white_balance_k) && !(white_balance_k >= 1000 && white_balance_k <= 20000))
    return InvalidArgumentError("VideoSourceOptions.white_balance_k = " + Number(white_balance_k) +
                                "; violated: in [1000, 20000] kelvin");
  return Status::Ok();
}

StatusOr<std::unique_ptr<VideoSource>> VideoSource::Open(const VideoSourceOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  std::unique_ptr<VideoSource> v(new VideoSource());
  const std::string& src = options.source;
  const bool pipeline = src.find(" ! ") != std::string::npos;
  const bool url = src.find("://") != std::string::npos;
  std::error_code ec;
  v->is_file_ = !pipeline && !url && fs::is_regular_file(src, ec);
  bool opened = false;
  try {
    if (IsIndex(src)) {
      opened = v->capture_.open(std::stoi(src), cv::CAP_ANY);
    } else if (pipeline) {
      opened = v->capture_.open(src, cv::CAP_GSTREAMER);
    } else {
      if (!url && !fs::exists(src, ec))
        return NotFoundError("source '" + src + "': no such file or device (a V4L2 device such as /dev/video0 or " +
                             "its index, a video file, a GStreamer pipeline or a URL)");
      opened = v->capture_.open(src, src.rfind("/dev/video", 0) == 0 ? cv::CAP_V4L2 : cv::CAP_ANY);
    }
  } catch (const cv::Exception& e) {
    return UnavailableError("source '" + src + "': OpenCV failed to open it: " + e.what());
  }
  if (!opened || !v->capture_.isOpened())
    return UnavailableError("source '" + src + "': OpenCV's VideoCapture cannot open it" +
                            (pipeline ? std::string(" (a GStreamer pipeline must end in appsink, and OpenCV needs "
                                                    "GStreamer support)")
                                      : std::string(v->is_file_ ? " (not a video format OpenCV decodes?)"
                                                                : " (busy, no permission, or not a capture device?)")));
  const double fps = v->capture_.get(cv::CAP_PROP_FPS);
  v->frames_per_s_ = std::isfinite(fps) && fps > 0 && fps < 1000 ? fps : 0.0;
  if (v->is_file_ && v->frames_per_s_ == 0) {
    v->frames_per_s_ = kDefaultFileFramesPerS;
    v->notes_.push_back("the file reports no frame rate; time stamps at " + Number(kDefaultFileFramesPerS) +
                        " frames/s");
  }
  v->ApplyControls(options);
  return v;
}

std::string VideoSource::backend() const {
  try {
    return capture_.getBackendName();
  } catch (const cv::Exception&) {
    return "unknown";
  }
}

void VideoSource::ApplyControls(const VideoSourceOptions& options) {
  const bool wants_exposure = options.lock_exposure || !std::isnan(options.exposure);
  const bool wants_white_balance = options.lock_white_balance || !std::isnan(options.white_balance_k);
  if (is_file_) {
    if (wants_exposure || wants_white_balance)
      notes_.push_back("exposure and white balance cannot be set on a video file; they are as recorded");
    return;
  }
  if (options.width > 0 && options.height > 0) {
    capture_.set(cv::CAP_PROP_FRAME_WIDTH, options.width);
    capture_.set(cv::CAP_PROP_FRAME_HEIGHT, options.height);
  }
  if (wants_exposure) LockExposure(options);
  if (wants_white_balance) LockWhiteBalance(options);
}

void VideoSource::LockExposure(const VideoSourceOptions& options) {
  const double current = capture_.get(cv::CAP_PROP_EXPOSURE);
  bool manual = capture_.set(cv::CAP_PROP_AUTO_EXPOSURE, kAutoExposureManual);
  if (!manual) manual = capture_.set(cv::CAP_PROP_AUTO_EXPOSURE, kAutoExposureManualLegacy);
  const double value = std::isnan(options.exposure) ? current : options.exposure;
  const bool set = value > 0 && capture_.set(cv::CAP_PROP_EXPOSURE, value);
  exposure_locked_ = manual;
  if (!manual) {
    notes_.push_back("the " + backend() +
                     " driver refused to turn automatic exposure off: the exposure may change during the run "
                     "(lock it with the camera's own tool, e.g. v4l2-ctl; docs/rig.md)");
  } else if (!std::isnan(options.exposure) && !set) {
    notes_.push_back("automatic exposure is off, but the " + backend() + " driver refused exposure " + Number(value) +
                     "; it stays at " + Number(capture_.get(cv::CAP_PROP_EXPOSURE)));
  } else {
    notes_.push_back("exposure locked at " + Number(capture_.get(cv::CAP_PROP_EXPOSURE)) + " (driver units)");
  }
}

void VideoSource::LockWhiteBalance(const VideoSourceOptions& options) {
  const bool manual = capture_.set(cv::CAP_PROP_AUTO_WB, 0);
  const bool set =
      !std::isnan(options.white_balance_k) && capture_.set(cv::CAP_PROP_WB_TEMPERATURE, options.white_balance_k);
  white_balance_locked_ = manual;
  if (!manual) {
    notes_.push_back("the " + backend() +
                     " driver refused to turn automatic white balance off: the colour response may change during the "
                     "run (lock it with the camera's own tool; docs/rig.md)");
  } else if (!std::isnan(options.white_balance_k) && !set) {
    notes_.push_back("automatic white balance is off, but the " + backend() + " driver refused " +
                     Number(options.white_balance_k) + " K; it stays at its current setting");
  } else {
    notes_.push_back("white balance locked at " + Number(capture_.get(cv::CAP_PROP_WB_TEMPERATURE)) + " K");
  }
}

Status VideoSource::PeekSize(int* width, int* height) {
  if (peeked_rgb_.empty()) PRISM_RETURN_IF_ERROR(ReadNext(&peeked_rgb_, &peeked_ns_));
  *width = peeked_rgb_.cols;
  *height = peeked_rgb_.rows;
  return Status::Ok();
}

Status VideoSource::Read(cv::Mat* rgb, int64_t* timestamp_ns) {
  if (peeked_rgb_.empty()) return ReadNext(rgb, timestamp_ns);
  cv::swap(*rgb, peeked_rgb_);
  peeked_rgb_.release();
  *timestamp_ns = peeked_ns_;
  return Status::Ok();
}

Status VideoSource::ReadNext(cv::Mat* rgb, int64_t* timestamp_ns) {
  bool grabbed = false;
  try {
    grabbed = capture_.grab();
  } catch (const cv::Exception& e) {
    return UnavailableError(std::string("capture failed: ") + e.what());
  }
  const int64_t grabbed_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
  if (!grabbed || !capture_.retrieve(bgr_) || bgr_.empty()) {
    if (is_file_) return OutOfRangeError("end of the video file after " + std::to_string(frames_read_) + " frames");
    return UnavailableError("the source stopped delivering frames after " + std::to_string(frames_read_));
  }
  cv::Mat eight_bit = bgr_;
  if (bgr_.depth() == CV_16U) bgr_.convertTo(eight_bit, CV_8U, 1.0 / 256.0);
  else if (bgr_.depth() != CV_8U) return InvalidArgumentError("the source delivers frames of an unsupported depth");
  switch (eight_bit.channels()) {
    case 1:
      cv::cvtColor(eight_bit, *rgb, cv::COLOR_GRAY2RGB);
      break;
    case 3:
      cv::cvtColor(eight_bit, *rgb, cv::COLOR_BGR2RGB);
      break;
    case 4:
      cv::cvtColor(eight_bit, *rgb, cv::COLOR_BGRA2RGB);
      break;
    default:
      return InvalidArgumentError("the source delivers frames with " + std::to_string(eight_bit.channels()) +
                                  " channels");
  }
  *timestamp_ns = is_file_ ? std::llround(static_cast<double>(frames_read_) * 1e9 / frames_per_s_) : grabbed_ns;
  ++frames_read_;
  return Status::Ok();
}

}  // namespace prism
