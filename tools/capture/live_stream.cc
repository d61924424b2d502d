#include "tools/capture/live_stream.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "core/io/image_io.h"
#include "core/io/sequence.h"

namespace prism {
namespace {

namespace fs = std::filesystem;
namespace pc = client;
using Clock = std::chrono::steady_clock;

}  // namespace

// ---------------------------------------------------------------------------------------------------
// SequenceRecorder

StatusOr<std::unique_ptr<SequenceRecorder>> SequenceRecorder::Create(const std::string& dir,
                                                                     const std::string& camera_yaml,
                                                                     size_t queue_capacity) {
  std::error_code ec;
  if (fs::exists(dir, ec) && !(fs::is_directory(dir, ec) && fs::is_empty(dir, ec)))
    return FailedPreconditionError("--record '" + dir + "' exists and is not an empty folder (it would mix two runs)");
  fs::create_directories(dir + "/rgb", ec);
  if (ec) return UnavailableError("cannot create '" + dir + "/rgb': " + ec.message());
  fs::copy_file(camera_yaml, dir + "/camera.yaml", fs::copy_options::overwrite_existing, ec);
  if (ec) return UnavailableError("cannot copy '" + camera_yaml + "' into '" + dir + "': " + ec.message());
  std::unique_ptr<SequenceRecorder> r(new SequenceRecorder(dir, std::max<size_t>(1, queue_capacity)));
  r->writer_ = std::thread([p = r.get()] { p->WriterLoop(); });
  return r;
}

SequenceRecorder::~SequenceRecorder() {
  if (writer_.joinable()) (void)Finish();
}

void SequenceRecorder::Add(int64_t timestamp_ns, const cv::Mat& rgb) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (finishing_ || queue_.size() >= capacity_) {
      ++dropped_;
      return;
    }
    queue_.emplace_back(timestamp_ns, rgb.clone());
  }
  cv_.notify_one();
}

void SequenceRecorder::WriterLoop() {
  for (;;) {
    std::pair<int64_t, cv::Mat> frame;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [this] { return finishing_ || !queue_.empty(); });
      if (queue_.empty()) return;
      frame = std::move(queue_.front());
      queue_.pop_front();
    }
    const double t = static_cast<double>(frame.first) * 1e-9;
    const Status s = WriteRgbImage(dir_ + "/rgb/" + SequenceWriter::FrameName(t), frame.second);
    if (s.ok()) {
      stamps_s_.push_back(t);
      ++written_;
    } else {
      ++dropped_;
      if (write_error_.ok()) write_error_ = s;
    }
  }
}

Status SequenceRecorder::Finish() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    finishing_ = true;
  }
  cv_.notify_all();
  if (writer_.joinable()) writer_.join();
  std::sort(stamps_s_.begin(), stamps_s_.end());
  // The index as core/io/sequence.h's SequenceWriter writes it (no ground truth for a live run).
  std::ofstream out(dir_ + "/rgb.txt");
  out << "# colour images (RGB, 8-bit)\n# timestamp filename\n";
  char line[96];
  for (double t : stamps_s_) {
    std::snprintf(line, sizeof(line), "%.6f rgb/%s\n", t, SequenceWriter::FrameName(t).c_str());
    out << line;
  }
  if (!out) return UnavailableError("cannot write '" + dir_ + "/rgb.txt'");
  if (!write_error_.ok()) return UnavailableError("recording into '" + dir_ + "': " + write_error_.ToString());
  return Status::Ok();
}

// ---------------------------------------------------------------------------------------------------
// LiveStream

Status LiveStreamOptions::Check() const {
  if (max_frames < 0)
    return InvalidArgumentError("LiveStreamOptions.max_frames = " + std::to_string(max_frames) + "; violated: >= 0");
  if (width < 0 || height < 0) return InvalidArgumentError("LiveStreamOptions.width, height must be >= 0");
  if (progress_interval_ms < 50 || progress_interval_ms > 60000)
    return InvalidArgumentError("LiveStreamOptions.progress_interval_ms = " + std::to_string(progress_interval_ms) +
                                "; violated: in [50, 60000]");
  return Status::Ok();
}

