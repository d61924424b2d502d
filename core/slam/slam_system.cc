#include "core/slam/slam_system.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <future>
#include <limits>
#include <sstream>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>

#include "core/photometric/depth_prior.h"
#include "core/slam/pose_graph.h"
#include "core/slam/shading_scale.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

// How a frame's alignment went (SlamFrameResult::tracking): tr, tracked from `guess`, whether it was
// tracked again from the last pose, the previous frame's pose on the same keyframe, and the keyframe's
// mean inverse depth (distances as fractions of the mean depth).
SlamTrackingQuality QualityOf(const TrackingResult& tr, bool retried, const Rigid3d& guess,
                              const Rigid3d& previous_from_keyframe, double mean_idepth) {
  SlamTrackingQuality q;
  q.tracked = true;
  q.residual_rms = tr.residual_rms;
  q.visible_fraction = tr.visible_fraction;
  q.inlier_fraction = tr.inlier_fraction;
  for (int n : tr.iterations) q.iterations += n;
  q.retried = retried;
  const Rigid3d frame_from_previous = tr.frame_from_keyframe * previous_from_keyframe.Inverse();
  q.step = frame_from_previous.translation.norm() * mean_idepth;
  q.rotation_deg = RotationAngle(frame_from_previous.rotation) * kRadToDeg;
  q.guess_correction = (tr.frame_from_keyframe.translation - guess.translation).norm() * mean_idepth;
  return q;
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

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

Sim3d ToSim3(const Rigid3d& r) { return Sim3d(1.0, r.rotation, r.translation); }

cv::Mat ToGrey8(const cv::Mat& rgb) {
  cv::Mat grey;
  cv::cvtColor(rgb, grey, cv::COLOR_RGB2GRAY);
  return grey;
}

// The initialisation's KLT image (SlamOptions::init_track_normalised) and, when `local_mean` is
// given, the raw box mean of the depth filter's normalisation.
cv::Mat KltImage(const cv::Mat& rgb, const SlamOptions& options, cv::Mat* local_mean) {
  if (!options.init_track_normalised) {
    cv::Mat grey = ToGrey8(rgb);
    if (local_mean != nullptr) {
      const int k = 2 * options.depth.local_mean_radius_px + 1;
      cv::blur(grey, *local_mean, cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
    }
    return grey;
  }
  cv::Mat j, mean, j8;
  KeyframeDepth::NormalisedGrey(rgb, options.depth, &j, &mean);
  j.convertTo(j8, CV_8U);  // J is about 128 on average; saturates at 255
  if (local_mean != nullptr) *local_mean = mean;
  return j8;
}

// Every light of the rig is a point light with an intensity (what the shading scale models).
bool AllPointLights(const RigCalibration& rig) {
  for (const Light& l : rig.lights)
    if (l.type != LightType::kPoint || !(l.intensity > 0)) return false;
  return true;
}

// The rig has a light with an intensity (it moves with the camera).
bool AnyLight(const RigCalibration& rig) {
  for (const Light& l : rig.lights)
    if (l.intensity > 0) return true;
  return false;
}

// The interquartile range of keyframe pairs' shading scales over their median (0 when empty).
double PairSpread(std::vector<double> estimates) {
  if (estimates.empty()) return 0;
  std::sort(estimates.begin(), estimates.end());
  const size_t n = estimates.size();
  const double median = estimates[n / 2];
  return (estimates[std::min((3 * n) / 4, n - 1)] - estimates[n / 4]) / median;
}

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
                                               ThreadPool* pool = nullptr) {
  const ShadingScaleOptions so;
  std::vector<double> scales(pairs.size(), 0.0);
  std::vector<char> found(pairs.size(), 0);
  const auto one = [&](std::ptrdiff_t i) {
    const ShadingPair& p = pairs[static_cast<size_t>(i)];
    const std::vector<ShadingScaleFrame> frames = {
        {p.newer_rgb, BFromAInUnitsOfA(p.world_from_older, p.world_from_newer)}};
    StatusOr<ShadingScaleResult> r = EstimateShadingScale(rig, p.older_rgb, p.older_inverse_depth, frames, so);
    if (!r.ok()) return;
    scales[static_cast<size_t>(i)] = r->metres_per_unit / p.world_from_older.scale;
    found[static_cast<size_t>(i)] = 1;
  };
  if (pool && pool->num_threads() > 1 && pairs.size() > 1) {
    pool->ParallelFor(0, static_cast<std::ptrdiff_t>(pairs.size()), one);
  } else {
    for (size_t i = 0; i < pairs.size(); ++i) one(static_cast<std::ptrdiff_t>(i));
  }
  std::vector<std::pair<int, double>> estimates;
  for (size_t i = 0; i < pairs.size(); ++i)
    if (found[i]) estimates.emplace_back(pairs[i].older, scales[i]);
  return estimates;
}

}  // namespace

Status SlamOptions::Check() const {
  PRISM_RETURN_IF_ERROR(tracker.Check());
  PRISM_RETURN_IF_ERROR(wide_baseline_tracker.Check());
  PRISM_RETURN_IF_ERROR(depth.Check());
  if (!(keyframe_distance_fraction > 0))
    return InvalidArgumentError("SlamOptions: keyframe_distance_fraction must be > 0");
  if (!(keyframe_min_visible_fraction >= 0 && keyframe_min_visible_fraction <= 1))
    return InvalidArgumentError("SlamOptions: keyframe_min_visible_fraction must be in [0, 1]");
  if (!(keyframe_max_rotation_deg > 0))
    return InvalidArgumentError("SlamOptions: keyframe_max_rotation_deg must be > 0");
  if (init_min_frames < 2) return InvalidArgumentError("SlamOptions: init_min_frames must be >= 2");
  if (init_rounds < 1 || init_rounds > 10) return InvalidArgumentError("SlamOptions: init_rounds must be in [1, 10]");
  if (init_threads < 1 || init_threads > 64)
    return InvalidArgumentError("SlamOptions: init_threads must be in [1, 64]");
  if (!(init_min_parallax_fraction > 0))
    return InvalidArgumentError("SlamOptions: init_min_parallax_fraction must be > 0");
  if (init_max_frames < init_min_frames)
    return InvalidArgumentError("SlamOptions: init_max_frames must be >= init_min_frames");
  if (!(init_min_feature_local_mean >= 0 && init_min_feature_local_mean <= 255))
    return InvalidArgumentError("SlamOptions: init_min_feature_local_mean must be in [0, 255]");
  if (relocalise_max_keyframes < 1) return InvalidArgumentError("SlamOptions: relocalise_max_keyframes must be >= 1");
  if (!(new_pixel_relative_sigma > 0)) return InvalidArgumentError("SlamOptions: new_pixel_relative_sigma must be > 0");
  if (tracker_refresh_frames < 1) return InvalidArgumentError("SlamOptions: tracker_refresh_frames must be >= 1");
  if (depth_update_interval < 1) return InvalidArgumentError("SlamOptions: depth_update_interval must be >= 1");
  if (!(mapping_budget_ms >= 0)) return InvalidArgumentError("SlamOptions: mapping_budget_ms must be >= 0");
  if (loop_min_keyframe_gap < 2) return InvalidArgumentError("SlamOptions: loop_min_keyframe_gap must be >= 2");
  if (!(loop_max_distance_fraction > 0))
    return InvalidArgumentError("SlamOptions: loop_max_distance_fraction must be > 0");
  if (!(loop_max_angle_deg > 0 && loop_max_angle_deg <= 180))
    return InvalidArgumentError("SlamOptions: loop_max_angle_deg must be in (0, 180]");
  if (loop_max_candidates < 1) return InvalidArgumentError("SlamOptions: loop_max_candidates must be >= 1");
  if (!(loop_max_rotation_inconsistency_deg > 0))
    return InvalidArgumentError("SlamOptions: loop_max_rotation_inconsistency_deg must be > 0");
  if (loop_min_depth_matches < 10) return InvalidArgumentError("SlamOptions: loop_min_depth_matches must be >= 10");
  for (double sigma : {odometry_rotation_sigma, odometry_translation_sigma, odometry_log_scale_sigma,
                       loop_rotation_sigma, loop_translation_sigma, loop_log_scale_sigma})
    if (!(sigma > 0)) return InvalidArgumentError("SlamOptions: pose-graph sigmas must be > 0");
  if (!(max_step_rotation_deg > 0) || !(max_step_translation_fraction > 0))
    return InvalidArgumentError("SlamOptions: max_step_rotation_deg and max_step_translation_fraction must be > 0");
  if (keyframe_window < 3) return InvalidArgumentError("SlamOptions: keyframe_window must be >= 3");
  if (keyframe_window_cell_px < 4) return InvalidArgumentError("SlamOptions: keyframe_window_cell_px must be >= 4");
  if (!(keyframe_window_min_overlap >= 0 && keyframe_window_min_overlap <= 1))
    return InvalidArgumentError("SlamOptions: keyframe_window_min_overlap must be in [0, 1]");
  if (keyframe_window_min_points < 10)
    return InvalidArgumentError("SlamOptions: keyframe_window_min_points must be >= 10");
  if (keyframe_adjustment_interval < 1)
    return InvalidArgumentError("SlamOptions: keyframe_adjustment_interval must be >= 1");
  PRISM_RETURN_IF_ERROR(keyframe_window_ba.Check());
  if (final_adjustment_max_keyframes < 3)
    return InvalidArgumentError("SlamOptions: final_adjustment_max_keyframes must be >= 3");
  if (feature_adjustment_max_keyframes < 3)
    return InvalidArgumentError("SlamOptions: feature_adjustment_max_keyframes must be >= 3");
  if (final_refinement_neighbours < 0 || final_refinement_neighbours > 5)
    return InvalidArgumentError("SlamOptions: final_refinement_neighbours must be in [0, 5]");
  if (!(final_refinement_relative_sigma > 0))
    return InvalidArgumentError("SlamOptions: final_refinement_relative_sigma must be > 0");
  if (final_refinement_rounds < 1 || final_refinement_rounds > 10)
    return InvalidArgumentError("SlamOptions: final_refinement_rounds must be in [1, 10]");
  PRISM_RETURN_IF_ERROR(final_adjustment_ba.Check());
  PRISM_RETURN_IF_ERROR(feature_adjustment.Check());
  if (!(feature_adjustment_min_overlap >= 0 && feature_adjustment_min_overlap <= 1))
    return InvalidArgumentError("SlamOptions: feature_adjustment_min_overlap must be in [0, 1]");
  PRISM_RETURN_IF_ERROR(final_adjustment_relit_ba.Check());
  if (!(metric_scale_max_pair_spread > 0))
    return InvalidArgumentError("SlamOptions: metric_scale_max_pair_spread must be > 0");
  if (scale_drift_window < 0) return InvalidArgumentError("SlamOptions: scale_drift_window must be >= 0");
  if (start_check_keyframes != 0 && start_check_keyframes < 4)
    return InvalidArgumentError("SlamOptions: start_check_keyframes must be 0 (off) or >= 4");
  if (!(start_check_max_pair_spread > 0) || !(start_check_retry_parallax_fraction > 0))
    return InvalidArgumentError(
        "SlamOptions: start_check_max_pair_spread and start_check_retry_parallax_fraction must be > 0");
  if (start_check_max_frames < 1) return InvalidArgumentError("SlamOptions: start_check_max_frames must be >= 1");
  if (start_check_window_cell_px < 4)
    return InvalidArgumentError("SlamOptions: start_check_window_cell_px must be >= 4");
  if (!(metric_scale_min_band_fraction >= 0 && metric_scale_min_band_fraction < 1))
    return InvalidArgumentError("SlamOptions: metric_scale_min_band_fraction must be in [0, 1)");
  if (!(final_adjustment_mixed_relit_scale > 0))
    return InvalidArgumentError("SlamOptions: final_adjustment_mixed_relit_scale must be > 0");
  if (final_adjustment_mixed && final_adjustment_ba.pyramid_levels != 1)
    return InvalidArgumentError("SlamOptions: final_adjustment_mixed needs final_adjustment_ba.pyramid_levels = 1");
  if (final_adjustment_relit && final_adjustment_relit_ba.pyramid_levels != 1)
    return InvalidArgumentError("SlamOptions: final_adjustment_relit_ba.pyramid_levels must be 1");
  return Status::Ok();
}

const char* SlamStateName(SlamState state) {
  switch (state) {
    case SlamState::kInitializing:
      return "initializing";
    case SlamState::kTracking:
      return "tracking";
    case SlamState::kLost:
      return "lost";
  }
  return "unknown";
}

