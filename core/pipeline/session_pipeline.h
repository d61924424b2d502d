// One session = one pipeline (paper Fig. 1, STYLE.md §5):
//
//   network thread --Push--> [frame queue, bounded] --> SLAM thread: decode -> SlamSystem::ProcessFrame
//       -> pose event per frame; finished keyframes -> [keyframe queue, bounded, drop-oldest]
//       -> the session's strand on the process-wide DenseWorkers: DenseStage::Process (photometric
//          stereo, fusion, ICP, map) -> Draco chunk of the changed voxels -> chunk event.
//
// The SLAM and the dense stage run in parallel (the paper's two systems). Events reach the owner
// through a callback called on the SLAM thread (poses, frame errors) or a dense worker (chunks,
// keyframe errors, the final kFinished); it must be cheap and thread-safe (the server queues them for
// its transport thread). A failure inside the pipeline (a broken invariant, PRISM_CHECK) ends this
// session with a fatal error event; other sessions never notice.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "core/codec/frame_codec.h"
#include "core/codec/map_chunk_codec.h"
#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/pipeline/bounded_queue.h"
#include "core/pipeline/dense_stage.h"
#include "core/pipeline/dense_workers.h"
#include "core/slam/slam_system.h"
#include "core/slam/undistort.h"
#include "core/util/status.h"

namespace prism {

struct SessionPipelineOptions {
  SlamOptions slam;
  DenseStageOptions dense;
  // Map chunk coding; voxel_m is taken from dense.map.voxel_m.
  MapChunkCodecOptions chunk;
  // Encoded frames waiting for the SLAM thread, in [1, 1024].
  int frame_queue_capacity = 8;
  // A full frame queue drops its oldest frame (live camera) or rejects the new one (upload).
  OverflowPolicy input_policy = OverflowPolicy::kDropOldest;
  // Finished keyframes waiting for the dense stage, in [1, 256]. When full, a live session
  // (input_policy kDropOldest) drops its oldest keyframe (counted): SLAM never waits for the dense
  // stage. An upload session (kReject) never drops a finished keyframe: the SLAM thread waits for
  // room, so it stops consuming frames, the frame queue fills and the server stops granting frame
  // credits (memory stays bounded by the two queue capacities).
  int keyframe_queue_capacity = 4;
  // When another of the session's keyframes waits behind it, a keyframe whose semi-dense points the map
  // already covers to more than this fraction (DenseStage::MapCoverage) skips the dense stage (counted in
  // keyframes_dropped): a dense stage that has fallen behind spends its time where the map lacks surface.
  // In (0, 1]; 1 = never.
  double covered_keyframe_fraction = 0.8;
  // When at least this many frames wait in the frame queue as the SLAM thread takes the next one, that
  // frame skips the SLAM's stereo depth update (SlamSystem::ProcessFrame's skip_depth_update; a frame
  // that makes a keyframe still updates): a SLAM that has fallen behind its input spends its time on
  // poses until it has caught up, as LSD-SLAM's and DSO's mapping threads do. 0 = never, in [0, 1024].
  int skip_depth_update_backlog = 0;
  // At the end of the stream, after the final adjustment: when keyframe poses moved since their clouds
  // entered the map, the map is rebuilt from the kept clouds at the final poses (DenseStage::Remap)
  // and sent as one chunk with replaces_map. false: the map keeps the poses each keyframe had when it
  // was handed over (the refined poses and the map then disagree by what the poses moved).
  bool remap_at_end = true;
  // With remap_at_end the map is rebuilt at the session's final scale (ChooseMetresPerUnit: the SLAM's
  // metric scale from the co-moving lights, SlamSystem::EstimateMetricScale after the final adjustment,
  // when it passes its check and agrees with the dense stage's; else the dense stage's final estimate),
  // which the session's summary then carries as metres_per_unit, as do the refined poses of the end
  // (poses sent before carry the map's early scale). false: the dense stage's final estimate alone.
  bool metric_scale_at_end = true;