// The newest captured frame, handed from the capture thread to the sending thread (a one-frame
// drop-oldest queue: an unsent frame replaced by a newer one is counted stale).
struct LiveStream::Slot {
  std::mutex mutex;
  std::condition_variable cv;
  cv::Mat rgb;               // Guarded by mutex.
  int64_t timestamp_ns = 0;  // Guarded by mutex.
  bool full = false;         // Guarded by mutex.
  bool closed = false;       // Guarded by mutex: the capture thread has ended.
  std::atomic<uint64_t> captured{0}, stale{0};
  std::string end;  // Guarded by mutex: why the capture ended, set with `closed`.
};

Status LiveStream::Run(const std::function<void(const pc::Event&)>& on_event,
                       const std::function<void(const LiveStats&)>& on_progress) {
  PRISM_RETURN_IF_ERROR(options_.Check());
  start_ = last_progress_ = Clock::now();
  const bool paced_by_credits = source_->is_file() && !options_.realtime;
  Status s =
      paced_by_credits || options_.wait_for_credit ? RunPaced(on_event, on_progress) : RunLive(on_event, on_progress);
  Drain(on_event);
  Progress(on_progress, /*force=*/true);
  return s;
}

// A video file read as fast as the server takes it: each frame waits for a credit, nothing is lost.
Status LiveStream::RunPaced(const std::function<void(const pc::Event&)>& on_event,
                            const std::function<void(const LiveStats&)>& on_progress) {
  cv::Mat rgb;
  int64_t timestamp_ns = 0;
  while (!stop_) {
    if (options_.max_frames > 0 && static_cast<int64_t>(stats_.captured) >= options_.max_frames) {
      stats_.end = "max frames";
      return Status::Ok();
    }
    const Status r = source_->Read(&rgb, &timestamp_ns);
    if (!r.ok()) {
      stats_.end = r.code() == StatusCode::kOutOfRange ? "end of file" : r.ToString();
      return Status::Ok();
    }
    ++stats_.captured;
    if (recorder_) recorder_->Add(timestamp_ns, rgb);
    PRISM_RETURN_IF_ERROR(Send(timestamp_ns, rgb, on_event));
    Progress(on_progress, false);
  }
  stats_.end = "stopped";
  return Status::Ok();
}

void LiveStream::CaptureLoop(Slot* slot) {
  cv::Mat rgb;
  int64_t timestamp_ns = 0, first_ns = -1;
  const Clock::time_point start = Clock::now();
  std::string why = "stopped";
  while (!stop_) {
    if (options_.max_frames > 0 && static_cast<int64_t>(slot->captured) >= options_.max_frames) {
      why = "max frames";
      break;
    }
    const Status r = source_->Read(&rgb, &timestamp_ns);
    if (!r.ok()) {
      why = r.code() == StatusCode::kOutOfRange ? "end of file" : r.ToString();
      break;
    }
    if (source_->is_file()) {  // --realtime: deliver the file's frames at their own times
      if (first_ns < 0) first_ns = timestamp_ns;
      std::this_thread::sleep_until(start + std::chrono::nanoseconds(timestamp_ns - first_ns));
    }
    ++slot->captured;
    if (recorder_) recorder_->Add(timestamp_ns, rgb);
    {
      std::lock_guard<std::mutex> lock(slot->mutex);
      if (slot->full) ++slot->stale;
      cv::swap(slot->rgb, rgb);  // no copy: the sender swaps the slot's frame out in turn
      slot->timestamp_ns = timestamp_ns;
      slot->full = true;
    }
    slot->cv.notify_one();
  }
  {
    std::lock_guard<std::mutex> lock(slot->mutex);
    slot->end = why;
    slot->closed = true;
  }
  slot->cv.notify_one();
}

