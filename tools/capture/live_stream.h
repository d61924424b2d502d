// Live capture into a session: frames from a VideoSource are time-stamped at capture, optionally
// recorded as a sequence folder, and pushed to prism-server. Used by `prism-client stream --source`
// and by the Python client's Session.stream_source.
#pragma once

#include <prism/client/client.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <opencv2/core.hpp>

#include "core/util/status.h"
#include "tools/capture/video_source.h"

namespace prism {

// Writes captured frames as a sequence folder in the TUM layout (rgb.txt, rgb/<t>.png, and the rig's
// camera.yaml), so that a live run replays with `prism-client stream --sequence DIR`. PNG encoding runs
// on a thread of its own behind a bounded queue: the capture never waits for the disk.
class SequenceRecorder {
 public:
  // dir must be new or empty; camera_yaml is copied into it as it is.
  static StatusOr<std::unique_ptr<SequenceRecorder>> Create(const std::string& dir, const std::string& camera_yaml,
                                                            size_t queue_capacity = kDefaultQueueCapacity);
  ~SequenceRecorder();
  // Never blocks: when queue_capacity frames are still waiting for the disk, this one is not recorded
  // (counted in dropped()). Thread-safe.
  void Add(int64_t timestamp_ns, const cv::Mat& rgb);
  // Writes the frames still queued, then rgb.txt (the frames written, in time order).
  Status Finish();
  uint64_t written() const { return written_; }
  uint64_t dropped() const { return dropped_; }
  const std::string& dir() const { return dir_; }

  // Frames waiting for the disk (about 6 MB each at 1920x1080).
  static constexpr size_t kDefaultQueueCapacity = 32;

 private:
  SequenceRecorder(std::string dir, size_t capacity) : dir_(std::move(dir)), capacity_(capacity) {}
  void WriterLoop();

  const std::string dir_;
  const size_t capacity_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<std::pair<int64_t, cv::Mat>> queue_;  // Guarded by mutex_.
  bool finishing_ = false;                         // Guarded by mutex_.
  std::vector<double> stamps_s_;                   // written frames; only the writer thread
  Status write_error_;                             // the first failed write; only the writer thread
  std::atomic<uint64_t> written_{0}, dropped_{0};
  std::thread writer_;
};

struct LiveStreamOptions {
  // true: wait for a frame credit before each frame, so nothing is lost (a video file, read as fast as
  // the server takes it); false: a frame captured while the server has no room is not sent (a live
  // camera does not wait: the newest frame wins).
  bool wait_for_credit = false;
  // Read a video file at its own frame rate on the capture thread, as a camera would deliver it
  // (frames then drop as for a camera). No effect on live sources.
  bool realtime = false;
  // Stop after this many frames captured; 0 = until the source ends or Stop().
  int64_t max_frames = 0;
  // The calibration's frame size, pixels: a frame of another size ends the stream (INVALID_ARGUMENT).
  int width = 0, height = 0;
  // How often on_progress is called while streaming, ms, in [50, 60000].
  int progress_interval_ms = 500;
  Status Check() const;
};

struct LiveStats {
  uint64_t captured = 0;           // frames read from the source
  uint64_t sent = 0;               // frames pushed to the server
  uint64_t skipped_no_credit = 0;  // captured while the server had no room for them: not sent
  uint64_t skipped_stale = 0;      // replaced by a newer frame before they could be sent
  uint64_t recorded = 0, record_dropped = 0;
  double frames_per_s = 0;  // frames sent per second over the last progress interval
  uint64_t poses = 0, chunks = 0;
  client::TrackingState tracking = client::TrackingState::kUnknown;  // the latest pose's
  size_t map_points = 0;                                             // the session's running map
  double seconds = 0;                                                // since Run started
  std::string end;  // why the capture ended: "end of file", "stopped", "max frames", or the source's error
  uint64_t dropped() const { return skipped_no_credit + skipped_stale; }
};

class LiveStream {
 public:
  // session and source stay owned by the caller and outlive Run; recorder may be null.
  LiveStream(client::Session* session, VideoSource* source, SequenceRecorder* recorder, LiveStreamOptions options)
      : session_(session), source_(source), recorder_(recorder), options_(options) {}

  // Streams until the source ends, max_frames, or Stop(). Every event the session receives goes to
  // on_event (on this thread) after the stream has counted it; on_progress gets the counts every
  // progress_interval_ms and once at the end. Returns INVALID_ARGUMENT for a frame of the wrong size,
  // or the SDK's status when a frame cannot be sent; the caller closes the session either way.
  Status Run(const std::function<void(const client::Event&)>& on_event,
             const std::function<void(const LiveStats&)>& on_progress);
  // Ends Run at the next frame. Thread-safe and async-signal-safe (sets a flag).
  void Stop() { stop_ = true; }
  const LiveStats& stats() const { return stats_; }

 private:
  struct Slot;
  Status RunPaced(const std::function<void(const client::Event&)>& on_event,
                  const std::function<void(const LiveStats&)>& on_progress);
  Status RunLive(const std::function<void(const client::Event&)>& on_event,
                 const std::function<void(const LiveStats&)>& on_progress);
  void CaptureLoop(Slot* slot);
  // Sends one frame (or counts it as skipped) and hands the events waiting now to on_event.
  Status Send(int64_t timestamp_ns, const cv::Mat& rgb, const std::function<void(const client::Event&)>& on_event);
  void Drain(const std::function<void(const client::Event&)>& on_event);
  void Progress(const std::function<void(const LiveStats&)>& on_progress, bool force);

  client::Session* const session_;
  VideoSource* const source_;
  SequenceRecorder* const recorder_;
  const LiveStreamOptions options_;
  std::atomic<bool> stop_{false};
  LiveStats stats_;
  std::chrono::steady_clock::time_point start_, last_progress_;
  uint64_t sent_at_last_progress_ = 0;
};

}  // namespace prism
