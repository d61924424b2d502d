// Internal to core/slam: SlamSystem's state (SlamSystem::Impl, SlamSystem::StartCheck) and the helpers shared
// by its source files: slam_system.cc (creation, the frame loop, accessors), slam_start.cc (initialisation and
// the start check), slam_tracking.cc, slam_keyframes.cc (new keyframes, loop closure), slam_backend.cc (the
// keyframe adjustments, the shading pairs) and slam_finish.cc (the end of the sequence).
#pragma once

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <future>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <opencv2/core.hpp>

#include "core/slam/pose_graph.h"
#include "core/slam/slam_system.h"

namespace prism {
namespace slam_internal {

constexpr double kRadToDeg = 180.0 / M_PI;

// How a frame's alignment went (SlamFrameResult::tracking): tr, tracked from `guess`, whether it was
// tracked again from the last pose, the previous frame's pose on the same keyframe, and the keyframe's
// mean inverse depth (distances as fractions of the mean depth).
SlamTrackingQuality QualityOf(const TrackingResult& tr, bool retried, const Rigid3d& guess,
                              const Rigid3d& previous_from_keyframe, double mean_idepth);

// The seconds from `start` to now.
double SecondsSince(std::chrono::steady_clock::time_point start);

// Adds the seconds from its construction to its destruction to *total.
class ScopedSeconds {
 public:
  explicit ScopedSeconds(double* total) : total_(total), start_(std::chrono::steady_clock::now()) {}
  ~ScopedSeconds() { *total_ += SecondsSince(start_); }
  ScopedSeconds(const ScopedSeconds&) = delete;
  ScopedSeconds& operator=(const ScopedSeconds&) = delete;

 private:
  double* total_;
  std::chrono::steady_clock::time_point start_;
};

// Every light of the rig is a point light with an intensity (what the shading scale models).
bool AllPointLights(const RigCalibration& rig);

// The interquartile range of keyframe pairs' shading scales over their median (0 when empty).
double PairSpread(std::vector<double> estimates);

// What one keyframe pair's shading scale reads: the older keyframe's image, inverse depth and pose, the
// newer one's image and pose.
struct ShadingPair {
  int older = 0;
  cv::Mat older_rgb, older_inverse_depth, newer_rgb;
  Sim3d world_from_older, world_from_newer;
};

// Each pair's shading scale (metres per world unit) with its older keyframe's index, in the pairs' order
// (the pairs on `pool` when given: each is independent, so the result is the same to the bit).
std::vector<std::pair<int, double>> PairScales(const RigCalibration& rig, const std::vector<ShadingPair>& pairs,
                                               ThreadPool* pool = nullptr);

}  // namespace slam_internal

struct SlamSystem::Impl {
  RigCalibration rig;
  SlamOptions options;
  ThreadPool* pool = nullptr;
  std::unique_ptr<Tracker> tracker;
  std::unique_ptr<Tracker> reloc_tracker;
  std::unique_ptr<Tracker> loop_tracker;
  std::vector<PoseGraphEdge> graph_edges;
  int loop_closures = 0;
  int keyframe_adjustments = 0;
  bool final_adjustment_done = false;  // SlamSystem::AdjustAllKeyframes ran
  // SlamOptions::final_adjustment_relit: the metres per world unit from the shading (0 = not yet
  // estimated, < 0 = failed).
  double relit_metres_per_world_unit = 0;
  // The keyframe pairs' shading scales it is the median of (metres per world unit).
  std::vector<double> relit_pair_estimates;
  // Estimates relit_metres_per_world_unit once (median over consecutive finished keyframe pairs).
  double RelitMetresPerWorldUnit();
  // The shading scale of each consecutive finished keyframe pair among the first num_keyframes
  // (EstimateShadingScale at the current poses and depths; metres per world unit); empty without three
  // point lights.
  std::vector<double> PairShadingScales(size_t num_keyframes) const;
  // The consecutive finished pairs among the first num_keyframes. With `own_depth` the inverse depths
  // are copies (the images are shared: a keyframe's image is never written after it is made).
  std::vector<slam_internal::ShadingPair> ShadingPairs(size_t num_keyframes, bool own_depth) const;
  // The start check's pair shading scales on their own thread (SlamOptions::start_check_async): started
  // by SlamSystem::StepStartCheck on a copy of the pairs, taken by it once done. The next keyframe waits
  // for them (MakeKeyframe): whether the check closes decides how its window adjustment runs.
  struct PendingStartCheck {
    std::vector<double> scales;
    double thread_seconds = 0;  // on its thread
    double wait_seconds = 0;    // the keyframe's wait for it
    std::future<void> done;
  };
  std::unique_ptr<PendingStartCheck> pending_start_check;
  // Starts pending_start_check over the first num_keyframes.
  void StartPairShadingScales(size_t num_keyframes);
  // Waits for pending_start_check (it stays pending, for StepStartCheck to take).
  void WaitForStartCheck();
  // Whether the start check closes with these pair scales (it passes, gives too few pairs, or a second
  // start would have the same baseline), as StepStartCheck decides.
  bool StartCheckCloses(const std::vector<double>& scales) const;
  // SlamSystem::ProcessFrame on this state.
  StatusOr<SlamFrameResult> Process(double timestamp, const cv::Mat& rgb);
  SlamTimings timings;
  // Tracks the initialisation frames on the first, rough depth: a looser residual limit.
  std::unique_ptr<Tracker> init_tracker;