  Status Check() const;
};

struct EncodedFrame {
  uint64_t sequence_number = 0;
  int64_t timestamp_ns = 0;
  FrameCodec codec = FrameCodec::kPng;
  std::vector<uint8_t> bytes;
};

struct PipelineStats {
  uint64_t frames_received = 0;              // accepted by Push
  uint64_t frames_dropped = 0;               // dropped from a full queue (drop-oldest) or at Abort
  uint64_t frames_rejected = 0;              // refused by Push (full queue with kReject, or closed)
  uint64_t frames_bad = 0;                   // failed to decode (corrupt, wrong size)
  uint64_t frames_processed = 0;             // tracked by SLAM
  uint64_t frames_depth_update_skipped = 0;  // of those, without their depth update (skip_depth_update_backlog)
  uint64_t keyframes = 0;                    // finished keyframes from SLAM
  uint64_t keyframes_dropped = 0;
  uint64_t keyframe_waits = 0;    // upload: times SLAM waited for room in the keyframe queue
  uint64_t keyframes_failed = 0;  // dense stage errors
  uint64_t chunks = 0;
  uint64_t chunk_bytes = 0;
  uint64_t chunk_points = 0;
  uint64_t map_points = 0;
  double metres_per_unit = 0;  // 0 until estimated
  double slam_ms_total = 0, dense_ms_total = 0;
  // The SLAM's check against the co-moving lights' shading at the end (MetricScaleEstimate::consistent,
  // with metric_scale_at_end): 0 not run, 1 consistent, 2 distorted; and its pair spread.
  int shading_check = 0;
  double shading_pair_spread = 0;
  // The SLAM's start check (SlamSystem::start_check): 0 not run (or not decided yet), 1 passed, 2 the
  // second start replaced the first (every pose so far is sent again, refined), 3 the first start failed
  // and was kept (the second start was no better, too slow, or would have been the same); and the first
  // start's pair spread.
  int start_check = 0;
  double start_pair_spread = 0;
};

// One keyframe through the dense stage: when the SLAM handed it over and when the dense stage took it
// (the wait between is the keyframe queue's), then the stage's time on it in ms, in all and by part.
struct DenseTiming {
  std::chrono::steady_clock::time_point queued_at, started_at;
  double photometric_ms = 0;  // photometric stereo
  double fusion_ms = 0;       // positions and normals
  double map_ms = 0;          // the keyframe cloud, ICP, the merge
  double encode_ms = 0;       // the chunk's Draco encoding
  double total_ms = 0;        // from started_at to the chunk ready to send
};

struct PipelineEvent {
  enum class Kind { kPose, kChunk, kError, kFinished };
  Kind kind = Kind::kPose;
  // kPose.
  uint64_t frame_sequence_number = 0;
  int64_t timestamp_ns = 0;
  SlamFrameResult slam;
  double metres_per_unit = 0;  // 0 until the dense stage estimated it
  // A later pose of a frame already reported: at the end of the stream, every frame whose pose the
  // SLAM changed since (initialisation frames, loop closures) is reported again with refined = true.
  bool refined = false;
  // kChunk.
  uint64_t keyframe_id = 0;
  uint64_t chunk_sequence = 0;
  std::vector<uint8_t> draco;
  size_t num_points = 0;
  Rigid3d world_from_keyframe;  // metres
  size_t map_points = 0;
  // The map was rebuilt at the final keyframe poses (SessionPipelineOptions::remap_at_end): this chunk
  // is the whole map and voids every earlier one (keyframe_id 0, identity pose).
  bool replaces_map = false;
  // Memory accounting: all of the map's voxels (map_points counts those in its output,
  // MapOptions::min_keyframes) and the points of the keyframe clouds kept for the rebuild.
  size_t map_voxels = 0;
  int64_t kept_points = 0;
  // Where a keyframe's time went (all zero for the rebuilt map and the last chunk of a stream).
  DenseTiming timing;
  // kError: a frame or keyframe failed (has_frame), or the session failed (fatal).
  Status status;
  bool has_frame = false;
  bool fatal = false;
  // kFinished: the last event of a pipeline.
  PipelineStats stats;
};

using PipelineEventSink = std::function<void(PipelineEvent&&)>;

class SessionPipeline {
 public:
  // INVALID_ARGUMENT on bad options or rig. The SLAM thread starts here; workers must outlive the
  // pipeline.
  static StatusOr<std::unique_ptr<SessionPipeline>> Create(const RigCalibration& rig,
                                                           const SessionPipelineOptions& options, DenseWorkers* workers,
                                                           PipelineEventSink sink);
  // Aborts and waits for the SLAM thread and this session's dense jobs.
  ~SessionPipeline();
  SessionPipeline(const SessionPipeline&) = delete;
  SessionPipeline& operator=(const SessionPipeline&) = delete;

  // Never blocks (network thread). OK (possibly after dropping the oldest queued frame, counted);
  // RESOURCE_EXHAUSTED when the queue is full under kReject; FAILED_PRECONDITION after Finish, Abort
  // or a fatal error. *dropped_oldest (optional) tells whether the oldest queued frame was dropped.
  Status Push(EncodedFrame frame, bool* dropped_oldest = nullptr);
  // End of stream: the queued frames are tracked, SLAM's last keyframe is finished, every keyframe goes
  // through the dense stage, then kFinished. Returns at once.
  void Finish();
  // Stop soon: queued frames and keyframes are dropped, running work completes, then kFinished.
  void Abort();

  // Moves the SLAM thread (decoding, tracking, mapping) to the lowest CPU priority (nice 19) and the
  // dense stage to the background worker (DenseWorkers) for the session's life, so that it runs on what
  // other sessions leave: for a client that floods the server. Never blocks. false when the SLAM thread
  // is not running yet or the system refused.
  bool Deprioritise();
  // Keyframes that reach the dense stage before `until` skip it (counted in keyframes_dropped): a
  // session over its frame-rate limit keeps its poses, and its map waits until it slows down. Never
  // blocks.
  void SkipDenseUntil(std::chrono::steady_clock::time_point until);

  PipelineStats stats() const;
  // Frames in the queue, not yet taken by the SLAM thread.
  size_t queued_frames() const { return frames_.size(); }
  // Finished keyframes waiting for the dense stage.
  size_t queued_keyframes() const;
  // The merged map so far (call after kFinished, or accept a snapshot taken between keyframes).
  PointCloud MapSnapshot() const;