struct SlamSystem::Impl {
  RigCalibration rig;
  SlamOptions options;
  ThreadPool* pool = nullptr;
  std::unique_ptr<Tracker> tracker;
  std::unique_ptr<Tracker> reloc_tracker;
  std::unique_ptr<Tracker> loop_tracker;
  std::vector<PoseGraphEdge> graph_edges;
  std::vector<uint8_t> graph_edge_is_loop;  // per graph_edges entry
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
  // The same with each pair's older keyframe index.
  std::vector<std::pair<int, double>> IndexedPairShadingScales(size_t num_keyframes) const;
  // The consecutive finished pairs among the first num_keyframes. With `own_depth` the inverse depths
  // are copies (the images are shared: a keyframe's image is never written after it is made).
  std::vector<ShadingPair> ShadingPairs(size_t num_keyframes, bool own_depth) const;
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
  void ResetInit(int64_t frame_id, double timestamp, const cv::Mat& rgb);
  StatusOr<SlamFrameResult> TrackFrame(int64_t frame_id, double timestamp, const cv::Mat& rgb);
  Status MakeKeyframe(int64_t frame_id, double timestamp, const cv::Mat& rgb, int reference_kf,
                      const Rigid3d& frame_from_reference, const KeyframeDepth& source);
  Status RefreshTracker();
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
    const double rotation_deg = RotationAngle(tracked.rotation * predicted.rotation.inverse()) * kRadToDeg;
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

StatusOr<std::unique_ptr<SlamSystem::Impl>> SlamSystem::NewImpl(const RigCalibration& rig, const SlamOptions& options,
                                                                ThreadPool* pool) {
  auto impl = std::make_unique<Impl>();
  impl->rig = rig;
  impl->options = options;
  impl->pool = pool;
  // Without lights on the rig (KITTI: daylight) the settings that target the co-moving lights' effects are
  // off: the camera-attached tests (only false alarms there), the initialisation's KLT on J (raw grey tracks
  // better), the final adjustment's gradient weight and the local mean's edge test (the pattern moves with
  // the scene).
  if (!AnyLight(rig)) {
    impl->options.tracker.camera_attached_min_votes = 0;
    impl->options.depth.camera_attached_min_votes = 0;
    impl->options.depth.max_local_mean_log_gradient = 0;
    impl->options.init_track_normalised = false;
    impl->options.init_min_feature_local_mean = 0;
    impl->options.final_adjustment_ba.gradient_weight_c = 0;
  }
  PRISM_ASSIGN_OR_RETURN(Tracker t, Tracker::Create(rig, impl->options.tracker));
  impl->tracker = std::make_unique<Tracker>(std::move(t));
  // The wide-baseline tracker's extra level is dropped on images too small for it (coarsest side >= 8).
  TrackerOptions wide = options.wide_baseline_tracker;
  while (wide.pyramid_levels > options.tracker.pyramid_levels &&
         std::min(rig.camera.width, rig.camera.height) >> (wide.pyramid_levels - 1) < 8)
    --wide.pyramid_levels;
  PRISM_ASSIGN_OR_RETURN(Tracker r, Tracker::Create(rig, wide));
  impl->reloc_tracker = std::make_unique<Tracker>(std::move(r));
  PRISM_ASSIGN_OR_RETURN(Tracker l, Tracker::Create(rig, wide));
  impl->loop_tracker = std::make_unique<Tracker>(std::move(l));
  TrackerOptions init_options = impl->options.tracker;
  init_options.max_residual_rms *= options.init_residual_factor;
  PRISM_ASSIGN_OR_RETURN(Tracker it, Tracker::Create(rig, init_options));
  impl->init_tracker = std::make_unique<Tracker>(std::move(it));
  return impl;
}

struct SlamSystem::StartCheck {
  struct Frame {
    double timestamp;
    cv::Mat rgb;
  };
  std::vector<Frame> frames;    // every frame so far
  size_t check_frame = 0;       // the index of the frame the first start was checked at
  std::unique_ptr<Impl> retry;  // the second start, once the first failed the check
};

StatusOr<std::unique_ptr<SlamSystem>> SlamSystem::Create(const RigCalibration& rig, const SlamOptions& options,
                                                         ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.camera.Check());
  if (rig.camera.HasDistortion())
    return InvalidArgumentError("SlamSystem: undistort the images first (camera has distortion)");
  PRISM_ASSIGN_OR_RETURN(std::unique_ptr<Impl> impl, NewImpl(rig, options, pool));
  std::unique_ptr<SlamSystem> slam(new SlamSystem(std::move(impl)));
  if (options.start_check_keyframes > 0 && rig.lights.size() == 3 && AllPointLights(rig))
    slam->start_check_ = std::make_unique<StartCheck>();
  return slam;
}