  struct Keyframe {
    int id = 0;
    int64_t frame_id = 0;
    double timestamp = 0;
    Sim3d world_from_keyframe;
    cv::Mat rgb;
    InverseDepthMap final_depth;  // set when finished
    cv::Mat grey_j;               // shading-normalised grey, for the keyframe adjustment (on demand)
    // The keyframe adjustment's points of a finished keyframe (host 0): they depend only on grey_j and
    // final_depth, so they are selected once; cleared when final_depth is replaced.
    std::vector<DirectBaPoint> window_points;
    int window_points_cell_px = 0;  // the cell size they were selected with; 0: none selected
    void DropWindowPoints() {
      std::vector<DirectBaPoint>().swap(window_points);
      window_points_cell_px = 0;
    }
    bool finished = false;
    bool handed_out = false;
    // The first keyframe made from a frame tracked on this one (its frame's record is on this keyframe);
    // -1 while there is none. SlamOptions::distribute_keyframe_corrections.
    int next = -1;
  };
  std::vector<Keyframe> keyframes;
  std::unique_ptr<KeyframeDepth> current_depth;  // of keyframes.back() while tracking
  // The depth the newest keyframe was propagated from (keyframe previous_depth_kf), kept until the
  // keyframe adjustment that follows it has run (AdjustKeyframeWindow re-propagates from it).
  std::unique_ptr<KeyframeDepth> previous_depth;
  int previous_depth_kf = -1;
  int frames_since_keyframe = 0;
  bool skip_depth_update = false;  // for the frame being processed (ProcessFrame's argument)

  struct FrameRecord {
    SlamFrameResult result;
    Rigid3d frame_from_keyframe;  // valid when result.keyframe_id >= 0
  };
  std::vector<FrameRecord> frames;
  bool initialized = false;
  double init_parallax_px = 0;  // the median feature motion the initialisation ran with
  int lost_count = 0;
  // Motion model: the last two good frame_from_keyframe (same keyframe) poses.
  bool has_last = false, has_prev = false;
  Rigid3d last_frame_from_kf, prev_frame_from_kf;

  // Initialisation.
  struct InitFrame {
    int64_t frame_id;
    double timestamp;
    cv::Mat rgb;
  };
  std::vector<InitFrame> init_frames;
  cv::Mat init_prev_grey;
  std::vector<cv::Point2f> init_points0, init_points;