 private:
  SessionPipeline(const RigCalibration& rig, const SessionPipelineOptions& options, DenseWorkers* workers,
                  PipelineEventSink sink);
  // The SLAM thread: every frame off the queue, then the end of the stream and the strand's last job.
  void SlamLoop();
  // One frame: decoded, undistorted and tracked; its pose (or error) to the sink and the keyframes it
  // finished to the dense stage. `rgb` is the decode buffer, reused from frame to frame.
  void TrackFrame(const EncodedFrame& frame, cv::Mat* rgb);
  // A frame's error event, the frame's sequence number before the message.
  void SendFrameError(uint64_t sequence_number, const Status& status);
  // After the last frame (SLAM thread): the SLAM's last keyframes to the dense stage, the final
  // adjustment and the metric scale; gives the final keyframe poses (remap_at_end) and the refined pose
  // events for FinishMap.
  void FinishSlam(std::vector<Sim3d>* final_keyframe_poses, std::vector<PipelineEvent>* refined);
  // The SLAM's metric scale from the co-moving lights (FinishStream's) into final_metres_per_unit_ and
  // the stats.
  void TakeFinalMetricScale(const SlamStreamEnd& end);
  // The strand's last job. Clouds still waiting for the session scale (it had not settled:
  // DenseStageOptions::scale_keyframes) enter the map; then the map is rebuilt at the final keyframe
  // poses when they moved (remap_at_end). The refined poses go out once the session's final scale is
  // known (the summary's and the rebuilt map's), before the rebuilt map; then kFinished.
  void FinishMap(const std::vector<Sim3d>& final_keyframe_poses, std::vector<PipelineEvent>* refined);
  // Sends the refined pose events with the current metres_per_unit_ and empties the list.
  void SendRefined(std::vector<PipelineEvent>* refined);
  void QueueKeyframe(SlamKeyframe keyframe);
  void DenseJob();
  // Encodes the changed voxels and hands the chunk to the sink (strand jobs only).
  void EmitChunk(const MapChunk& changes, uint64_t keyframe_id, const Rigid3d& world_from_keyframe, size_t map_points,
                 DenseTiming timing = {});
  void Fail(const Status& status);

  const RigCalibration rig_;
  const SessionPipelineOptions options_;
  DenseWorkers* workers_;
  std::shared_ptr<DenseWorkers::Strand> strand_;
  PipelineEventSink sink_;
  std::unique_ptr<ImageUndistorter> undistorter_;  // rig_'s camera -> the pinhole camera of slam_ and dense_
  std::unique_ptr<SlamSystem> slam_;               // SLAM thread only
  // Per SLAM frame id: the frame's sequence number and timestamp and the pose and state reported
  // (SLAM thread only); compared with the SLAM's final trajectory for the refined poses.
  struct ReportedPose {
    bool valid = false;  // false: the SLAM recorded the frame but the pipeline reported an error
    uint64_t sequence_number = 0;
    int64_t timestamp_ns = 0;
    SlamState state = SlamState::kInitializing;
    Rigid3d world_from_camera;
  };
  std::vector<ReportedPose> reported_;
  // The refined pose events (metres_per_unit not set) of every pose that moved since it was sent; with
  // untracked_too also those sent as tracked that are no longer (with their new state). Marks them sent.
  std::vector<PipelineEvent> RefinedPoses(bool untracked_too);
  // After each frame and at the end: the SLAM's start check into the stats, once it is done. true when
  // the second start has just replaced the first (every pose so far is to be sent again).
  bool UpdateStartCheck();
  bool start_check_done_ = false;
  std::unique_ptr<DenseStage> dense_;  // strand jobs only (one at a time)
  BoundedQueue<EncodedFrame> frames_;
  std::atomic<bool> accepting_{true};
  std::atomic<bool> aborted_{false};
  std::atomic<bool> failed_{false};
  std::atomic<double> metres_per_unit_{0.0};
  // The SLAM's metric scale at the end (metric_scale_at_end; 0 = none) and its shading check, for the
  // map's rebuild (ChooseMetresPerUnit).
  std::atomic<double> final_metres_per_unit_{0.0};
  std::atomic<bool> final_shading_consistent_{false};
  mutable std::mutex mutex_;
  std::condition_variable keyframe_room_;  // signalled when keyframes_ shrinks or on Abort/Fail
  struct QueuedKeyframe {
    SlamKeyframe keyframe;
    std::chrono::steady_clock::time_point queued_at;
  };
  std::deque<QueuedKeyframe> keyframes_;  // Guarded by mutex_.
  PipelineStats stats_;                   // Guarded by mutex_.
  mutable std::mutex map_mutex_;          // held by dense jobs while they write the map
  std::thread slam_thread_;
  std::atomic<std::chrono::steady_clock::rep> skip_dense_until_{0};  // steady_clock ticks
  std::atomic<int> slam_thread_id_{0};  // the kernel's id of slam_thread_ (0 until it runs)
};

}  // namespace prism