// A live source: a capture thread grabs frames at the source's rate; this thread sends the newest.
Status LiveStream::RunLive(const std::function<void(const pc::Event&)>& on_event,
                           const std::function<void(const LiveStats&)>& on_progress) {
  Slot slot;
  std::thread capture([this, &slot] { CaptureLoop(&slot); });
  cv::Mat rgb;
  Status result = Status::Ok();
  for (;;) {
    int64_t timestamp_ns = 0;
    bool got = false, closed = false;
    {
      std::unique_lock<std::mutex> lock(slot.mutex);
      slot.cv.wait_for(lock, std::chrono::milliseconds(options_.progress_interval_ms),
                       [&slot] { return slot.full || slot.closed; });
      if (slot.full) {
        cv::swap(rgb, slot.rgb);
        timestamp_ns = slot.timestamp_ns;
        slot.full = false;
        got = true;
      }
      closed = slot.closed && !slot.full;
    }
    stats_.captured = slot.captured;
    stats_.skipped_stale = slot.stale;
    if (got) result = Send(timestamp_ns, rgb, on_event);
    else Drain(on_event);
    Progress(on_progress, false);
    if (!result.ok()) break;
    if (closed && !got) break;
  }
  stop_ = true;
  capture.join();
  stats_.captured = slot.captured;
  stats_.skipped_stale = slot.stale;
  stats_.end = slot.end;
  return result;
}

Status LiveStream::Send(int64_t timestamp_ns, const cv::Mat& rgb,
                        const std::function<void(const pc::Event&)>& on_event) {
  if (rgb.cols != options_.width || rgb.rows != options_.height)
    return InvalidArgumentError("the source gives " + std::to_string(rgb.cols) + "x" + std::to_string(rgb.rows) +
                                " frames, but the camera calibration is for " + std::to_string(options_.width) + "x" +
                                std::to_string(options_.height) +
                                " (calibrate at the size the camera delivers, or make it deliver the calibrated size)");
  Drain(on_event);
  const bool wait = options_.wait_for_credit || (source_->is_file() && !options_.realtime);
  if (!wait && session_->frame_credits() <= 0) {  // a live camera does not wait for the server
    ++stats_.skipped_no_credit;
    return Status::Ok();
  }
  const pc::Status s =
      session_->PushFrame(timestamp_ns, rgb.ptr<uint8_t>(), rgb.cols, rgb.rows, static_cast<int>(rgb.step[0]));
  if (!s.ok()) return UnavailableError("frame " + std::to_string(stats_.sent) + ": " + s.ToString());
  ++stats_.sent;
  Drain(on_event);
  return Status::Ok();
}

void LiveStream::Drain(const std::function<void(const pc::Event&)>& on_event) {
  pc::Event e;
  bool map_changed = false;
  while (session_->Poll(&e, 0)) {
    if (e.kind == pc::Event::Kind::kPose) {
      if (!e.pose.refined) ++stats_.poses;
      stats_.tracking = e.pose.state;
    } else if (e.kind == pc::Event::Kind::kChunk) {
      ++stats_.chunks;
      map_changed = true;
    }
    if (on_event) on_event(e);
  }
  if (map_changed) stats_.map_points = session_->Map().size();
}

void LiveStream::Progress(const std::function<void(const LiveStats&)>& on_progress, bool force) {
  const Clock::time_point now = Clock::now();
  const double dt = std::chrono::duration<double>(now - last_progress_).count();
  if (!force && dt * 1000 < options_.progress_interval_ms) return;
  stats_.seconds = std::chrono::duration<double>(now - start_).count();
  if (force) {  // the end: the mean over the whole run
    stats_.frames_per_s = stats_.seconds > 0 ? static_cast<double>(stats_.sent) / stats_.seconds : 0.0;
  } else if (dt > 0) {
    stats_.frames_per_s = static_cast<double>(stats_.sent - sent_at_last_progress_) / dt;
    sent_at_last_progress_ = stats_.sent;
    last_progress_ = now;
  }
  if (recorder_) {
    stats_.recorded = recorder_->written();
    stats_.record_dropped = recorder_->dropped();
  }
  if (on_progress) on_progress(stats_);
}

}  // namespace prism