  StatusOr<SlamFrameResult> Initialise(int64_t frame_id, double timestamp, const cv::Mat& rgb);
  bool TryInitialise(std::string* why);
  // The last buffered frame's pose relative to the first from the essential matrix of the KLT features
  // (R, t, the RANSAC inliers) and the parallax it rests on, pixels. False, with *why, while the parallax
  // is short of init_min_parallax_fraction or the motion is ambiguous.
  bool EstimateInitMotion(double* parallax, Eigen::Matrix3d* R, Eigen::Vector3d* t, cv::Mat* inlier_mask,
                          std::string* why) const;
  // The initialisation's RANSAC inliers (inlier_mask) triangulated at the midpoint of the two rays, in the
  // first camera, with their pixels there; R, t: the essential matrix's pose of the last frame.
  void TriangulateInitFeatures(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const cv::Mat& inlier_mask,
                               std::vector<Eigen::Vector3d>* points, std::vector<cv::Point2f>* pixels) const;
  // TryInitialise's passes (1 + init_rounds): the buffered frames tracked against the first one, whose depth
  // (*depth, seeded from `dense`) is refined by stereo with them; their poses and alignments. False, with
  // *why, when a pass fails.
  bool TrackInitialisationFrames(const DepthFilterOptions& init_depth, const cv::Mat& dense,
                                 const std::vector<cv::Mat>& init_j, ThreadPool* init_pool, const Rigid3d& last_guess,
                                 std::unique_ptr<KeyframeDepth>* depth_in_out, std::vector<Rigid3d>* poses_out,
                                 std::vector<SlamTrackingQuality>* quality_out, std::string* why);
  void ResetInit(int64_t frame_id, double timestamp, const cv::Mat& rgb);
  StatusOr<SlamFrameResult> TrackFrame(int64_t frame_id, double timestamp, const cv::Mat& rgb);
  Status MakeKeyframe(int64_t frame_id, double timestamp, const cv::Mat& rgb, int reference_kf,
                      const Rigid3d& frame_from_reference, const KeyframeDepth& source);
  Status RefreshTracker();
  // RefreshTracker, or, when the current keyframe's depth has too few points for it, the tracker goes on
  // with its earlier copy of the same keyframe (Tracker::SetKeyframe changes nothing when it fails).
  void RefreshTrackerOrKeep(int64_t frame_id);
  // Hands `depth` (of the keyframe image `rgb`) to the frame tracker, with the SlamOptions::tracking_*
  // thresholds.
  Status SetTrackerKeyframe(const cv::Mat& rgb, const KeyframeDepth& depth);
  // A new keyframe depth for `rgb`, propagated from `source` along this_from_source, once the frame
  // tracker has accepted it (FailedPrecondition otherwise; the tracker's keyframe is then unusable).
  // `blank`: when given, a KeyframeDepth of the same image rgb (its Blank() replaces Create).
  StatusOr<KeyframeDepth> PropagateForTracking(const cv::Mat& rgb, const KeyframeDepth& source,
                                               const Rigid3d& this_from_source, const KeyframeDepth* blank = nullptr);
  bool Relocalise(const cv::Mat& rgb, Rigid3d* frame_from_kf, int* keyframe_index);
  void FinishCurrent();
  // Loop closure for finished keyframe `index` (see SlamOptions::loop_closure); re-optimises the pose
  // graph when an edge was added.
  void CloseLoops(int index);
  bool AlignKeyframes(int j, int k, Sim3d* j_from_k, std::string* why);
  // The frame's pose: its keyframe's pose composed with frame_from_keyframe, and with corrected the share of
  // the next keyframe's correction (SlamOptions::distribute_keyframe_corrections).
  Rigid3d WorldFromFrame(const FrameRecord& f, bool corrected = true) const;
  // Whether a tracked frame_from_keyframe is within SlamOptions::max_step_* of the prediction.
  bool PlausibleStep(const Rigid3d& tracked, const Rigid3d& predicted, double mean_inverse_depth) const {
    const double rotation_deg =
        RotationAngle(tracked.rotation * predicted.rotation.inverse()) * slam_internal::kRadToDeg;
    const double translation = (tracked.translation - predicted.translation).norm() * mean_inverse_depth;
    return rotation_deg <= options.max_step_rotation_deg && translation <= options.max_step_translation_fraction;
  }
  // The direct adjustment of keyframes first..newest (keyframe_ba.h): after a new keyframe over the
  // window (SlamOptions::keyframe_adjustment), after Finish over all keyframes (final_adjustment).
  void AdjustKeyframes(int first, const DirectBaOptions& ba_options, bool at_finish);
  // Keyframe 0's refinement seed (final_refinement_first_from_second), in its units.
  cv::Mat SeedFromSecondKeyframe(const KeyframeDepth& first, const cv::Mat& first_inverse_depth,
                                 const cv::Mat& second_inverse_depth);
  // The adjustment's problem over keyframes first..newest (false: too few points); with `relit`, the
  // relit residual at metres_per_world_unit, estimated with the poses.
  bool BuildAdjustmentProblem(int first, bool relit, bool mixed, double metres_per_world_unit, double min_band_fraction,
                              DirectBaProblem* problem);
  // The first keyframe of the adjustment window: from `first`, older keyframes that share less than
  // keyframe_window_min_overlap of the newest keyframe's view are left out (at least 3 stay).
  int WindowStart(int first) const;
  // The fraction of keyframe k's final depth (every 8th pixel in each direction) that projects into
  // keyframe j (DepthOverlapFraction); 1 while k is not finished.
  double DepthOverlap(int k, int j) const;
  // The adjustment of all keyframes at once is possible: adjustment on, every keyframe finished, at most
  // final_adjustment_max_keyframes of them.
  bool CanAdjustAllKeyframes() const {
    return options.keyframe_adjustment && !keyframes.empty() &&
           static_cast<int>(keyframes.size()) <= options.final_adjustment_max_keyframes && keyframes.back().finished;
  }
  // Beyond the direct adjustment's limit, the feature adjustment alone is possible: on, every keyframe
  // finished, more than final_adjustment_max_keyframes and at most feature_adjustment_max_keyframes.
  bool CanAdjustByFeaturesAlone() const {
    const int n = static_cast<int>(keyframes.size());
    return options.final_feature_adjustment && options.keyframe_adjustment && !keyframes.empty() &&
           keyframes.back().finished && n > options.final_adjustment_max_keyframes &&
           n <= options.feature_adjustment_max_keyframes;
  }
  // After an adjustment: the newest keyframe's depth propagated again, along the adjusted pose.
  void RepropagateNewestKeyframe();
  // The feature adjustment of every keyframe (SlamOptions::final_feature_adjustment), when the final
  // adjustment's conditions hold: the keyframes, the odometry edges and the frames move.
  void AdjustByFeatures();
  FeatureAdjustmentReport feature_report;
  std::unique_ptr<FeatureTracks> feature_tracks;  // of the keyframes, once built (AdjustByFeatures)
  int feature_tracks_failed_for = -1;             // the number of keyframes whose tracks failed
  // After keyframes first.. moved: the odometry edges between consecutive ones and the frames tracked on
  // keyframes first_moved.. follow.
  void FollowKeyframes(int first_edge, int first_moved);
  // A window adjustment: its problem, set up from keyframes first..num_keyframes-1, and its result
  // (solved inline, or on its own thread with SlamOptions::keyframe_adjustment_async).
  struct PendingAdjustment {
    int first = 0;
    int num_keyframes = 0;
    bool at_finish = false, relit = false, mixed = false;
    DirectBaProblem problem;
    std::vector<float> initial_inverse_depth;  // of problem.points, before the adjustment
    StatusOr<DirectBaSummary> summary = InternalError("keyframe adjustment not run");
    double seconds = 0;      // its wall time on its thread
    std::future<void> done;  // keyframe_adjustment_async
  };
  // The adjustment's result in the keyframes, edges and frames (and the re-propagation).
  void ApplyAdjustment(PendingAdjustment* job);
  // Waits for the adjustment running on its own thread, if any, and applies it. With `max_wait_ms` >= 0
  // it waits at most that long: false when the adjustment is still running then (it stays pending).
  bool ApplyPendingAdjustment(double max_wait_ms = -1);
  // Every frame: applies the adjustment running on its thread if it has finished, and starts the window
  // adjustment owed since a keyframe was made while it ran (SlamOptions::keyframe_adjustment_max_wait_ms).
  void PollPendingAdjustment();
  // The window adjustment over the newest keyframes (SlamOptions::keyframe_window).
  void AdjustWindow() {
    AdjustKeyframes(WindowStart(std::max(0, static_cast<int>(keyframes.size()) - options.keyframe_window)),
                    options.keyframe_window_ba, /*at_finish=*/false);
  }
  // A keyframe was made while an adjustment ran on its thread: the window adjustment it would have
  // started is owed (PollPendingAdjustment starts it once that one has been applied).
  bool adjustment_owed = false;
  // Starts the owed window adjustment.
  void StartOwedAdjustment() {
    adjustment_owed = false;
    ++timings.adjustments_started_late;
    AdjustWindow();
  }
  // The pose of the most recent tracked frame (identity before any).
  Rigid3d LastGoodWorldFromCamera() const;
  // Set while the start check runs (SlamSystem::start_check_): the window adjustment then stays inline,
  // with the re-propagation (see SlamOptions::keyframe_adjustment_async).
  bool start_check_running = false;
  // Whether the next window adjustment runs on its own thread.
  bool AdjustAsync() const { return options.keyframe_adjustment_async && !start_check_running; }
  // The window adjustment's cell size now (SlamOptions::start_check_window_cell_px while the check runs).
  int WindowCellPx() const {
    return start_check_running ? options.start_check_window_cell_px : options.keyframe_window_cell_px;
  }
  // The adjustment running on its own thread (keyframe_adjustment_async). Last member: destroyed first,
  // its future waits for the thread.
  std::unique_ptr<PendingAdjustment> pending_adjustment;
};

struct SlamSystem::StartCheck {
  struct Frame {
    double timestamp;
    cv::Mat rgb;
  };
  // Where the second start on its thread closed the check: at `frame`, with that frame's result and, when
  // it had start_check_keyframes keyframes there, its pair shading scales; kept, the result of the last
  // frame it caught up with.
  struct SecondStartEnd {
    bool decided = false;  // it reached start_check_keyframes keyframes or start_check_max_frames frames
    size_t frame = 0;
    std::optional<StatusOr<SlamFrameResult>> result;
    std::optional<StatusOr<SlamFrameResult>> last;
    bool enough_keyframes = false;
    std::vector<double> scales;
  };
  ~StartCheck();
  // Runs the second start (retry) on its own thread over `frames`, waiting for each new one, until it has
  // start_check_keyframes keyframes or start_check_max_frames frames. When it spreads less than
  // `first_spread` (kept) it sets `keeping` and goes on over the frames until the caller sets catch_up
  // and it has them all.
  void StartSecondStartThread(size_t num_keyframes, size_t max_frames, double first_spread);
  void AddFrame(double timestamp, const cv::Mat& rgb);

  std::mutex mutex;
  std::condition_variable more;
  std::vector<Frame> frames;  // every frame so far; guarded by mutex while second_start runs
  bool stop = false;          // guarded by mutex: the thread returns before its next frame
  bool catch_up = false;      // guarded by mutex: the thread returns once it has every frame
  std::atomic<bool> keeping{false};
  size_t check_frame = 0;       // the index of the frame the first start was checked at
  std::unique_ptr<Impl> retry;  // the second start, once the first failed the check
  // SlamOptions::start_check_async: the second start's thread. Last member: waited for before retry goes.
  std::future<SecondStartEnd> second_start;
};

}  // namespace prism