SlamSystem::SlamSystem(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
SlamSystem::~SlamSystem() = default;

StatusOr<SlamFrameResult> SlamSystem::ProcessFrame(double timestamp, const cv::Mat& rgb, bool skip_depth_update) {
  const PinholeCamera& cam = impl_->rig.camera;
  if (rgb.type() != CV_8UC3 || rgb.cols != cam.width || rgb.rows != cam.height) {
    std::ostringstream m;
    m << "SlamSystem::ProcessFrame: expected a CV_8UC3 image of " << cam.width << "x" << cam.height << ", got "
      << rgb.cols << "x" << rgb.rows << " type " << rgb.type();
    return InvalidArgumentError(m.str());
  }
  impl_->skip_depth_update = skip_depth_update;
  impl_->start_check_running = start_check_ != nullptr;
  StatusOr<SlamFrameResult> r = impl_->Process(timestamp, rgb);
  impl_->skip_depth_update = false;
  if (start_check_) StepStartCheck(timestamp, rgb, &r);
  return r;
}

StatusOr<SlamFrameResult> SlamSystem::Impl::Process(double timestamp, const cv::Mat& rgb) {
  const int64_t frame_id = static_cast<int64_t>(frames.size());
  if (!initialized) {
    const ScopedSeconds timer(&timings.initialisation);
    return Initialise(frame_id, timestamp, rgb);
  }
  return TrackFrame(frame_id, timestamp, rgb);
}

void SlamSystem::StepStartCheck(double timestamp, const cv::Mat& rgb, StatusOr<SlamFrameResult>* result) {
  const ScopedSeconds timer(&start_check_report_.seconds);
  StartCheck& c = *start_check_;
  const SlamOptions o = impl_->options;  // a copy: impl_ may be replaced below
  const size_t n = static_cast<size_t>(o.start_check_keyframes);
  c.frames.push_back({timestamp, rgb.clone()});
  if (!c.retry) {
    if (impl_->keyframes.size() < n) {
      if (static_cast<int>(c.frames.size()) >= o.start_check_max_frames) {
        PRISM_LOG(INFO) << "slam: start check: fewer than " << n << " keyframes after " << c.frames.size()
                        << " frames; not checked";
        start_check_.reset();
      }
      return;
    }
    const auto check_start = std::chrono::steady_clock::now();
    std::vector<double> first;
    if (o.start_check_async) {
      // The pair scales run on their own thread from this frame on; taken at the first frame after they
      // are done (the next keyframe waits for them).
      Impl::PendingStartCheck* pending = impl_->pending_start_check.get();
      if (pending == nullptr) {
        impl_->ApplyPendingAdjustment();
        impl_->StartPairShadingScales(n);
        c.check_frame = c.frames.size() - 1;
        return;
      }
      if (pending->done.wait_for(std::chrono::seconds(0)) != std::future_status::ready) return;
      first = TakeStartCheckScales();
    } else {
      impl_->ApplyPendingAdjustment();
      first = impl_->PairShadingScales(n);
      c.check_frame = c.frames.size() - 1;
    }
    if (first.size() < 3) {
      PRISM_LOG(INFO) << "slam: start check: " << first.size() << " keyframe pairs gave a shading scale; not checked";
      start_check_.reset();
      return;
    }
    start_check_report_.checked = true;
    start_check_report_.first_spread = PairSpread(first);
    if (start_check_report_.first_spread <= o.start_check_max_pair_spread) {
      start_check_report_.passed = true;
      PRISM_LOG(INFO) << "slam: start check passed: the first " << n << " keyframes' pair shading scales spread by "
                      << start_check_report_.first_spread << " (" << 1000 * SecondsSince(check_start) << " ms)";
      start_check_.reset();
      return;
    }
    if (impl_->init_parallax_px >= o.start_check_retry_parallax_fraction * impl_->rig.camera.width) {
      PRISM_LOG(WARNING) << "slam: start check failed: the first " << n << " keyframes' pair shading scales spread by "
                         << start_check_report_.first_spread << " (limit " << o.start_check_max_pair_spread
                         << "), but its initialisation already had the second "
                         << "start's baseline (" << impl_->init_parallax_px << " px); the first start is kept";
      start_check_.reset();
      return;
    }
    PRISM_LOG(WARNING) << "slam: start check failed: the first " << n << " keyframes' pair shading scales spread by "
                       << start_check_report_.first_spread << " (limit " << o.start_check_max_pair_spread
                       << "); starting again from frame 0 with a longer initialisation baseline ("
                       << o.start_check_retry_parallax_fraction << " of the width) alongside";
    SlamOptions retry_options = o;
    retry_options.init_min_parallax_fraction = o.start_check_retry_parallax_fraction;
    StatusOr<std::unique_ptr<Impl>> retry = NewImpl(impl_->rig, retry_options, impl_->pool);
    if (!retry.ok()) {
      PRISM_LOG(WARNING) << "slam: start check: " << retry.status();
      start_check_.reset();
      return;
    }
    c.retry = std::move(*retry);
    c.retry->start_check_running = true;
    start_check_report_.retried = true;
    // The second start runs over the frames up to the one the first was checked at, at once (inline that
    // is this frame; on its thread an earlier one), then frame by frame, checked after each as if it had
    // run alongside the first from the check's frame on.
    for (size_t i = 0; i < c.check_frame; ++i) {
      StatusOr<SlamFrameResult> r = c.retry->Process(c.frames[i].timestamp, c.frames[i].rgb);
      if (!r.ok()) {
        PRISM_LOG(WARNING) << "slam: start check: second start: " << r.status();
      }
    }
    for (size_t i = c.check_frame; i < c.frames.size(); ++i) {
      StatusOr<SlamFrameResult> second = c.retry->Process(c.frames[i].timestamp, c.frames[i].rgb);
      if (!StepSecondStart(i, &second)) continue;
      // Closed at frame i. Kept, the second start goes on over the frames after it (as the only start, as
      // if it had been kept there); the caller gets this frame's result from it.
      if (start_check_report_.second_kept) {
        for (size_t j = i + 1; j < c.frames.size(); ++j)
          second = impl_->Process(c.frames[j].timestamp, c.frames[j].rgb);
        *result = std::move(second);
      }
      start_check_.reset();
      return;
    }
    return;
  }
  StatusOr<SlamFrameResult> second = c.retry->Process(timestamp, rgb);
  if (!StepSecondStart(c.frames.size() - 1, &second)) return;
  if (start_check_report_.second_kept) *result = std::move(second);
  start_check_.reset();
}

std::vector<double> SlamSystem::TakeStartCheckScales() {
  std::unique_ptr<Impl::PendingStartCheck> pending = std::move(impl_->pending_start_check);
  pending->done.get();  // waits; rethrows what the thread threw
  start_check_report_.thread_seconds = pending->thread_seconds;
  start_check_report_.seconds += pending->wait_seconds;
  return std::move(pending->scales);
}

bool SlamSystem::StepSecondStart(size_t frame, StatusOr<SlamFrameResult>* second) {
  StartCheck& c = *start_check_;
  const SlamOptions o = impl_->options;  // a copy: impl_ may be replaced below
  const size_t n = static_cast<size_t>(o.start_check_keyframes);
  if (c.retry->keyframes.size() < n) {
    if (static_cast<int>(frame + 1) >= o.start_check_max_frames) {
      PRISM_LOG(WARNING) << "slam: start check: the second start has fewer than " << n << " keyframes after "
                         << frame + 1 << " frames; the first start is kept";
      return true;
    }
    return false;
  }
  c.retry->ApplyPendingAdjustment();
  const std::vector<double> again = c.retry->PairShadingScales(n);
  const double spread = again.size() >= 3 ? PairSpread(again) : std::numeric_limits<double>::infinity();
  start_check_report_.second_checked = true;
  start_check_report_.second_spread = spread;
  if (spread < start_check_report_.first_spread && second->ok()) {
    PRISM_LOG(WARNING) << "slam: start check: the second start is kept (pair spread " << spread << " against "
                       << start_check_report_.first_spread << ")";
    impl_ = std::move(c.retry);
    impl_->start_check_running = false;
    start_check_report_.second_kept = true;
  } else {
    PRISM_LOG(WARNING) << "slam: start check: the first start is kept (pair spread " << start_check_report_.first_spread
                       << " against " << spread << " for the second)";
  }
  return true;
}

void SlamSystem::Impl::ResetInit(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  init_frames.clear();
  init_frames.push_back({frame_id, timestamp, rgb.clone()});
  cv::Mat local_mean, feature_mask;
  const bool masked = options.init_min_feature_local_mean > 0;
  init_prev_grey = KltImage(rgb, options, masked ? &local_mean : nullptr);
  if (masked) cv::compare(local_mean, options.init_min_feature_local_mean, feature_mask, cv::CMP_GE);
  init_points0.clear();
  cv::goodFeaturesToTrack(init_prev_grey, init_points0, 800, 0.01, std::max(4, rig.camera.width / 64), feature_mask);
  init_points = init_points0;
}

StatusOr<SlamFrameResult> SlamSystem::Impl::Initialise(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  FrameRecord rec;
  rec.result.frame_id = frame_id;
  rec.result.timestamp = timestamp;
  rec.result.state = SlamState::kInitializing;
  if (init_frames.empty()) {
    ResetInit(frame_id, timestamp, rgb);
    rec.result.message = "initialising: waiting for parallax";
    frames.push_back(rec);
    return rec.result;
  }
  init_frames.push_back({frame_id, timestamp, rgb.clone()});
  cv::Mat grey = KltImage(rgb, options, nullptr);
  std::vector<cv::Point2f> next;
  std::vector<uint8_t> status;
  std::vector<float> err;
  if (!init_points.empty()) {
    cv::calcOpticalFlowPyrLK(init_prev_grey, grey, init_points, next, status, err, cv::Size(21, 21), 3);
  }
  std::vector<cv::Point2f> p0, p1;
  for (size_t i = 0; i < next.size(); ++i) {
    if (!status[i]) continue;
    if (next[i].x < 0 || next[i].y < 0 || next[i].x > rgb.cols - 1 || next[i].y > rgb.rows - 1) continue;
    p0.push_back(init_points0[i]);
    p1.push_back(next[i]);
  }
  init_points0.swap(p0);
  init_points.swap(p1);
  init_prev_grey = grey;
  frames.push_back(rec);

  std::string why;
  if (init_points.size() < 40) {
    why = "too few features tracked since the first frame (restarted initialisation)";
    // The frames so far stay kInitializing with identity poses and no keyframe.
    ResetInit(frame_id, timestamp, rgb);
  } else if (static_cast<int>(init_frames.size()) >= options.init_min_frames && TryInitialise(&why)) {
    initialized = true;
    // TryInitialise filled in the buffered frames' records; return this frame's.
    init_frames.clear();
    return frames.back().result;
  }
  if (!initialized && static_cast<int>(init_frames.size()) >= options.init_max_frames) {
    why += " (no initialisation within init_max_frames, restarted from this frame)";
    ResetInit(frame_id, timestamp, rgb);
  }
  frames.back().result.message = "initialising: " + why;
  return frames.back().result;
}

bool SlamSystem::Impl::TryInitialise(std::string* why) {
  const PinholeCamera& cam = rig.camera;
  std::vector<double> disp;
  for (size_t i = 0; i < init_points.size(); ++i) disp.push_back(cv::norm(init_points[i] - init_points0[i]));
  std::nth_element(disp.begin(), disp.begin() + disp.size() / 2, disp.end());
  const double parallax = disp[disp.size() / 2];
  if (parallax < options.init_min_parallax_fraction * cam.width) {
    *why = "waiting for parallax";
    return false;
  }
  cv::Mat K = (cv::Mat_<double>(3, 3) << cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  cv::Mat inlier_mask;
  cv::Mat E =
      cv::findEssentialMat(init_points0, init_points, K, cv::RANSAC, 0.999, 1.0 * cam.width / 512.0, inlier_mask);
  if (E.rows != 3 || E.cols != 3) {
    *why = "essential matrix estimation failed";
    return false;
  }
  cv::Mat Rm, tm;
  const int good = cv::recoverPose(E, init_points0, init_points, K, Rm, tm, inlier_mask);
  const int inliers = cv::countNonZero(inlier_mask);
  // Features on shading (terminators, shadow edges, highlights) move with the lights, not with the
  // surface, so only a part of them is consistent with one rigid motion: ask for enough RANSAC inliers,
  // nearly all in front of both cameras.
  if (inliers < 30 || inliers < 0.15 * static_cast<double>(init_points.size()) || good < 0.9 * inliers) {
    *why = "relative pose ambiguous (" + std::to_string(good) + " of " + std::to_string(init_points.size()) +
           " features consistent, " + std::to_string(inliers) + " RANSAC inliers, parallax " +
           std::to_string(parallax) + " px)";
    return false;
  }
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = Rm.at<double>(r, c);
    t(r) = tm.at<double>(r, 0);
  }
  // Triangulate (midpoint of the two rays) in the first camera.
  std::vector<Eigen::Vector3d> points;
  std::vector<cv::Point2f> pixels;
  for (size_t i = 0; i < init_points.size(); ++i) {
    if (!inlier_mask.at<uint8_t>(static_cast<int>(i))) continue;
    const Eigen::Vector3d a = cam.Unproject(Eigen::Vector2d(init_points0[i].x, init_points0[i].y));
    const Eigen::Vector3d b = R.transpose() * cam.Unproject(Eigen::Vector2d(init_points[i].x, init_points[i].y));
    const Eigen::Vector3d c = -R.transpose() * t;  // second centre in the first camera
    // Solve s a - u b = c in least squares.
    Eigen::Matrix<double, 3, 2> A;
    A.col(0) = a;
    A.col(1) = -b;
    const Eigen::Vector2d su = A.colPivHouseholderQr().solve(c);
    if (!(su(0) > 0 && su(1) > 0)) continue;
    const Eigen::Vector3d p = 0.5 * (su(0) * a + c + su(1) * b);
    if (!(p.z() > 0)) continue;
    points.push_back(p);
    pixels.push_back(init_points0[i]);
  }
  if (points.size() < 30) {
    *why = "too few triangulated points";
    return false;
  }
  std::vector<double> depths;
  for (const auto& p : points) depths.push_back(p.z());
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  const double median_depth = depths[depths.size() / 2];
  const double scale = 1.0 / median_depth;

  // Sparse inverse depth at the features, densified to seed the first keyframe's depth filter.
  InverseDepthMap sparse;
  sparse.inverse_depth = cv::Mat::zeros(cam.height, cam.width, CV_32F);
  sparse.variance = cv::Mat::zeros(cam.height, cam.width, CV_32F);
  for (size_t i = 0; i < points.size(); ++i) {
    const int x = static_cast<int>(std::lround(pixels[i].x)), y = static_cast<int>(std::lround(pixels[i].y));
    if (x < 0 || y < 0 || x >= cam.width || y >= cam.height) continue;
    const float rho = static_cast<float>(1.0 / (points[i].z() * scale));
    sparse.inverse_depth.at<float>(y, x) = rho;
    sparse.variance.at<float>(y, x) = 0.01f * rho * rho;
  }
  DensifyOptions dens;
  dens.sigma_px = std::max(2.0, cam.width / 100.0);
  dens.levels = 6;
  const cv::Mat dense = DensifyInverseDepth(sparse, dens);

  const InitFrame& first = init_frames.front();
  DepthFilterOptions init_depth = options.depth;
  if (!options.init_depth_edge_test) init_depth.max_local_mean_log_gradient = 0;
  StatusOr<KeyframeDepth> kd = KeyframeDepth::Create(first.rgb, cam, init_depth, rig.crosstalk);
  if (!kd.ok()) {
    *why = kd.status().ToString();
    return false;
  }
  auto depth = std::make_unique<KeyframeDepth>(std::move(kd).value());
  depth->Seed(dense, 0.25, 1);

  // The buffered frames' normalised images J and depth updates below run on options.init_threads threads
  // when the SLAM's own pool has fewer: before the first keyframe nothing else runs beside the tracking
  // (the window adjustment and the start check come later), and both are the same to the bit on any
  // number of threads (KeyframeDepth::Update splits by rows).
  std::unique_ptr<ThreadPool> own_pool;
  ThreadPool* init_pool = pool;
  if (options.init_threads > (pool ? pool->num_threads() : 1)) {
    own_pool = std::make_unique<ThreadPool>(options.init_threads);
    init_pool = own_pool.get();
  }
  std::vector<cv::Mat> init_j(init_frames.size());  // frame 0's is not needed (the keyframe)
  const auto make_j = [&](std::ptrdiff_t i) {
    cv::Mat mean;
    if (i > 0) KeyframeDepth::NormalisedGrey(init_frames[static_cast<size_t>(i)].rgb, options.depth, &init_j[i], &mean);
  };
  if (init_pool) {
    init_pool->ParallelFor(0, static_cast<std::ptrdiff_t>(init_frames.size()), make_j);
  } else {
    for (size_t i = 0; i < init_frames.size(); ++i) make_j(static_cast<std::ptrdiff_t>(i));
  }

  // Track the buffered frames against the first one and refine its depth by stereo with each (two
  // passes: the second re-tracks on the refined depth).
  std::vector<Rigid3d> poses(init_frames.size());
  // Each buffered frame's alignment in the last pass (its record's SlamTrackingQuality; frame 0 is the
  // keyframe itself).
  std::vector<SlamTrackingQuality> quality(init_frames.size());
  const Rigid3d last_guess(Eigen::Quaterniond(R), t * scale);
  for (int pass = 0; pass < 1 + options.init_rounds; ++pass) {
    if (pass >= 2) {
      // A further round: the depth estimated again from the seed, by stereo with every buffered frame at
      // the poses of the previous pass, then the frames tracked again on it.
      StatusOr<KeyframeDepth> fresh = KeyframeDepth::Create(first.rgb, cam, init_depth, rig.crosstalk);
      if (!fresh.ok()) {
        *why = fresh.status().ToString();
        return false;
      }
      auto redo = std::make_unique<KeyframeDepth>(std::move(fresh).value());
      redo->Seed(dense, 0.25, 1);
      redo->Seed(depth->ToInverseDepthMap(1, 0.5).inverse_depth, 0.25, 1);
      for (size_t i = 1; i < init_frames.size(); ++i) redo->Update(init_j[i], poses[i], init_pool);
      redo->Regularise();
      depth = std::move(redo);
    }
    Tracker* init = init_tracker.get();
    if (!init->SetKeyframe(first.rgb, depth->ToInverseDepthMap(1, 0.5)).ok()) {
      *why = "too few points to track on the first keyframe";
      return false;
    }
    Rigid3d prev, prev2;
    for (size_t i = 1; i < init_frames.size(); ++i) {
      // Constant velocity (pass 1 starts from pass 0's first pose); the last frame of pass 0 starts from
      // the essential-matrix pose.
      Rigid3d guess = i == 1 ? (pass >= 1 ? poses[1] : Rigid3d()) : (prev * prev2.Inverse()) * prev;
      const bool from_essential = pass == 0 && i + 1 == init_frames.size();
      if (from_essential) guess = last_guess;
      StatusOr<TrackingResult> tr = init->Track(init_frames[i].rgb, guess);
      const double mean_idepth = depth->MeanInverseDepth();
      bool retried = false;
      if (tr.ok() && tr->ok && !from_essential && !PlausibleStep(tr->frame_from_keyframe, guess, mean_idepth)) {
        StatusOr<TrackingResult> retry = init->Track(init_frames[i].rgb, prev);
        if (!(retry.ok() && retry->ok && PlausibleStep(retry->frame_from_keyframe, guess, mean_idepth))) {
          *why = "tracking the initialisation frames failed: implausible jump at buffered frame " + std::to_string(i);
          return false;
        }
        tr = retry;
        retried = true;
      }
      if (!tr.ok() || !tr->ok) {
        *why = "tracking the initialisation frames failed" + (tr.ok() ? ": " + tr->lost_reason : std::string());
        return false;
      }
      poses[i] = tr->frame_from_keyframe;
      // The previous buffered frame's pose (frame 1's is the keyframe's own).
      quality[i] = QualityOf(*tr, retried, guess, prev, mean_idepth);
      prev2 = prev;
      prev = poses[i];
      if (pass == 0) {
        depth->Update(init_j[i], poses[i], init_pool);
        // Keep the tracker's copy of the refined depth fresh, as during tracking (on the rough first depth
        // the residuals grew from frame to frame until one frame jumped).
        if (i % static_cast<size_t>(options.tracker_refresh_frames) == 0 && i + 1 < init_frames.size()) {
          depth->Regularise();
          if (!init->SetKeyframe(first.rgb, depth->ToInverseDepthMap(1, 0.5)).ok()) {
            *why = "too few points to track on the first keyframe";
            return false;
          }
        }
      }
    }
    if (pass == 0) depth->Regularise();
  }
  // Fraction of candidates with converged depth.
  const double converged = static_cast<double>(depth->NumValid()) / std::max(1, depth->NumCandidates());
  if (converged < options.init_min_converged_fraction) {
    *why = "first keyframe's depth did not converge (" + std::to_string(static_cast<int>(100 * converged)) + "%)";
    return false;
  }

  Keyframe k;
  k.id = 0;
  k.frame_id = first.frame_id;
  k.timestamp = first.timestamp;
  k.rgb = first.rgb;
  keyframes.push_back(k);
  current_depth = std::move(depth);
  if (!RefreshTracker().ok()) {
    // Not initialised after all: no keyframe (the next attempt makes keyframe 0 again).
    keyframes.pop_back();
    current_depth.reset();
    *why = "too few points with depth for the tracker in the first keyframe";
    return false;
  }
  for (size_t i = 0; i < init_frames.size(); ++i) {
    FrameRecord& f = frames[static_cast<size_t>(init_frames[i].frame_id)];
    f.frame_from_keyframe = poses[i];
    f.result.keyframe_id = 0;
    f.result.state = SlamState::kTracking;
    f.result.message.clear();
    f.result.tracking = quality[i];
    f.result.world_from_camera = WorldFromFrame(f);
  }
  frames[static_cast<size_t>(first.frame_id)].result.new_keyframe = true;
  frames_since_keyframe = static_cast<int>(init_frames.size()) - 1;
  has_last = true;
  last_frame_from_kf = poses.back();
  has_prev = init_frames.size() >= 2;
  prev_frame_from_kf = poses[poses.size() - 2];
  init_parallax_px = parallax;
  PRISM_LOG(INFO) << "slam: initialised on frames " << first.frame_id << ".." << init_frames.back().frame_id
                  << ", parallax " << parallax << " px, " << points.size() << " points, converged " << 100 * converged
                  << "%";
  return true;
}

Status SlamSystem::Impl::RefreshTracker() { return SetTrackerKeyframe(keyframes.back().rgb, *current_depth); }

Status SlamSystem::Impl::SetTrackerKeyframe(const cv::Mat& rgb, const KeyframeDepth& depth) {
  return tracker->SetKeyframe(
      rgb, depth.ToInverseDepthMap(options.tracking_min_observations, options.tracking_max_relative_sigma));
}

StatusOr<KeyframeDepth> SlamSystem::Impl::PropagateForTracking(const cv::Mat& rgb, const KeyframeDepth& source,
                                                               const Rigid3d& this_from_source,
                                                               const KeyframeDepth* blank) {
  StatusOr<KeyframeDepth> created = blank ? StatusOr<KeyframeDepth>(blank->Blank())
                                          : KeyframeDepth::Create(rgb, rig.camera, options.depth, rig.crosstalk);
  PRISM_ASSIGN_OR_RETURN(KeyframeDepth kd, std::move(created));
  kd.PropagateFrom(source, this_from_source, options.new_pixel_relative_sigma);
  if (!SetTrackerKeyframe(rgb, kd).ok())
    return FailedPreconditionError("too few points with depth in the new keyframe");
  return kd;
}

Rigid3d SlamSystem::Impl::WorldFromFrame(const FrameRecord& f, bool corrected) const {
  const Keyframe& k = keyframes[static_cast<size_t>(f.result.keyframe_id)];
  Rigid3d keyframe_from_frame = f.frame_from_keyframe.Inverse();
  if (corrected && options.distribute_keyframe_corrections && k.next >= 0) {
    const Keyframe& n = keyframes[static_cast<size_t>(k.next)];
    const FrameRecord& made = frames[static_cast<size_t>(n.frame_id)];
    if (f.result.frame_id > k.frame_id && f.result.frame_id <= n.frame_id && made.result.keyframe_id == k.id &&
        made.result.state == SlamState::kTracking) {
      // The next keyframe's camera in this keyframe (this keyframe's unit): now, and as tracked.
      const Rigid3d keyframe_from_next = BFromAInUnitsOfA(k.world_from_keyframe, n.world_from_keyframe).Inverse();
      const Rigid3d correction = keyframe_from_next * made.frame_from_keyframe;
      const double fraction =
          static_cast<double>(f.result.frame_id - k.frame_id) / static_cast<double>(n.frame_id - k.frame_id);
      const Eigen::AngleAxisd angle_axis(correction.rotation);
      const Rigid3d part(ExpSo3(fraction * angle_axis.angle() * angle_axis.axis()), fraction * correction.translation);
      keyframe_from_frame = part * keyframe_from_frame;
    }
  }
  return k.world_from_keyframe.TransformPose(keyframe_from_frame);
}

Rigid3d SlamSystem::Impl::LastGoodWorldFromCamera() const {
  // As tracked (the frames' corrections are for their output: the estimation never depends on them).
  for (auto it = frames.rbegin(); it != frames.rend(); ++it)
    if (it->result.state == SlamState::kTracking)
      return it->result.keyframe_id >= 0 ? WorldFromFrame(*it, /*corrected=*/false) : it->result.world_from_camera;
  return Rigid3d();
}

StatusOr<SlamFrameResult> SlamSystem::Impl::TrackFrame(int64_t frame_id, double timestamp, const cv::Mat& rgb) {
  FrameRecord rec;
  rec.result.frame_id = frame_id;
  rec.result.timestamp = timestamp;
  Rigid3d guess = has_last ? last_frame_from_kf : Rigid3d();
  if (has_last && has_prev) guess = (last_frame_from_kf * prev_frame_from_kf.Inverse()) * last_frame_from_kf;
  ++timings.tracked_frames;
  const auto tracking_start = std::chrono::steady_clock::now();
  PRISM_ASSIGN_OR_RETURN(TrackingResult tr, tracker->Track(rgb, guess));
  const double mean_idepth_now = current_depth->MeanInverseDepth();
  const bool implausible = tr.ok && has_last && !PlausibleStep(tr.frame_from_keyframe, guess, mean_idepth_now);
  bool retried = false;
  if ((!tr.ok || implausible) && has_last) {
    PRISM_ASSIGN_OR_RETURN(TrackingResult retry, tracker->Track(rgb, last_frame_from_kf));
    if (retry.ok && PlausibleStep(retry.frame_from_keyframe, guess, mean_idepth_now)) {
      tr = retry;
      retried = true;
    } else if (implausible) {
      std::ostringstream m;
      m << "implausible jump from the predicted pose ("
        << RotationAngle(tr.frame_from_keyframe.rotation * guess.rotation.inverse()) * kRadToDeg << " deg, "
        << (tr.frame_from_keyframe.translation - guess.translation).norm() * mean_idepth_now << " of the mean depth)";
      tr.ok = false;
      tr.lost_reason = m.str();
    }
  }
  timings.tracking += SecondsSince(tracking_start);
  int kf_index = static_cast<int>(keyframes.size()) - 1;
  if (!tr.ok) {
    const ScopedSeconds timer(&timings.relocalisation);
    ++lost_count;
    Rigid3d reloc_pose;
    int reloc_kf = -1;
    std::string reloc_failure;
    if (lost_count >= options.relocalise_after_lost_frames && Relocalise(rgb, &reloc_pose, &reloc_kf)) {
      // Resume from the keyframe found: a new keyframe at this frame, seeded from its depth. The frame
      // is recorded first (MakeKeyframe marks it), and taken back if the new keyframe is unusable.
      PRISM_ASSIGN_OR_RETURN(KeyframeDepth source, KeyframeDepth::Create(keyframes[static_cast<size_t>(reloc_kf)].rgb,
                                                                         rig.camera, options.depth, rig.crosstalk));
      source.Seed(keyframes[static_cast<size_t>(reloc_kf)].final_depth.inverse_depth, 0.05, 2);
      rec.frame_from_keyframe = reloc_pose;
      rec.result.keyframe_id = reloc_kf;
      rec.result.state = SlamState::kTracking;
      rec.result.message = "relocalised against keyframe " + std::to_string(reloc_kf) + " after " + tr.lost_reason;
      rec.result.world_from_camera = WorldFromFrame(rec);
      frames.push_back(rec);
      const Status made = MakeKeyframe(frame_id, timestamp, rgb, reloc_kf, reloc_pose, source);
      if (made.ok()) {
        frames.back().result.new_keyframe = true;
        lost_count = 0;
        PRISM_LOG(INFO) << "slam: frame " << frame_id << " " << frames.back().result.message;
        return frames.back().result;
      }
      frames.pop_back();
      // The current keyframe stays; restore the tracker's copy of it (MakeKeyframe replaced it).
      PRISM_RETURN_IF_ERROR(RefreshTracker());
      reloc_failure =
          " (relocalised against keyframe " + std::to_string(reloc_kf) + " but " + std::string(made.message()) + ")";
      rec = FrameRecord();
      rec.result.frame_id = frame_id;
      rec.result.timestamp = timestamp;
    }
    rec.result.state = SlamState::kLost;
    rec.result.message = "tracking lost: " + tr.lost_reason + reloc_failure;
    // Keep the last good pose.
    rec.result.world_from_camera = LastGoodWorldFromCamera();
    rec.result.keyframe_id = -1;
    frames.push_back(rec);
    return rec.result;
  }
  lost_count = 0;
  rec.frame_from_keyframe = tr.frame_from_keyframe;
  rec.result.keyframe_id = keyframes[static_cast<size_t>(kf_index)].id;
  rec.result.state = SlamState::kTracking;
  // The previous frame's pose on this keyframe (the keyframe's own pose when it was made from it).
  rec.result.tracking = QualityOf(tr, retried, guess, has_last ? last_frame_from_kf : Rigid3d(), mean_idepth_now);
  rec.result.world_from_camera = WorldFromFrame(rec);
  frames.push_back(rec);
  prev_frame_from_kf = last_frame_from_kf;
  has_prev = has_last;
  last_frame_from_kf = tr.frame_from_keyframe;
  has_last = true;

  // Stereo update of the keyframe's depth (every depth_update_interval frames, and on a frame that
  // makes a keyframe).
  ++frames_since_keyframe;
  const double rotation_deg = RotationAngle(tr.frame_from_keyframe.rotation) * kRadToDeg;
  const auto needs_keyframe = [&](double mean_idepth) {
    const double distance = tr.frame_from_keyframe.translation.norm() * mean_idepth;
    return distance > options.keyframe_distance_fraction ||
           tr.visible_fraction < options.keyframe_min_visible_fraction ||
           rotation_deg > options.keyframe_max_rotation_deg;
  };
  // Over the mapping budget: the time spent so far on mapping, with this update's expected time (the
  // mean of the updates so far), against the budget of the frames tracked.
  const double expected_update = timings.depth_updates > 0 ? timings.depth_update / timings.depth_updates : 0.0;
  const bool over_budget =
      options.mapping_budget_ms > 0 && 1000.0 * (timings.depth_update + timings.keyframes + expected_update) >
                                           options.mapping_budget_ms * static_cast<double>(timings.tracked_frames);
  const bool interval_update = !skip_depth_update && frames_since_keyframe % options.depth_update_interval == 0;
  const bool makes_keyframe = needs_keyframe(current_depth->MeanInverseDepth());
  if (interval_update && over_budget && !makes_keyframe) ++timings.depth_updates_over_budget;
  if ((interval_update && !over_budget) || makes_keyframe) {
    const ScopedSeconds timer(&timings.depth_update);
    ++timings.depth_updates;
    frames.back().result.depth_updated = true;
    // The tracker's J of this frame when its normalisation is the depth filter's (the defaults: the
    // same image, not computed twice).
    const TrackerOptions& to = tracker->options();
    cv::Mat j, mean;
    if (to.shading_model != ShadingModel::kNone && to.local_mean_radius_px == options.depth.local_mean_radius_px &&
        to.local_mean_floor == options.depth.local_mean_floor && !tracker->last_frame_grey().empty()) {
      j = tracker->last_frame_grey();
    } else {
      KeyframeDepth::NormalisedGrey(rgb, options.depth, &j, &mean);
    }
    const DepthUpdateStats stats = current_depth->Update(j, tr.frame_from_keyframe, pool);
    timings.depth_pixels_searched += stats.searched;
    timings.depth_pixels_skipped += stats.skipped;
  }

  // New keyframe?
  const ScopedSeconds keyframe_timer(&timings.keyframes);
  PollPendingAdjustment();
  if (needs_keyframe(current_depth->MeanInverseDepth())) {
    current_depth->Regularise();
    const Status made = MakeKeyframe(frame_id, timestamp, rgb, kf_index, tr.frame_from_keyframe, *current_depth);
    if (made.ok()) {
      frames.back().result.new_keyframe = true;
      const ScopedSeconds adjustment_timer(&timings.keyframe_adjustment);
      if (options.keyframe_adjustment && (keyframes.size() - 1) % options.keyframe_adjustment_interval == 0) {
        if (pending_adjustment) {
          adjustment_owed = true;  // MakeKeyframe went on without the running one
        } else {
          AdjustWindow();
        }
      }
    } else {
      // Keep tracking against the current keyframe; restore the tracker's copy.
      frames.back().result.message = "no new keyframe: " + std::string(made.message());
      PRISM_RETURN_IF_ERROR(RefreshTracker());
    }
  } else if (frames_since_keyframe % options.tracker_refresh_frames == 0) {
    current_depth->Regularise();
    PRISM_RETURN_IF_ERROR(RefreshTracker());
  }
  return frames.back().result;
}

Status SlamSystem::Impl::MakeKeyframe(int64_t frame_id, double timestamp, const cv::Mat& rgb, int reference_kf,
                                      const Rigid3d& frame_from_reference, const KeyframeDepth& source) {
  // The start check's pair scales, on their thread (start_check_async), decide how this keyframe's window
  // adjustment runs (inline with 16 px cells while the check is open): as if they had been taken inline.
  if (pending_start_check) {
    WaitForStartCheck();
    if (StartCheckCloses(pending_start_check->scales)) start_check_running = false;
  }
  // The adjustment started at the previous keyframe moves the reference keyframe: first apply it (or,
  // with keyframe_adjustment_max_wait_ms, go on without it when it takes longer: ApplyAdjustment moves
  // this keyframe with the reference keyframe then).
  const bool adjusted = ApplyPendingAdjustment(options.keyframe_adjustment_max_wait_ms);
  // The tracker must accept it before it becomes the keyframe.
  PRISM_ASSIGN_OR_RETURN(KeyframeDepth kd, PropagateForTracking(rgb, source, frame_from_reference));
  // The last frame-to-frame motion (newest from previous tracked frame), for the next frame's guess.
  const bool had_velocity = has_last && has_prev;
  const Rigid3d velocity = had_velocity ? last_frame_from_kf * prev_frame_from_kf.Inverse() : Rigid3d();
  FinishCurrent();  // the keyframe being replaced (uses current_depth before it is replaced)
  Keyframe k;
  k.id = static_cast<int>(keyframes.size());
  k.frame_id = frame_id;
  k.timestamp = timestamp;
  k.rgb = rgb.clone();
  k.world_from_keyframe =
      keyframes[static_cast<size_t>(reference_kf)].world_from_keyframe * ToSim3(frame_from_reference.Inverse());
  PoseGraphEdge edge;
  edge.from = reference_kf;
  edge.to = k.id;
  edge.from_from_to = ToSim3(frame_from_reference.Inverse());
  edge.rotation_sigma = options.odometry_rotation_sigma;
  edge.translation_sigma = options.odometry_translation_sigma;
  edge.log_scale_sigma = options.odometry_log_scale_sigma;
  graph_edges.push_back(edge);
  graph_edge_is_loop.push_back(0);
  keyframes.push_back(std::move(k));
  if (keyframes[static_cast<size_t>(reference_kf)].next < 0)
    keyframes[static_cast<size_t>(reference_kf)].next = keyframes.back().id;
  previous_depth.reset();
  previous_depth_kf = -1;
  if (options.keyframe_adjustment && options.repropagate_after_adjustment && !AdjustAsync() && current_depth &&
      &source == current_depth.get()) {
    previous_depth = std::move(current_depth);
    previous_depth_kf = reference_kf;
  }
  current_depth = std::make_unique<KeyframeDepth>(std::move(kd));
  frames_since_keyframe = 0;
  if (!adjusted) ++timings.keyframes_made_before_adjustment;
  if (options.loop_closure && keyframes.size() >= 2) {
    const ScopedSeconds loop_timer(&timings.loop_search);
    CloseLoops(static_cast<int>(keyframes.size()) - 2);
  }
  // The new keyframe is at this frame's pose; with the velocity kept, the previous frame sits one step
  // behind it, so the next frame's constant-velocity guess is one step ahead.
  has_last = true;
  last_frame_from_kf = Rigid3d();
  has_prev = options.keep_velocity_across_keyframes && had_velocity;
  prev_frame_from_kf = has_prev ? velocity.Inverse() : Rigid3d();
  return Status::Ok();
}

void SlamSystem::Impl::FinishCurrent() {
  if (!current_depth || keyframes.empty() || keyframes.back().finished) return;
  keyframes.back().final_depth = current_depth->ToInverseDepthMap();
  keyframes.back().finished = true;
}

bool SlamSystem::Impl::AlignKeyframes(int j, int k, Sim3d* j_from_k, std::string* why) {
  const Keyframe& kj = keyframes[static_cast<size_t>(j)];
  const Keyframe& kk = keyframes[static_cast<size_t>(k)];
  // Current estimate as a rigid guess in each keyframe's units.
  const Sim3d k_from_j_estimate = kk.world_from_keyframe.Inverse() * kj.world_from_keyframe;
  const Rigid3d guess_k_from_j(k_from_j_estimate.rotation, k_from_j_estimate.translation / k_from_j_estimate.scale);
  // A: image k against depth j -> k_from_j in j's units.
  if (!loop_tracker->SetKeyframe(kj.rgb, kj.final_depth).ok()) return (*why = "keyframe j has too little depth", false);
  StatusOr<TrackingResult> a = loop_tracker->Track(kk.rgb, guess_k_from_j);
  if (!a.ok() || !a->ok) return (*why = "k does not track on j", false);
  // B: image j against depth k -> j_from_k in k's units.
  if (!loop_tracker->SetKeyframe(kk.rgb, kk.final_depth).ok()) return (*why = "keyframe k has too little depth", false);
  const Rigid3d guess_j_from_k = a->frame_from_keyframe.Inverse();
  StatusOr<TrackingResult> b = loop_tracker->Track(kj.rgb, guess_j_from_k);
  if (!b.ok() || !b->ok) return (*why = "j does not track on k", false);
  const double inconsistency_deg =
      RotationAngle(a->frame_from_keyframe.rotation * b->frame_from_keyframe.rotation) * kRadToDeg;
  if (inconsistency_deg > options.loop_max_rotation_inconsistency_deg)
    return (*why = "alignments disagree by " + std::to_string(inconsistency_deg) + " deg", false);
  // Ratio of the depth units (k units per j unit): j's points moved into k's camera (in j's units)
  // against k's own depth at the pixels they land on.
  const PinholeCamera& cam = rig.camera;
  std::vector<double> ratios;
  for (int y = 0; y < cam.height; y += 2) {
    const float* d = kj.final_depth.inverse_depth.ptr<float>(y);
    for (int x = 0; x < cam.width; x += 2) {
      if (!(d[x] > 0)) continue;
      const Eigen::Vector3d p = a->frame_from_keyframe * (cam.Unproject(Eigen::Vector2d(x, y)) / d[x]);
      if (!(p.z() > 0)) continue;
      const Eigen::Vector2d uv = cam.Project(p);
      const int u = static_cast<int>(std::lround(uv.x())), v = static_cast<int>(std::lround(uv.y()));
      if (u < 0 || v < 0 || u >= cam.width || v >= cam.height) continue;
      const float idk = kk.final_depth.inverse_depth.at<float>(v, u);
      if (idk > 0) ratios.push_back((1.0 / idk) / p.z());
    }
  }
  // Every second pixel in x and y was tried: a quarter of the matches a full scan would find.
  if (static_cast<int>(ratios.size()) < options.loop_min_depth_matches / 4)
    return (*why = "depths overlap on " + std::to_string(ratios.size()) + " points", false);
  std::nth_element(ratios.begin(), ratios.begin() + static_cast<std::ptrdiff_t>(ratios.size() / 2), ratios.end());
  const double s_kj = ratios[ratios.size() / 2];
  if (!(s_kj > 0.5 && s_kj < 2.0)) return (*why = "implausible unit ratio " + std::to_string(s_kj), false);
  const Sim3d k_from_j(s_kj, a->frame_from_keyframe.rotation, s_kj * a->frame_from_keyframe.translation);
  *j_from_k = k_from_j.Inverse();
  return true;
}

void SlamSystem::Impl::CloseLoops(int index) {
  const Keyframe& kk = keyframes[static_cast<size_t>(index)];
  if (!kk.finished) return;
  // Mean depth of the keyframe in world units.
  double sum = 0;
  int count = 0;
  for (int y = 0; y < kk.final_depth.inverse_depth.rows; y += 4) {
    const float* d = kk.final_depth.inverse_depth.ptr<float>(y);
    for (int x = 0; x < kk.final_depth.inverse_depth.cols; x += 4)
      if (d[x] > 0) {
        sum += 1.0 / d[x];
        ++count;
      }
  }
  if (count == 0) return;
  const double mean_depth = kk.world_from_keyframe.scale * sum / count;
  const Eigen::Vector3d axis_k = kk.world_from_keyframe.rotation * Eigen::Vector3d::UnitZ();
  std::vector<std::pair<double, int>> candidates;
  for (int j = 0; j + options.loop_min_keyframe_gap <= index; ++j) {
    const Keyframe& kj = keyframes[static_cast<size_t>(j)];
    if (!kj.finished) continue;
    const double distance = (kj.world_from_keyframe.translation - kk.world_from_keyframe.translation).norm();
    const double angle =
        std::acos(std::clamp(axis_k.dot(kj.world_from_keyframe.rotation * Eigen::Vector3d::UnitZ()), -1.0, 1.0)) *
        kRadToDeg;
    if (distance < options.loop_max_distance_fraction * mean_depth && angle < options.loop_max_angle_deg)
      candidates.push_back({distance / mean_depth + angle / options.loop_max_angle_deg, j});
  }
  std::sort(candidates.begin(), candidates.end());
  if (static_cast<int>(candidates.size()) > options.loop_max_candidates) candidates.resize(options.loop_max_candidates);
  // A candidate waits for the adjustment still running (keyframe_adjustment_max_wait_ms): the alignment
  // and the pose graph start from the adjusted poses.
  if (!candidates.empty()) ApplyPendingAdjustment();
  bool added = false;
  for (const auto& [score, j] : candidates) {
    Sim3d j_from_k;
    std::string why;
    if (!AlignKeyframes(j, index, &j_from_k, &why)) {
      PRISM_LOG(INFO) << "slam: no loop edge " << j << " - " << index << ": " << why;
      continue;
    }
    PoseGraphEdge edge;
    edge.from = j;
    edge.to = index;
    edge.from_from_to = j_from_k;
    edge.rotation_sigma = options.loop_rotation_sigma;
    edge.translation_sigma = options.loop_translation_sigma;
    edge.log_scale_sigma = options.loop_log_scale_sigma;
    graph_edges.push_back(edge);
    graph_edge_is_loop.push_back(1);
    ++loop_closures;
    added = true;
    PRISM_LOG(INFO) << "slam: loop edge keyframe " << j << " - " << index << ", unit ratio " << 1.0 / j_from_k.scale;
  }
  if (!added) return;
  std::vector<Sim3d> nodes;
  for (const Keyframe& k : keyframes) nodes.push_back(k.world_from_keyframe);
  StatusOr<PoseGraphSummary> summary = OptimisePoseGraph(graph_edges, PoseGraphOptions(), &nodes);
  if (!summary.ok()) {
    PRISM_LOG(WARNING) << "slam: pose graph: " << summary.status();
    return;
  }
  for (size_t i = 0; i < keyframes.size(); ++i) keyframes[i].world_from_keyframe = nodes[i];
  // Poses of tracked frames follow their keyframes.
  for (FrameRecord& f : frames)
    if (f.result.state == SlamState::kTracking && f.result.keyframe_id >= 0)
      f.result.world_from_camera = WorldFromFrame(f);
  PRISM_LOG(INFO) << "slam: pose graph " << keyframes.size() << " keyframes, " << graph_edges.size() << " edges, cost "
                  << summary->initial_cost << " -> " << summary->final_cost << " in " << summary->iterations
                  << " iterations";
}

double SlamSystem::Impl::DepthOverlap(int k, int j) const {
  const Keyframe& a = keyframes[static_cast<size_t>(k)];
  if (!a.finished) return 1.0;
  return DepthOverlapFraction(rig.camera, a.final_depth.inverse_depth, a.world_from_keyframe,
                              keyframes[static_cast<size_t>(j)].world_from_keyframe, 8);
}

int SlamSystem::Impl::WindowStart(int first) const {
  const int n = static_cast<int>(keyframes.size());
  if (options.keyframe_window_min_overlap <= 0) return first;
  while (n - first > 3 && DepthOverlap(first, n - 1) < options.keyframe_window_min_overlap) ++first;
  return first;
}

std::vector<ShadingPair> SlamSystem::Impl::ShadingPairs(size_t num_keyframes, bool own_depth) const {
  std::vector<ShadingPair> pairs;
  for (size_t k = 0; k + 1 < std::min(num_keyframes, keyframes.size()); ++k) {
    const Keyframe& a = keyframes[k];
    const Keyframe& b = keyframes[k + 1];
    if (!a.finished || a.final_depth.inverse_depth.empty()) continue;
    ShadingPair p;
    p.older = static_cast<int>(k);
    p.older_rgb = a.rgb;
    p.older_inverse_depth = own_depth ? a.final_depth.inverse_depth.clone() : a.final_depth.inverse_depth;
    p.newer_rgb = b.rgb;
    p.world_from_older = a.world_from_keyframe;
    p.world_from_newer = b.world_from_keyframe;
    pairs.push_back(std::move(p));
  }
  return pairs;
}

std::vector<std::pair<int, double>> SlamSystem::Impl::IndexedPairShadingScales(size_t num_keyframes) const {
  if (!AllPointLights(rig)) return {};
  return PairScales(rig, ShadingPairs(num_keyframes, /*own_depth=*/false), pool);
}

void SlamSystem::Impl::StartPairShadingScales(size_t num_keyframes) {
  auto job = std::make_unique<PendingStartCheck>();
  PendingStartCheck* p = job.get();
  // The thread reads its own copies and the rig (a copy too): nothing the frames change.
  job->done = std::async(std::launch::async, [p, rig = rig, pairs = ShadingPairs(num_keyframes, true)] {
    SetCurrentThreadName("slam-start-chk");
    const auto start = std::chrono::steady_clock::now();
    if (AllPointLights(rig))
      for (const auto& [k, scale] : PairScales(rig, pairs)) p->scales.push_back(scale);
    p->thread_seconds = SecondsSince(start);
  });
  pending_start_check = std::move(job);
}

void SlamSystem::Impl::WaitForStartCheck() {
  if (!pending_start_check) return;
  const auto start = std::chrono::steady_clock::now();
  pending_start_check->done.wait();
  pending_start_check->wait_seconds += SecondsSince(start);
}

bool SlamSystem::Impl::StartCheckCloses(const std::vector<double>& scales) const {
  return scales.size() < 3 || PairSpread(scales) <= options.start_check_max_pair_spread ||
         init_parallax_px >= options.start_check_retry_parallax_fraction * rig.camera.width;
}

std::vector<double> SlamSystem::Impl::PairShadingScales(size_t num_keyframes) const {
  std::vector<double> estimates;
  for (const auto& [k, scale] : IndexedPairShadingScales(num_keyframes)) estimates.push_back(scale);
  return estimates;
}

double SlamSystem::Impl::RelitMetresPerWorldUnit() {
  if (relit_metres_per_world_unit != 0) return relit_metres_per_world_unit;
  relit_metres_per_world_unit = -1;
  if (!AllPointLights(rig)) return -1;
  std::vector<double> estimates = PairShadingScales(keyframes.size());
  if (estimates.size() < 3) {
    PRISM_LOG(INFO) << "slam: relit adjustment off: " << estimates.size() << " keyframe pairs gave a shading scale";
    return -1;
  }
  // After CorrectScaleDrift the pairs agree by construction: the check keeps the scales from before it.
  if (relit_pair_estimates.empty()) relit_pair_estimates = estimates;
  std::nth_element(estimates.begin(), estimates.begin() + estimates.size() / 2, estimates.end());
  relit_metres_per_world_unit = estimates[estimates.size() / 2];
  PRISM_LOG(INFO) << "slam: relit adjustment at " << relit_metres_per_world_unit << " metres per world unit ("
                  << estimates.size() << " keyframe pairs)";
  return relit_metres_per_world_unit;
}

bool SlamSystem::Impl::BuildAdjustmentProblem(int first, bool relit, bool mixed, double metres_per_world_unit,
                                              double min_band_fraction, DirectBaProblem* problem) {
  const int n = static_cast<int>(keyframes.size());
  problem->camera = rig.camera;
  std::vector<InverseDepthMap> maps;
  for (int k = first; k < n; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    problem->world_from_keyframe.push_back(kf.world_from_keyframe);
    if (kf.grey_j.empty()) {
      cv::Mat mean;
      KeyframeDepth::NormalisedGrey(kf.rgb, options.depth, &kf.grey_j, &mean);
    }
    problem->grey_j.push_back(kf.grey_j);
    // The newest keyframe's depth is the one propagated into it.
    maps.push_back(kf.finished ? kf.final_depth : current_depth->ToInverseDepthMap());
  }
  // Points: per cell, the strongest gradient with a converged inverse depth.
  const int cell_px = WindowCellPx();
  for (int k = 0; k < n - first; ++k) {
    const cv::Mat& d = maps[static_cast<size_t>(k)].inverse_depth;
    const cv::Mat& var = maps[static_cast<size_t>(k)].variance;
    if (d.empty()) continue;
    Keyframe& kf = keyframes[static_cast<size_t>(first + k)];
    if (kf.finished && kf.window_points_cell_px == cell_px) {
      for (DirectBaPoint p : kf.window_points) {
        p.host = k;
        problem->points.push_back(p);
      }
      continue;
    }
    const size_t begin = problem->points.size();
    const double max_sigma = options.tracking_max_relative_sigma;
    SelectCellPoints(
        problem->grey_j[static_cast<size_t>(k)], d, k, cell_px, 0.0f,
        [&](int x, int y) { return var.empty() || std::sqrt(var.at<float>(y, x)) <= max_sigma * d.at<float>(y, x); },
        &problem->points);
    if (kf.finished) {
      kf.window_points.assign(problem->points.begin() + static_cast<std::ptrdiff_t>(begin), problem->points.end());
      for (DirectBaPoint& p : kf.window_points) p.host = 0;
      kf.window_points_cell_px = cell_px;
    }
  }
  if (static_cast<int>(problem->points.size()) < options.keyframe_window_min_points) return false;
  if (relit && mixed) {
    // J stays; every point is also a relit point (the adjustment computes the raw grey levels).
    const size_t num_j = problem->points.size();
    for (size_t i = 0; i < num_j; ++i) {
      DirectBaPoint p = problem->points[i];
      p.relit = true;
      problem->points.push_back(p);
    }
    for (int k = first; k < n; ++k) problem->relit.rgb.push_back(keyframes[static_cast<size_t>(k)].rgb);
    problem->relit.mixed = true;
    problem->relit.relit_residual_scale = options.final_adjustment_mixed_relit_scale;
  } else if (relit) {
    // The raw grey level of every keyframe and the hosts' colours (the points stay those J selected).
    for (int k = first; k < n; ++k) {
      const cv::Mat& rgb = keyframes[static_cast<size_t>(k)].rgb;
      problem->grey_j[static_cast<size_t>(k - first)] = MeanOfChannels(rgb);
      problem->relit.rgb.push_back(rgb);
    }
  }
  if (relit) {
    problem->relit.rig = &rig;
    problem->relit.metres_per_world_unit = metres_per_world_unit;
    problem->relit.estimate_metres_per_world_unit = true;
    problem->relit.min_band_fraction = min_band_fraction;
  }
  return true;
}

void SlamSystem::Impl::AdjustKeyframes(int first, const DirectBaOptions& ba_options, bool at_finish) {
  ApplyPendingAdjustment();
  const int n = static_cast<int>(keyframes.size());
  if (n - first < 3 || !current_depth) return;
  // Keyframes that left the window are not adjusted again until the final adjustment (which recomputes
  // them): drop their normalised images (1 MB each at 512x512, which would otherwise grow with the
  // session).
  for (int k = 0; k < first; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    kf.grey_j.release();
    kf.DropWindowPoints();
  }
  const bool mixed = at_finish && options.final_adjustment_mixed && RelitMetresPerWorldUnit() > 0;
  const bool relit = mixed || (at_finish && options.final_adjustment_relit && RelitMetresPerWorldUnit() > 0);
  auto job = std::make_unique<PendingAdjustment>();
  job->first = first;
  job->num_keyframes = n;
  job->at_finish = at_finish;
  job->relit = relit;
  job->mixed = mixed;
  DirectBaProblem& problem = job->problem;
  if (!BuildAdjustmentProblem(first, relit, mixed, relit_metres_per_world_unit,
                              mixed ? options.metric_scale_min_band_fraction : DirectBaRelit().min_band_fraction,
                              &problem))
    return;
  const DirectBaOptions used_options = relit && !mixed ? options.final_adjustment_relit_ba : ba_options;
  job->initial_inverse_depth.reserve(problem.points.size());
  for (const DirectBaPoint& p : problem.points) job->initial_inverse_depth.push_back(p.inverse_depth);
  if (AdjustAsync() && !at_finish) {
    // The problem holds its own copies (the images are shared, read-only): the thread touches nothing
    // else. One thread, no pool: the result is the same to the bit as with the pool (keyframe_ba.h).
    PendingAdjustment* p = job.get();
    job->done = std::async(std::launch::async, [p, used_options] {
      SetCurrentThreadName("slam-adjust");
      const auto start = std::chrono::steady_clock::now();
      p->summary = AdjustKeyframeWindowDirect(used_options, &p->problem, nullptr);
      p->seconds = SecondsSince(start);
    });
    pending_adjustment = std::move(job);
    return;
  }
  job->summary = AdjustKeyframeWindowDirect(used_options, &problem, pool);
  ApplyAdjustment(job.get());
}

bool SlamSystem::Impl::ApplyPendingAdjustment(double max_wait_ms) {
  if (!pending_adjustment) return true;
  if (max_wait_ms >= 0) {
    const ScopedSeconds wait(&timings.keyframe_adjustment_wait);
    const auto bound = std::chrono::duration<double, std::milli>(max_wait_ms);
    if (pending_adjustment->done.wait_for(bound) != std::future_status::ready) return false;
  }
  std::unique_ptr<PendingAdjustment> job = std::move(pending_adjustment);
  {
    const ScopedSeconds wait(&timings.keyframe_adjustment_wait);
    job->done.get();  // rethrows what the thread threw
  }
  timings.keyframe_adjustment_thread += job->seconds;
  ApplyAdjustment(job.get());
  return true;
}

void SlamSystem::Impl::PollPendingAdjustment() {
  if (pending_adjustment && pending_adjustment->done.wait_for(std::chrono::seconds(0)) == std::future_status::ready)
    ApplyPendingAdjustment();
  if (adjustment_owed && !pending_adjustment) {
    const ScopedSeconds adjustment_timer(&timings.keyframe_adjustment);
    StartOwedAdjustment();
  }
}

void SlamSystem::Impl::ApplyAdjustment(PendingAdjustment* job) {
  const int first = job->first;
  const int n = job->num_keyframes;
  const bool at_finish = job->at_finish, relit = job->relit, mixed = job->mixed;
  const DirectBaProblem& problem = job->problem;
  const std::vector<float>& initial_inverse_depth = job->initial_inverse_depth;
  // Keyframes made while the adjustment ran (keyframe_adjustment_max_wait_ms) follow its newest keyframe.
  if (static_cast<int>(keyframes.size()) < n) {
    PRISM_LOG(WARNING) << "slam: keyframe adjustment over " << n << " keyframes dropped: there are now "
                       << keyframes.size();
    return;
  }
  const Sim3d newest_before = keyframes[static_cast<size_t>(n - 1)].world_from_keyframe;
  if (at_finish)
    for (Keyframe& kf : keyframes) kf.grey_j.release();
  const StatusOr<DirectBaSummary>& summary = job->summary;
  if (relit && summary.ok()) {
    PRISM_LOG(INFO) << "slam: relit adjustment: " << relit_metres_per_world_unit << " -> "
                    << problem.relit.metres_per_world_unit << " metres per world unit";
    relit_metres_per_world_unit = problem.relit.metres_per_world_unit;
  }
  if (!summary.ok()) {
    PRISM_LOG(WARNING) << "slam: keyframe adjustment: " << summary.status();
    return;
  }
  // Each adjusted keyframe keeps its depth map; its depth unit follows the adjusted inverse depths of the
  // points it hosts (median ratio).
  // The oldest keeps its pose (the gauge) and with refit_oldest_keyframe_scale has its unit re-fitted too.
  const int first_refitted = options.refit_oldest_keyframe_scale ? first : first + 1;
  for (int k = first_refitted; k < n; ++k) {
    Sim3d pose = problem.world_from_keyframe[static_cast<size_t>(k - first)];
    std::vector<double> ratios;
    for (size_t i = 0; i < problem.points.size(); ++i) {
      const DirectBaPoint& p = problem.points[i];
      // (Mixed: the J points alone; the keyframe's depth map is J's.)
      if (p.host == k - first && p.ok && !(mixed && p.relit))
        ratios.push_back(initial_inverse_depth[i] / p.inverse_depth);
    }
    if (ratios.size() >= 20) {
      std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
      pose.scale *= ratios[ratios.size() / 2];
    }
    keyframes[static_cast<size_t>(k)].world_from_keyframe = pose;
  }
  // Made at the newest one's pose before the adjustment: moved as it moved.
  const Sim3d newest_move = keyframes[static_cast<size_t>(n - 1)].world_from_keyframe * newest_before.Inverse();
  for (size_t k = static_cast<size_t>(n); k < keyframes.size(); ++k)
    keyframes[k].world_from_keyframe = newest_move * keyframes[k].world_from_keyframe;
  if (options.repropagate_after_adjustment && !at_finish) {
    FollowKeyframes(first_refitted, static_cast<int>(keyframes.size()));  // the edges, before the re-propagation
    RepropagateNewestKeyframe();
  }
  // The frames of the oldest keyframe move too when its next keyframe moved (distribute_keyframe_corrections).
  FollowKeyframes(first_refitted, options.distribute_keyframe_corrections ? first : first_refitted);
  ++keyframe_adjustments;
  PRISM_LOG(DEBUG) << "slam: " << (at_finish ? "final" : "keyframe") << " adjustment " << first << ".." << n - 1 << ": "
                   << problem.points.size() << " points, " << summary->residuals << " residuals, RMS "
                   << summary->initial_rms << " -> " << summary->final_rms << " in " << summary->iterations
                   << " iterations";
}

void SlamSystem::Impl::FollowKeyframes(int first_edge, int first_moved) {
  // The odometry edges follow (a later loop closure starts from the adjusted chain), as do the frames.
  for (PoseGraphEdge& e : graph_edges) {
    if (e.to - e.from != 1 || e.to < first_edge) continue;
    e.from_from_to = keyframes[static_cast<size_t>(e.from)].world_from_keyframe.Inverse() *
                     keyframes[static_cast<size_t>(e.to)].world_from_keyframe;
  }
  for (FrameRecord& f : frames)
    if (f.result.state == SlamState::kTracking && f.result.keyframe_id >= first_moved)
      f.result.world_from_camera = WorldFromFrame(f);
}

void SlamSystem::Impl::AdjustByFeatures() {
  ApplyPendingAdjustment();
  const int n = static_cast<int>(keyframes.size());
  if (!options.final_feature_adjustment || !(CanAdjustAllKeyframes() || CanAdjustByFeaturesAlone()) || n < 3) return;
  if (feature_tracks_failed_for == n) return;  // the same keyframes' images gave no tracks: not again
  const auto start = std::chrono::steady_clock::now();
  feature_report.ran = true;
  ++feature_report.runs;
  // The tracks depend on the images alone: built once for these keyframes (RefineKeyframeDepths' rounds
  // adjust the same keyframes again).
  if (!feature_tracks || feature_tracks->num_keyframes != n) {
    std::vector<FeatureImage> images(static_cast<size_t>(n));
    std::vector<Sim3d> poses;
    for (const Keyframe& kf : keyframes) poses.push_back(kf.world_from_keyframe);
    auto prepare = [&](std::ptrdiff_t k) {
      FeatureImage& in = images[static_cast<size_t>(k)];
      KeyframeDepth::NormalisedGrey(keyframes[static_cast<size_t>(k)].rgb, options.depth, &in.grey_j, &in.local_mean);
    };
    if (pool) pool->ParallelFor(0, n, prepare);
    else
      for (int k = 0; k < n; ++k) prepare(k);
    const double min_overlap = options.feature_adjustment_min_overlap;
    StatusOr<FeatureTracks> tracks = BuildFeatureTracks(
        rig.camera, options.feature_adjustment, images, poses, pool,
        [&](int a, int b) { return DepthOverlap(a, b) >= min_overlap || DepthOverlap(b, a) >= min_overlap; });
    feature_report.tracks_seconds = SecondsSince(start);
    if (!tracks.ok()) {
      feature_report.seconds += SecondsSince(start);
      feature_report.applied = false;
      feature_report.error = std::string(tracks.status().message());
      feature_tracks_failed_for = n;
      PRISM_LOG(WARNING) << "slam: feature adjustment not applied: " << tracks.status();
      return;
    }
    feature_tracks = std::make_unique<FeatureTracks>(std::move(tracks).value());
    feature_report.pairs_tried = feature_tracks->pairs_tried;
  }
  std::vector<Sim3d> adjusted;
  for (const Keyframe& kf : keyframes) adjusted.push_back(kf.world_from_keyframe);
  StatusOr<FeatureAdjustmentSummary> summary =
      AdjustKeyframesByFeatures(rig.camera, options.feature_adjustment, *feature_tracks, &adjusted);
  feature_report.seconds += SecondsSince(start);
  if (!summary.ok()) {
    feature_report.applied = false;
    feature_report.error = std::string(summary.status().message());
    PRISM_LOG(WARNING) << "slam: feature adjustment not applied: " << summary.status();
    return;
  }
  // Each keyframe's depth unit follows the tracks' depths where its depth map has them: a point at depth
  // z_map (the keyframe's units) is at depth scale * z_map in world units.
  int rescaled = 0;
  for (int k = 0; k < n; ++k) {
    Keyframe& kf = keyframes[static_cast<size_t>(k)];
    Sim3d pose = adjusted[static_cast<size_t>(k)];
    const cv::Mat& d = kf.final_depth.inverse_depth;
    std::vector<double> ratios;
    if (!d.empty()) {
      for (const FeatureObservation& o : summary->observations_by_keyframe[static_cast<size_t>(k)]) {
        const int x = static_cast<int>(std::lround(o.u)), y = static_cast<int>(std::lround(o.v));
        if (x < 0 || y < 0 || x >= d.cols || y >= d.rows) continue;
        const float rho = d.at<float>(y, x);
        if (rho > 0 && o.depth > 0) ratios.push_back(o.depth * rho);
      }
    }
    if (ratios.size() >= 20) {
      std::nth_element(ratios.begin(), ratios.begin() + static_cast<std::ptrdiff_t>(ratios.size() / 2), ratios.end());
      pose.scale = ratios[ratios.size() / 2];
      ++rescaled;
    }
    kf.world_from_keyframe = pose;
  }
  FollowKeyframes(0, 0);
  feature_report.applied = true;
  feature_report.error.clear();
  feature_report.keyframes_rescaled = rescaled;
  feature_report.summary = std::move(summary).value();
  feature_report.summary.observations_by_keyframe.clear();
  const FeatureAdjustmentSummary& r = feature_report.summary;
  PRISM_LOG(INFO) << "slam: feature adjustment: " << r.features << " features, " << r.pairs_matched << " of "
                  << feature_report.pairs_tried << " pairs matched, " << r.tracks << " tracks (" << r.mean_track_length
                  << " keyframes each), reprojection RMS " << r.initial_rms_px << " -> " << r.final_rms_px
                  << " px (median " << r.initial_median_px << " -> " << r.final_median_px << "), " << r.iterations
                  << " iterations, " << rescaled << " depth units refitted";
}

cv::Mat SlamSystem::Impl::SeedFromSecondKeyframe(const KeyframeDepth& first, const cv::Mat& first_inverse_depth,
                                                 const cv::Mat& second_inverse_depth) {
  const Keyframe& k0 = keyframes[0];
  const Keyframe& k1 = keyframes[1];
  StatusOr<KeyframeDepth> source = KeyframeDepth::Create(k1.rgb, rig.camera, options.depth, rig.crosstalk);
  if (!source.ok()) return first_inverse_depth;
  KeyframeDepth target = first.Blank();  // keyframe 0's image parts, no estimates
  source->Seed(second_inverse_depth, options.final_refinement_relative_sigma, 2);
  // Keyframe 1's points in keyframe 0's camera, in keyframe 1's units; then in keyframe 0's.
  target.PropagateFrom(*source, BFromAInUnitsOfA(k1.world_from_keyframe, k0.world_from_keyframe), 0.0);
  const cv::Mat propagated = target.ToInverseDepthMap(1, 1.0).inverse_depth;
  const float to_first_units = static_cast<float>(k0.world_from_keyframe.scale / k1.world_from_keyframe.scale);
  std::vector<double> ratios;
  for (int y = 0; y < propagated.rows; ++y)
    for (int x = 0; x < propagated.cols; ++x) {
      const float p = propagated.at<float>(y, x), o = first_inverse_depth.at<float>(y, x);
      if (p > 0 && o > 0) ratios.push_back(p * to_first_units / o);
    }
  if (ratios.size() < 100) return first_inverse_depth;
  std::nth_element(ratios.begin(), ratios.begin() + ratios.size() / 2, ratios.end());
  const float own_scale = static_cast<float>(ratios[ratios.size() / 2]);
  cv::Mat seed(first_inverse_depth.size(), CV_32F, cv::Scalar(0));
  for (int y = 0; y < seed.rows; ++y)
    for (int x = 0; x < seed.cols; ++x) {
      const float p = propagated.at<float>(y, x), o = first_inverse_depth.at<float>(y, x);
      seed.at<float>(y, x) = p > 0 ? p * to_first_units : o > 0 ? o * own_scale : 0.0f;
    }
  return seed;
}

void SlamSystem::Impl::RepropagateNewestKeyframe() {
  const int n = static_cast<int>(keyframes.size());
  std::unique_ptr<KeyframeDepth> source = std::move(previous_depth);
  if (!source || previous_depth_kf != n - 2 || n < 2) return;
  Keyframe& reference = keyframes[static_cast<size_t>(n - 2)];
  Keyframe& newest = keyframes[static_cast<size_t>(n - 1)];
  // The adjusted relative pose, in the reference keyframe's depth units.
  const Sim3d& a = reference.world_from_keyframe;
  const Sim3d& b = newest.world_from_keyframe;
  const Eigen::Quaterniond a_inv = a.rotation.conjugate();
  const Rigid3d reference_from_newest(a_inv * b.rotation, a_inv * (b.translation - a.translation) / a.scale);
  // current_depth is the newest keyframe's (propagated into it along the tracked pose): its image parts
  // are reused.
  const KeyframeDepth* blank = current_depth && current_depth->HasImage(newest.rgb) ? current_depth.get() : nullptr;
  StatusOr<KeyframeDepth> kd = PropagateForTracking(newest.rgb, *source, reference_from_newest.Inverse(), blank);
  if (!kd.ok()) {
    // Keep the depth propagated along the tracked pose; restore the tracker's copy of it.
    if (!RefreshTracker().ok()) {
      PRISM_LOG(WARNING) << "slam: tracker refresh failed after re-propagation";
    }
    return;
  }
  current_depth = std::make_unique<KeyframeDepth>(std::move(kd).value());
  newest.world_from_keyframe.scale = a.scale;
  for (PoseGraphEdge& e : graph_edges) {
    if (e.from == n - 2 && e.to == n - 1) e.from_from_to = a.Inverse() * newest.world_from_keyframe;
  }
}

bool SlamSystem::Impl::Relocalise(const cv::Mat& rgb, Rigid3d* frame_from_kf, int* keyframe_index) {
  ApplyPendingAdjustment();  // the keyframes' current poses
  // The last good pose, and the keyframes nearest to it (finished ones have their final depth).
  const Rigid3d last_world_from_camera = LastGoodWorldFromCamera();
  std::vector<std::pair<double, int>> candidates;
  for (const Keyframe& k : keyframes) {
    if (!k.finished) continue;
    const double d = (k.world_from_keyframe.translation - last_world_from_camera.translation).norm();
    candidates.push_back({d, k.id});
  }
  std::sort(candidates.begin(), candidates.end());
  if (static_cast<int>(candidates.size()) > options.relocalise_max_keyframes)
    candidates.resize(options.relocalise_max_keyframes);
  for (const auto& [d, id] : candidates) {
    const Keyframe& k = keyframes[static_cast<size_t>(id)];
    if (!reloc_tracker->SetKeyframe(k.rgb, k.final_depth).ok()) continue;
    const Sim3d kf_from_world = k.world_from_keyframe.Inverse();
    const Rigid3d kf_from_camera = kf_from_world.TransformPose(last_world_from_camera);
    for (const Rigid3d& guess : {kf_from_camera.Inverse(), Rigid3d()}) {
      StatusOr<TrackingResult> tr = reloc_tracker->Track(rgb, guess);
      if (tr.ok() && tr->ok) {
        *frame_from_kf = tr->frame_from_keyframe;
        *keyframe_index = id;
        return true;
      }
    }
  }
  return false;
}

std::vector<SlamKeyframe> SlamSystem::TakeFinishedKeyframes() {
  std::vector<SlamKeyframe> out;
  if (start_check_) return out;  // held until the start check is done
  // With keyframe_adjustment_async, the keyframe finished when the running adjustment was started (the
  // one before its newest) is held until that adjustment has been applied: handed out inline, it would
  // have had it.
  const int held_from = impl_->pending_adjustment ? impl_->pending_adjustment->num_keyframes - 2
                                                  : static_cast<int>(impl_->keyframes.size());
  for (Impl::Keyframe& k : impl_->keyframes) {
    if (!k.finished || k.handed_out || k.id >= held_from) continue;
    SlamKeyframe s;
    s.id = k.id;
    s.frame_id = k.frame_id;
    s.timestamp = k.timestamp;
    s.world_from_keyframe = k.world_from_keyframe;
    s.rgb = k.rgb;
    s.depth = k.final_depth;
    out.push_back(std::move(s));
    k.handed_out = true;
  }
  return out;
}

std::vector<SlamKeyframe> SlamSystem::Finish() {
  if (start_check_ && impl_->pending_start_check) {
    // The pair scales still on their thread (start_check_async): reported; no second start can run now.
    const ScopedSeconds timer(&start_check_report_.seconds);
    const std::vector<double> first = TakeStartCheckScales();
    if (first.size() >= 3) {
      start_check_report_.checked = true;
      start_check_report_.first_spread = PairSpread(first);
      start_check_report_.passed = start_check_report_.first_spread <= impl_->options.start_check_max_pair_spread;
    }
    PRISM_LOG(INFO) << "slam: start check at Finish: " << first.size() << " keyframe pairs gave a shading scale"
                    << (start_check_report_.checked ? ", spread " + std::to_string(start_check_report_.first_spread)
                                                    : std::string());
  }
  if (start_check_) {
    PRISM_LOG(INFO) << "slam: start check not done at Finish; the " << (start_check_->retry ? "first " : "")
                    << "start is kept";
    start_check_.reset();
    impl_->start_check_running = false;  // the last keyframe's adjustments as after the check
  }
  impl_->ApplyPendingAdjustment();
  if (impl_->adjustment_owed) {  // keyframe_adjustment_max_wait_ms: the newest keyframe's window adjustment
    impl_->StartOwedAdjustment();
    impl_->ApplyPendingAdjustment();
  }
  if (impl_->current_depth && !impl_->keyframes.empty() && !impl_->keyframes.back().finished) {
    impl_->current_depth->Regularise();
    impl_->FinishCurrent();
    // The last keyframe may close a loop too.
    if (impl_->options.loop_closure) impl_->CloseLoops(static_cast<int>(impl_->keyframes.size()) - 1);
  }
  std::vector<SlamKeyframe> last = TakeFinishedKeyframes();
  if (impl_->options.final_adjustment) AdjustAllKeyframes();
  return last;
}

void SlamSystem::AdjustAllKeyframes() {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  if (m.final_adjustment_done) return;
  if (m.CanAdjustAllKeyframes()) {
    m.final_adjustment_done = true;
    m.AdjustKeyframes(0, m.options.final_adjustment_ba, /*at_finish=*/true);
    m.AdjustByFeatures();
  } else if (m.CanAdjustByFeaturesAlone()) {
    m.final_adjustment_done = true;
    m.AdjustByFeatures();
  }
}

FeatureAdjustmentReport SlamSystem::feature_adjustment() const { return impl_->feature_report; }

StatusOr<MetricScaleEstimate> SlamSystem::EstimateMetricScale() {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  const int n = static_cast<int>(m.keyframes.size());
  if (n < 3 || !m.current_depth || !m.keyframes.back().finished)
    return FailedPreconditionError("EstimateMetricScale: needs at least 3 finished keyframes (call Finish first)");
  if (!AllPointLights(m.rig))
    return FailedPreconditionError("EstimateMetricScale: needs three point lights on the rig");
  const double start = m.RelitMetresPerWorldUnit();
  if (!(start > 0)) return FailedPreconditionError("EstimateMetricScale: no keyframe pair gave a shading scale");
  // At most final_adjustment_max_keyframes, the newest.
  const int first = std::max(0, n - m.options.final_adjustment_max_keyframes);
  MetricScaleEstimate e;
  e.start_metres_per_world_unit = start;
  {
    const size_t np = m.relit_pair_estimates.size();
    e.pairs = static_cast<int>(np);
    e.pair_spread = PairSpread(m.relit_pair_estimates);
    e.consistent = e.pair_spread <= m.options.metric_scale_max_pair_spread;
    if (!e.consistent) {
      PRISM_LOG(WARNING) << "slam: the reconstruction disagrees with the co-moving lights' shading: the " << np
                         << " keyframe pairs' shading scales spread by " << e.pair_spread
                         << " of their median (interquartile range; limit " << m.options.metric_scale_max_pair_spread
                         << "); the trajectory and depth are probably distorted (e.g. an initialisation in the "
                            "bas-relief ambiguity of a sideways start)";
    }
  }
  double k = start;
  for (int pass = 0; pass < 4; ++pass) {
    DirectBaProblem problem;
    if (!m.BuildAdjustmentProblem(first, /*relit=*/true, /*mixed=*/false, k, m.options.metric_scale_min_band_fraction,
                                  &problem))
      return FailedPreconditionError("EstimateMetricScale: too few adjustment points");
    StatusOr<DirectBaSummary> summary =
        AdjustKeyframeWindowDirect(m.options.final_adjustment_relit_ba, &problem, m.pool);
    if (!summary.ok()) return summary.status();
    const double next = problem.relit.metres_per_world_unit;
    e.passes = pass + 1;
    e.residuals = summary->residuals;
    e.final_rms = summary->final_rms;
    const bool settled = std::abs(std::log(next / k)) < 0.005;
    k = next;
    if (settled) break;
  }
  for (Impl::Keyframe& kf : m.keyframes) kf.grey_j.release();
  e.metres_per_world_unit = k;
  e.keyframes = n - first;
  return e;
}

StatusOr<ScaleDriftCorrection> SlamSystem::CorrectScaleDrift() {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  const int n = static_cast<int>(m.keyframes.size());
  if (n < 3 || !m.keyframes.back().finished)
    return FailedPreconditionError("CorrectScaleDrift: needs at least 3 finished keyframes (call Finish first)");
  if (!AllPointLights(m.rig)) return FailedPreconditionError("CorrectScaleDrift: needs three point lights on the rig");
  const std::vector<std::pair<int, double>> pairs = m.IndexedPairShadingScales(static_cast<size_t>(n));
  if (pairs.size() < 3)
    return FailedPreconditionError("CorrectScaleDrift: " + std::to_string(pairs.size()) +
                                   " keyframe pairs gave a shading scale (3 needed)");
  // The consistency check (EstimateMetricScale) sees the scales from before the correction.
  m.relit_pair_estimates.clear();
  for (const auto& [k, scale] : pairs) m.relit_pair_estimates.push_back(scale);
  m.relit_metres_per_world_unit = 0;  // estimated again at the corrected poses
  // Keyframe k's depth unit in metres: its pair's scale times its own Sim(3) scale (the pair's scale is
  // metres per world unit through k's unit). Pairs without a scale, and the last keyframe, take the
  // nearest pair's.
  std::vector<double> by_pair(static_cast<size_t>(n - 1), std::numeric_limits<double>::quiet_NaN());
  for (const auto& [k, scale] : pairs) by_pair[static_cast<size_t>(k)] = scale;
  const int w = m.options.scale_drift_window;
  std::vector<double> metres_per_world_unit(static_cast<size_t>(n));
  for (int k = 0; k < n; ++k) {
    const int centre = std::min(k, n - 2);
    std::vector<double> near;
    for (int reach = w; near.empty(); ++reach) {
      for (int j = std::max(0, centre - reach); j <= std::min(n - 2, centre + reach); ++j)
        if (std::isfinite(by_pair[static_cast<size_t>(j)])) near.push_back(by_pair[static_cast<size_t>(j)]);
    }
    std::sort(near.begin(), near.end());
    const size_t h = near.size() / 2;
    metres_per_world_unit[static_cast<size_t>(k)] = near.size() % 2 ? near[h] : 0.5 * (near[h - 1] + near[h]);
  }
  ScaleDriftCorrection c;
  c.pairs = static_cast<int>(pairs.size());
  c.min_factor = c.max_factor = 1;
  std::vector<double> factor(static_cast<size_t>(n));
  for (int k = 0; k < n; ++k) {
    factor[static_cast<size_t>(k)] = metres_per_world_unit[static_cast<size_t>(k)] / metres_per_world_unit[0];
    c.min_factor = std::min(c.min_factor, factor[static_cast<size_t>(k)]);
    c.max_factor = std::max(c.max_factor, factor[static_cast<size_t>(k)]);
  }
  // Odometry edges: the same rotation and translation (in the older keyframe's units), the corrected
  // ratio of depth units. Loop edges as measured.
  std::vector<PoseGraphEdge> edges = m.graph_edges;
  for (size_t e = 0; e < edges.size(); ++e) {
    if (m.graph_edge_is_loop[e]) {
      ++c.loop_edges;
      continue;
    }
    PoseGraphEdge& edge = edges[e];
    edge.from_from_to = m.keyframes[static_cast<size_t>(edge.from)].world_from_keyframe.Inverse() *
                        m.keyframes[static_cast<size_t>(edge.to)].world_from_keyframe;
    edge.from_from_to.scale *= factor[static_cast<size_t>(edge.to)] / factor[static_cast<size_t>(edge.from)];
  }
  std::vector<Sim3d> nodes;
  for (const Impl::Keyframe& k : m.keyframes) nodes.push_back(k.world_from_keyframe);
  PoseGraphOptions go;
  go.max_iterations = 100;
  PRISM_ASSIGN_OR_RETURN(PoseGraphSummary summary, OptimisePoseGraph(edges, go, &nodes));
  for (int k = 0; k < n; ++k) m.keyframes[static_cast<size_t>(k)].world_from_keyframe = nodes[static_cast<size_t>(k)];
  m.graph_edges = std::move(edges);
  for (Impl::FrameRecord& f : m.frames)
    if (f.result.state == SlamState::kTracking && f.result.keyframe_id >= 0)
      f.result.world_from_camera = m.WorldFromFrame(f);
  PRISM_LOG(INFO) << "slam: scale drift corrected from " << c.pairs << " keyframe pairs' shading scales: depth units x"
                  << c.min_factor << " .. x" << c.max_factor << " (pose graph cost " << summary.initial_cost << " -> "
                  << summary.final_cost << ", " << c.loop_edges << " loop edges)";
  return c;
}

std::vector<SlamFrameResult> SlamSystem::Trajectory() const {
  std::vector<SlamFrameResult> out;
  out.reserve(impl_->frames.size());
  for (const Impl::FrameRecord& f : impl_->frames) {
    SlamFrameResult r = f.result;
    if (r.state == SlamState::kTracking && r.keyframe_id >= 0) r.world_from_camera = impl_->WorldFromFrame(f);
    out.push_back(std::move(r));
  }
  return out;
}

PointCloud SlamSystem::SemiDenseCloud() const {
  PointCloud cloud;
  const PinholeCamera& cam = impl_->rig.camera;
  for (const Impl::Keyframe& k : impl_->keyframes) {
    InverseDepthMap depth =
        k.finished ? k.final_depth
                   : (impl_->current_depth ? impl_->current_depth->ToInverseDepthMap() : InverseDepthMap());
    if (depth.inverse_depth.empty()) continue;
    for (int y = 0; y < cam.height; ++y) {
      const float* d = depth.inverse_depth.ptr<float>(y);
      const uint8_t* c = k.rgb.ptr<uint8_t>(y);
      for (int x = 0; x < cam.width; ++x) {
        if (!(d[x] > 0)) continue;
        const Eigen::Vector3d p = cam.Unproject(Eigen::Vector2d(x, y)) / d[x];
        cloud.positions.push_back((k.world_from_keyframe * p).cast<float>());
        cloud.colors.push_back(Eigen::Matrix<uint8_t, 3, 1>(c[3 * x], c[3 * x + 1], c[3 * x + 2]));
      }
    }
  }
  return cloud;
}

int SlamSystem::num_keyframes() const { return static_cast<int>(impl_->keyframes.size()); }

int SlamSystem::num_loop_closures() const { return impl_->loop_closures; }

int SlamSystem::num_keyframe_adjustments() const {
  // The one running on its own thread counts (it is applied before anything reads its result).
  return impl_->keyframe_adjustments + (impl_->pending_adjustment ? 1 : 0) + (impl_->adjustment_owed ? 1 : 0);
}

SlamTimings SlamSystem::timings() const { return impl_->timings; }

void SlamSystem::RefineKeyframeDepths(int neighbours, double relative_sigma, int rounds,
                                      std::vector<SlamKeyframe>* keyframes) {
  impl_->ApplyPendingAdjustment();
  Impl& m = *impl_;
  const int span = neighbours;
  if (span <= 0 || !(relative_sigma > 0) || keyframes == nullptr) return;
  const int n = static_cast<int>(m.keyframes.size());
  std::vector<cv::Mat> grey_j(static_cast<size_t>(n));  // each keyframe's J, computed once
  std::vector<InverseDepthMap> handed_out;              // each round starts from these
  for (const SlamKeyframe& out : *keyframes) handed_out.push_back(out.depth);
  const bool readjust = m.options.final_adjustment && m.CanAdjustAllKeyframes() && n >= 3;
  const bool features_alone = m.options.final_adjustment && m.CanAdjustByFeaturesAlone() && n >= 3;
  for (int round = 0; round < std::max(1, rounds); ++round) {
    if (round > 0) {
      if (!readjust && !features_alone) break;
      // The adjustment's points come from the keyframes' (refined) final depths; it uses the same J.
      for (int k = 0; k < n; ++k)
        if (!grey_j[static_cast<size_t>(k)].empty())
          m.keyframes[static_cast<size_t>(k)].grey_j = grey_j[static_cast<size_t>(k)];
      // The features first: they set the turn the direct cost leaves nearly flat, the direct adjustment
      // then refines the poses locally from there.
      m.AdjustByFeatures();
      if (readjust) m.AdjustKeyframes(0, m.options.final_adjustment_ba, /*at_finish=*/true);
      for (size_t i = 0; i < keyframes->size(); ++i) (*keyframes)[i].depth = handed_out[i];
    }
    // Each keyframe apart: with a pool of more than one thread the keyframes are refined in parallel,
    // each on one thread (the depth update gives the same bits with or without a pool), every neighbour's
    // J made first. Keyframe 0's seed reads keyframe 1's depth as handed out (the one-thread order
    // refines keyframe 0 first).
    const bool by_keyframe = m.pool != nullptr && m.pool->num_threads() > 1 && keyframes->size() > 1;
    if (by_keyframe) {
      m.pool->ParallelFor(0, n, [&](std::ptrdiff_t j) {
        cv::Mat& jj = grey_j[static_cast<size_t>(j)];
        if (jj.empty()) {
          cv::Mat mean;
          KeyframeDepth::NormalisedGrey(m.keyframes[static_cast<size_t>(j)].rgb, m.options.depth, &jj, &mean);
        }
      });
    }
    std::vector<InverseDepthMap> round_start;  // by_keyframe: the depths this round starts from
    if (by_keyframe)
      for (const SlamKeyframe& o : *keyframes) round_start.push_back(o.depth);
    auto refine = [&](SlamKeyframe& out, ThreadPool* update_pool) {
      const int id = out.id;
      if (id < 0 || id >= n || out.depth.inverse_depth.empty()) return;
      const Impl::Keyframe& k = m.keyframes[static_cast<size_t>(id)];
      // Every search made: this runs once, after the last frame (skip_information_ratio is for the
      // online mapping's time).
      DepthFilterOptions refine_options = m.options.depth;
      refine_options.skip_information_ratio = 0;
      StatusOr<KeyframeDepth> kd = KeyframeDepth::Create(k.rgb, m.rig.camera, refine_options, m.rig.crosstalk);
      if (!kd.ok()) return;
      cv::Mat seed = out.depth.inverse_depth;
      if (id == 0 && n >= 2 && m.options.final_refinement_first_from_second) {
        const cv::Mat* second = nullptr;
        for (size_t i = 0; i < keyframes->size(); ++i) {
          const SlamKeyframe& o = (*keyframes)[i];
          const cv::Mat& second_depth = by_keyframe ? round_start[i].inverse_depth : o.depth.inverse_depth;
          if (o.id == 1 && !second_depth.empty()) second = &second_depth;
        }
        if (second != nullptr) seed = m.SeedFromSecondKeyframe(*kd, out.depth.inverse_depth, *second);
      }
      kd->Seed(seed, relative_sigma, 2);
      const double mean_idepth = kd->MeanInverseDepth();
      for (int j = std::max(0, id - span); j <= std::min(n - 1, id + span); ++j) {
        if (j == id) continue;
        // A point X of keyframe id (its units) in j's camera, in id's units.
        const Rigid3d j_from_id =
            BFromAInUnitsOfA(k.world_from_keyframe, m.keyframes[static_cast<size_t>(j)].world_from_keyframe);
        // Only neighbours that see about the same scene (not across a relocalisation): within twice the
        // keyframe distance and rotation limits.
        if (j_from_id.translation.norm() * mean_idepth > 2 * m.options.keyframe_distance_fraction + 0.2 ||
            RotationAngle(j_from_id.rotation) * kRadToDeg > 2 * m.options.keyframe_max_rotation_deg)
          continue;
        cv::Mat& jj = grey_j[static_cast<size_t>(j)];
        if (jj.empty()) {
          cv::Mat mean;
          KeyframeDepth::NormalisedGrey(m.keyframes[static_cast<size_t>(j)].rgb, m.options.depth, &jj, &mean);
        }
        kd->Update(jj, j_from_id, update_pool);
      }
      kd->Regularise();
      out.depth = kd->ToInverseDepthMap();
      // Only a neighbour's image is used above, not its depth: the order does not matter.
      Impl::Keyframe& refined = m.keyframes[static_cast<size_t>(id)];
      if (refined.finished) {
        refined.final_depth = out.depth;
        refined.DropWindowPoints();
      }
    };
    if (by_keyframe) {
      m.pool->ParallelFor(0, static_cast<std::ptrdiff_t>(keyframes->size()),
                          [&](std::ptrdiff_t i) { refine((*keyframes)[static_cast<size_t>(i)], nullptr); });
    } else {
      for (SlamKeyframe& out : *keyframes) refine(out, m.pool);
    }
  }
}

std::vector<Sim3d> SlamSystem::KeyframePoses() const {
  std::vector<Sim3d> out;
  for (const Impl::Keyframe& k : impl_->keyframes) out.push_back(k.world_from_keyframe);
  return out;
}

}  // namespace prism
