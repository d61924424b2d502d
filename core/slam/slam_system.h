// Semi-dense direct monocular SLAM for one session (in the spirit of LSD-SLAM, Engel et al. 2014):
// every frame is tracked against the current keyframe (tracker.h); the keyframe's semi-dense inverse
// depth is refined by small-baseline stereo along epipolar lines in the tracked frames (a per-pixel
// Kalman-style filter, depth_filter.h); when the camera has moved far enough a new keyframe is made and
// the depth is propagated into it. Keyframes form a Sim(3) pose graph (pose_graph.h): an edge from
// each keyframe to the one it was made from (its tracked pose), and loop-closure edges when a finished
// keyframe is found close to a much older one and the two align directly in both directions; every
// loop edge re-optimises the graph, correcting position and scale drift.
//
// Monocular: the scale is arbitrary (fixed at initialisation so that the median depth of the first
// triangulated points is 1) and drifts slowly; keyframe poses are Sim(3).
//
// Not thread-safe: one thread (or one serial strand) calls ProcessFrame in frame order.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/io/inverse_depth.h"
#include "core/slam/depth_filter.h"
#include "core/slam/feature_adjustment.h"
#include "core/slam/keyframe_ba.h"
#include "core/slam/tracker.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

// Every field, nested ones included, has a text key in slam_config.cc (SlamOptionKeys): prism-slam and
// prism-server read and write the options through it, so a new field needs its line there.
struct SlamOptions {
  // Frame-to-keyframe tracking on J, the local-mean normalised image (25x25 box), which cancels gain: no free gain
  // (it lets a wrong pose explain the image). Darker, weaker-gradient pixels and a looser residual limit than
  // TrackerOptions' defaults suit the dim dark-room presets: more points and accuracy, more time per frame.
  TrackerOptions tracker = [] {
    TrackerOptions t;
    t.estimate_affine_brightness = false;
    t.max_residual_rms = 40.0;
    t.min_gradient = 4.0;
    t.min_local_mean = 15.0;
    t.local_mean_radius_px = 12;
    t.local_mean_floor = 4.0;
    // Camera-attached points (cast-shadow edges, shading that moves with the lights) leave the cost after 2 votes.
    t.camera_attached_min_votes = 2;
    t.camera_attached_min_flow_px = 1.0;
    t.camera_attached_residual_ratio = 0.8;
    return t;
  }();
  // Loop closure and relocalisation align views far apart from a drifted guess: a fifth (32 px) level widens the
  // basin; the tracker's own, stronger pixel thresholds. Levels the image is too small for (side < 8 px) are dropped.
  TrackerOptions wide_baseline_tracker = [] {
    TrackerOptions t;
    t.estimate_affine_brightness = false;
    t.max_residual_rms = 40.0;
    t.pyramid_levels = 5;
    return t;
  }();
  // Semi-dense stereo depth on the same J as `tracker`, with darker, weaker-gradient pixels than its defaults.
  DepthFilterOptions depth = [] {
    DepthFilterOptions d;
    d.min_gradient = 3.0;
    d.min_local_mean = 12.0;
    d.local_mean_radius_px = 12;  // see `tracker`
    d.local_mean_floor = 4.0;
    // 1.25% propagation noise: a new keyframe's depth follows the fresh stereo more than the previous scale.
    d.propagation_relative_sigma = 0.0125;
    d.camera_attached_min_votes = 2;  // see `tracker`
    d.camera_attached_error_ratio = 0.8;
    // Leave out the dim side of local-mean edges (the ground beside a bright object): better depth, less coverage.
    d.max_local_mean_log_gradient = 0.03;
    d.local_mean_edge_dim_side_only = true;
    return d;
  }();
  // New keyframe when the translation exceeds this fraction of the keyframe's mean depth, > 0: lower = more keyframes.
  double keyframe_distance_fraction = 0.09;
  // ... or fewer than this fraction of the keyframe's points are visible, in [0, 1]: higher = more keyframes.
  double keyframe_min_visible_fraction = 0.6;
  // ... or the rotation exceeds this, degrees, > 0: keeps a turn with little translation from stretching a keyframe.
  double keyframe_max_rotation_deg = 10.0;
  // Initialisation (KLT, essential matrix, triangulation): frames buffered before it is tried, >= 2.
  int init_min_frames = 10;
  // The first keyframe needs this fraction of its candidate pixels converged, in [0, 1]: higher = later, safer start.
  double init_min_converged_fraction = 0.3;
  // Median KLT motion needed first (raw, or with the essential matrix's rotation taken out), fraction of the
  // image width, > 0: higher = better conditioned, later start.
  double init_min_parallax_fraction = 0.03;
  // Initialisation restarts from the current frame after this many frames without success, >= init_min_frames.
  int init_max_frames = 90;
  // KLT on J instead of raw grey, cancelling the lights' shading (SlamSystem::Create turns it off without lights).
  bool init_track_normalised = true;
  // KLT features only where the raw local mean is at least this, grey levels, in [0, 255] (0 = anywhere).
  double init_min_feature_local_mean = 20.0;
  // The tracker's max_residual_rms is multiplied by this while the first depth is rough, >= 1.
  double init_residual_factor = 2.0;
  // Refinement rounds of the first keyframe over the buffered frames, in [1, 10]: more = better seed, slower start.
  int init_rounds = 1;
  // Threads for the first keyframe's depth updates when the pool has fewer, in [1, 64]; same bits on any number.
  int init_threads = 2;
  // depth.max_local_mean_log_gradient in the first keyframe too; false: better forward starts, worse standard runs.
  bool init_depth_edge_test = true;
  // Relative sigma of a new keyframe's pixels without propagated depth (searched along the whole segment), > 0.
  double new_pixel_relative_sigma = 0.5;
  // The tracker's copy of the keyframe depth is refreshed every this many frames, >= 1: lower = fresher, slower.
  int tracker_refresh_frames = 3;
  // Stereo update on every this many tracked frames (always on a new keyframe), >= 1: higher = faster, less accurate.
  int depth_update_interval = 1;
  // Mapping budget, ms per tracked frame, >= 0 (0 = off): skips stereo updates to keep up; less depth, not repeatable.
  double mapping_budget_ms = 0;
  // The tracker uses keyframe estimates with at least this many observations, >= 1 ...
  int tracking_min_observations = 2;
  // ... and at most this relative sigma, > 0: lower = fewer, more reliable points.
  double tracking_max_relative_sigma = 0.05;
  // A pose further than this from the constant-velocity guess is retried from the last pose, degrees, > 0 ...
  double max_step_rotation_deg = 10.0;
  // ... or this, fraction of the keyframe's mean depth, > 0: lower = catches more wrong minima, more lost frames.
  double max_step_translation_fraction = 0.2;
  // The first frame on a new keyframe starts from the last motion, not at rest (fast forward motion needs it).
  bool keep_velocity_across_keyframes = true;
  // Relocalisation tries at most this many finished keyframes, nearest to the last good pose first, >= 1.
  int relocalise_max_keyframes = 5;
  // Relocalisation is tried after this many consecutive lost frames, >= 1.
  int relocalise_after_lost_frames = 1;
  // Loop closure: each finished keyframe aligned both ways with older ones nearby; an edge re-optimises the graph.
  bool loop_closure = true;
  // Candidates are at least this many keyframes older, >= 2.
  int loop_min_keyframe_gap = 8;
  // ... with their camera centre within this fraction of the keyframe's mean depth, > 0 ...
  double loop_max_distance_fraction = 0.35;
  // ... and their optical axis within this, degrees, in (0, 180].
  double loop_max_angle_deg = 30.0;
  // At most this many candidates aligned per keyframe, >= 1: more = more loops found, more time.
  int loop_max_candidates = 3;
  // The two directions must agree within this, degrees, > 0: lower = fewer false loops, fewer loops.
  double loop_max_rotation_inconsistency_deg = 1.0;
  // ... and at least this many depth pixels overlap, >= 10 (their median ratio gives the depth unit ratio).
  int loop_min_depth_matches = 500;
  // Pose-graph edge sigmas, > 0: rotation (radians), translation (keyframe depth units), log-scale; odometry ...
  double odometry_rotation_sigma = 0.002, odometry_translation_sigma = 0.005, odometry_log_scale_sigma = 0.01;
  // ... and loop edges: smaller = a loop pulls the graph harder.
  double loop_rotation_sigma = 0.002, loop_translation_sigma = 0.005, loop_log_scale_sigma = 0.005;
  // Windowed direct bundle adjustment (keyframe_ba.h) after each keyframe: relative poses and scale far better than
  // tracking gives them. Each adjusted keyframe's depth unit is re-fitted to its points.
  bool keyframe_adjustment = true;
  int keyframe_window = 8;              // keyframes, >= 3: longer = better depth, more time
  int keyframe_window_cell_px = 12;     // one point per cell, pixels, >= 4: smaller = more points, more time
  int keyframe_window_min_points = 40;  // fewer points: no adjustment, >= 10
  // Adjust after every this many new keyframes, >= 1: 2 halves the cost, loses accuracy.
  int keyframe_adjustment_interval = 1;
  // Keyframes with less than this fraction of their depth in the newest's view leave the window, in [0, 1] (0 = off).
  double keyframe_window_min_overlap = 0.5;
  // Re-propagate the newest keyframe's depth along the adjusted pose (the tracked one falls short): better depth.
  bool repropagate_after_adjustment = true;
  // Window adjustment on its own thread, applied at the next keyframe (inline during the start check): faster mapping.
  bool keyframe_adjustment_async = true;
  // Async: ms a keyframe waits for the adjustment, < 0 = until done (repeatable); >= 0: shorter frames, not repeatable.
  double keyframe_adjustment_max_wait_ms = -1;
  // Re-fit the oldest keyframe's depth unit too (it holds the pose gauge): better depth, worse trajectories.
  bool refit_oldest_keyframe_scale = false;
  // Spread each keyframe's later correction over the frames tracked on it: smoother trajectory, keyframes unchanged.
  bool distribute_keyframe_corrections = true;
  // The window adjustment's solver: 6 iterations, Huber 4 grey levels of J (the lights' residuals), gain-ratio damping.
  DirectBaOptions keyframe_window_ba = [] {
    DirectBaOptions b;
    b.max_iterations = 6;
    b.huber = 4.0;
    b.gain_ratio_damping = true;
    return b;
  }();
  // At Finish, one adjustment of all keyframes at once (needs keyframe_adjustment): better depth, time ~ keyframes^2.
  bool final_adjustment = true;
  // ... only up to this many keyframes, >= 3 (all or none; 64: ~10 s after the last frame).
  int final_adjustment_max_keyframes = 64;
  // Then a feature (SIFT) adjustment of all keyframes: pins an orbit's turn-for-depth direction, flat in direct cost.
  bool final_feature_adjustment = true;
  // Beyond final_adjustment_max_keyframes and up to this, the feature adjustment runs alone, >= 3.
  int feature_adjustment_max_keyframes = 96;
  // Its features, tracks and reprojection error (feature_adjustment.h).
  FeatureAdjustmentOptions feature_adjustment;
  // Pairs matched only when this fraction of either's depth projects into the other, in [0, 1]: fewer pairs, faster.
  double feature_adjustment_min_overlap = 0.1;
  // RefineKeyframeDepths (prism-slam): stereo with this many keyframes per side, in [0, 5] (0 = off): better depth.
  int final_refinement_neighbours = 2;
  // Seed keyframe 0's refinement from keyframe 1's depth, fixing the initialisation's depth unit.
  bool final_refinement_first_from_second = true;
  // Relative sigma of each keyframe's own depth as the refinement's prior, > 0.
  double final_refinement_relative_sigma = 0.05;
  // Refinement rounds with the final adjustment re-run between them, in [1, 10]: more = better depth, more time.
  int final_refinement_rounds = 8;
  // The final adjustment's solver: residuals weighted by host gradient (DSO, c = 20), as the lights move strong edges.
  DirectBaOptions final_adjustment_ba = [] {
    DirectBaOptions b;
    b.max_iterations = 6;
    b.huber = 4.0;
    b.gradient_weight_c = 20.0;
    return b;
  }();
  // Final adjustment on the relit residual (keyframe_ba.h; three lights, grey albedo): off, it worsens depth.
  bool final_adjustment_relit = false;
  // Final adjustment on J and the relit residual together (over final_adjustment_relit): off, mixed results.
  bool final_adjustment_mixed = false;
  // The relit residual's scale in the mixed adjustment, > 0: higher = more weight on the lights' shading model.
  double final_adjustment_mixed_relit_scale = 1.0;
  // EstimateMetricScale: a point's weakest band is at least this fraction of its strongest, in [0, 1): fewer points.
  double metric_scale_min_band_fraction = 0.3;
  // EstimateMetricScale: pair-scale spread above this is reported inconsistent with the shading (a warning), > 0.
  double metric_scale_max_pair_spread = 0.16;
  // Start check at this many keyframes, 0 = off or >= 4: pair shading scales that disagree run a second start.
  int start_check_keyframes = 6;
  // Their largest spread, > 0: lower = more second starts (a few seconds each).
  double start_check_max_pair_spread = 0.16;
  // The second start's init_min_parallax_fraction, > 0.
  double start_check_retry_parallax_fraction = 0.05;
  // The check gives up after this many frames, >= 1; their images are kept until then (120 at 512x512: 94 MB).
  int start_check_max_frames = 120;
  // The window's cell size while the check runs, pixels, >= 4: smaller cells hide a distorted start.
  int start_check_window_cell_px = 16;
  // The check's pair scales on their own thread: the same results, a shorter pause of the frame that needs them.
  bool start_check_async = true;
  // The relit adjustment's solver (final_adjustment_relit, EstimateMetricScale).
  DirectBaOptions final_adjustment_relit_ba = [] {
    DirectBaOptions b;
    b.max_iterations = 6;
    b.huber = 4.0;
    b.outlier = 20.0;
    return b;
  }();
  Status Check() const;
};

// SlamSystem::EstimateMetricScale: the metres per SLAM world unit from the co-moving lights.
struct MetricScaleEstimate {
  double metres_per_world_unit = 0;
  double start_metres_per_world_unit = 0;  // the median over keyframe pairs it started from
  int keyframes = 0;                       // keyframes in the adjustment
  int passes = 0;                          // relit adjustments run (until K moved by < 0.5%)
  int residuals = 0;                       // of the last pass
  double final_rms = 0;                    // grey levels, of the last pass
  // A check of the SLAM's geometry against the shading: each consecutive keyframe pair gives its own
  // shading scale (shading_scale.h, at the SLAM's poses and depths); on a consistent reconstruction
  // they agree, on a distorted one (e.g. an initialisation in the bas-relief ambiguity of a sideways
  // start) they scatter. pair_spread: their interquartile range over their median.
  int pairs = 0;
  double pair_spread = 0;
  bool consistent = true;  // pair_spread <= SlamOptions::metric_scale_max_pair_spread
};

// What SlamSystem::FinishStream did, and its times.
struct SlamStreamEnd {
  std::optional<MetricScaleEstimate> metric;  // with FinishStream's metric_scale
  std::string metric_error;
  double adjustment_seconds = 0, refinement_seconds = 0, metric_seconds = 0;
};

enum class SlamState {
  kInitializing,  // first keyframe, depth not converged yet; poses are provisional
  kTracking,      // pose is good
  kLost,          // tracking failed for this frame; the pose is the last good one
};
const char* SlamStateName(SlamState state);

// How a frame's alignment against its keyframe went (SlamFrameResult::tracking; prism-slam writes it to
// tracking.txt). Distances are fractions of the keyframe's mean depth (its mean inverse depth times the
// translation, in the keyframe's depth unit), so they mean the same on every scene and scale.
struct SlamTrackingQuality {
  bool tracked = false;  // false: the frame was not aligned against a keyframe (initialising, lost, relocalised)
  // At the finest pyramid level (TrackingResult): RMS of the inlier residuals (grey levels of the
  // tracker's image), the fraction of the keyframe's points projecting into the frame and the fraction of
  // those that are inliers.
  double residual_rms = 0;
  double visible_fraction = 0;
  double inlier_fraction = 0;
  int iterations = 0;    // Gauss-Newton iterations over all levels of the kept attempt
  bool retried = false;  // the constant-velocity guess failed and the frame was tracked from the last pose
  // The motion from the previous frame (translation, rotation in degrees) and how far the result lies
  // from the constant-velocity guess it started from. A result that stops far short of the guess (a
  // correction near the step) is what a failing alignment looks like.
  double step = 0;
  double rotation_deg = 0;
  double guess_correction = 0;
};

struct SlamFrameResult {
  int64_t frame_id = 0;  // 0, 1, 2, ... in ProcessFrame order
  double timestamp = 0;
  SlamState state = SlamState::kInitializing;
  // world_from_camera in the SLAM's world frame (the first keyframe's camera) and scale.
  Rigid3d world_from_camera;
  bool new_keyframe = false;   // this frame became a keyframe
  bool depth_updated = false;  // the keyframe's depth was updated by stereo with this frame
  int keyframe_id = -1;        // the keyframe this frame was tracked against
  std::string message;         // why, when kLost
  SlamTrackingQuality tracking;
};

// A keyframe handed to the dense stage once its depth map is final.
struct SlamKeyframe {
  int id = 0;
  int64_t frame_id = 0;
  double timestamp = 0;
  // world_from_keyframe camera, SLAM world and scale (after pose-graph optimisation at hand-over).
  Sim3d world_from_keyframe;
  cv::Mat rgb;            // CV_8UC3, the keyframe image
  InverseDepthMap depth;  // semi-dense, in the keyframe's camera, 1/SLAM unit
};

// Wall time (steady clock) spent in each part of ProcessFrame so far, seconds, and counts. Tracking
// and mapping are the two halves the speed bar puts on separate cores: `tracking` is the frame's
// alignment (retries included); mapping is `depth_update` (the stereo updates) plus `keyframes` (new
// keyframes: propagation, the window adjustment, loop search; regularisation and the tracker's
// refreshed copy of the depth between keyframes).
struct SlamTimings {
  double initialisation = 0;  // frames before the first keyframe is tracked (KLT, the first depth)
  double tracking = 0;
  double depth_update = 0;
  double keyframes = 0;
  // Part of `keyframes`: the window adjustment and re-propagation (with
  // SlamOptions::keyframe_adjustment_async: setting each adjustment up).
  double keyframe_adjustment = 0;
  // SlamOptions::keyframe_adjustment_async: the adjustments' wall time on their own thread (not part of
  // `keyframes`), and the time ProcessFrame waited for one to finish (part of `keyframes`).
  double keyframe_adjustment_thread = 0;
  double keyframe_adjustment_wait = 0;
  // SlamOptions::keyframe_adjustment_max_wait_ms: keyframes made while an adjustment still ran (it was
  // applied later), and window adjustments started between keyframes (after such a late one).
  int keyframes_made_before_adjustment = 0;
  int adjustments_started_late = 0;
  double loop_search = 0;             // part of `keyframes` (or `relocalisation`): loop-closure alignments
  double relocalisation = 0;          // lost frames' searches among the keyframes
  int tracked_frames = 0;             // frames that reached the tracker
  int depth_updates = 0;              // stereo updates of the current keyframe's depth
  int depth_updates_over_budget = 0;  // tracked frames not updated because of mapping_budget_ms
  int64_t depth_pixels_searched = 0;  // over those updates: epipolar searches
  int64_t depth_pixels_skipped = 0;   // and searches skipped as uninformative (skip_information_ratio)
};

// The last feature adjustment of the keyframes (SlamOptions::final_feature_adjustment).
struct FeatureAdjustmentReport {
  bool ran = false;                  // it was tried
  bool applied = false;              // it succeeded and moved the keyframes
  std::string error;                 // why not, when it was tried and did not apply
  int runs = 0;                      // times it ran (Finish, and RefineKeyframeDepths' rounds)
  FeatureAdjustmentSummary summary;  // of the last run that applied (observations_by_keyframe cleared)
  int pairs_tried = 0;               // keyframe pairs matched (within the angle and overlap)
  double tracks_seconds = 0;         // wall time of finding and matching the features (once)
  int keyframes_rescaled = 0;        // keyframes whose depth unit followed the tracks in the last run
  double seconds = 0;                // wall time over all runs
};

// What the start check (SlamOptions::start_check_*) found.
struct StartCheckReport {
  bool checked = false;     // the first start reached start_check_keyframes keyframes and was checked
  double first_spread = 0;  // its keyframe pairs' shading-scale spread
  bool passed = false;      // within start_check_max_pair_spread
  // It failed and a second start ran alongside (not when the first start's initialisation already had
  // start_check_retry_parallax_fraction: the second would be the same).
  bool retried = false;
  bool second_checked = false;  // the second start reached as many keyframes in time
  double second_spread = 0;     // its spread (infinity when fewer than 3 of its pairs gave a scale)
  bool second_kept = false;     // the second start replaced the first
  // Frames the second start processed inside ProcessFrame (all of its frames inline; with start_check_async
  // none: it runs on its own thread).
  int second_frames_on_caller = 0;
  bool done = false;  // the check is closed (also when it is off or could not run)
  // Wall time of the check inside ProcessFrame: the pair shading scales (a one-time pause of the frame
  // that reaches start_check_keyframes; with start_check_async only the copy of the pairs and a keyframe's
  // wait for their thread) and, when a second start runs, its replay and its frames.
  double seconds = 0;
  // start_check_async: the pair shading scales' time on their own thread.
  double thread_seconds = 0;
};

class SlamSystem {
 public:
  // Fails on invalid options or rig (camera with distortion: undistort first).
  // `pool` (optional, not owned, may be shared by sessions) parallelises the depth filter.
  static StatusOr<std::unique_ptr<SlamSystem>> Create(const RigCalibration& rig, const SlamOptions& options,
                                                      ThreadPool* pool = nullptr);
  ~SlamSystem();

  // rgb: CV_8UC3 of the camera's size. Fails only on invalid input; tracking loss is a state.
  // skip_depth_update: the frame is tracked, but the keyframe's depth is not updated by stereo with it
  // (unless it makes a new keyframe, whose depth always takes the widest baseline). A caller that has
  // fallen behind its input (SessionPipelineOptions::skip_depth_update_backlog) spends its time on poses.
  StatusOr<SlamFrameResult> ProcessFrame(double timestamp, const cv::Mat& rgb, bool skip_depth_update = false);

  // Keyframes whose depth maps are final (the system has moved on to a newer keyframe), oldest first;
  // each is returned once.
  std::vector<SlamKeyframe> TakeFinishedKeyframes();
  // Ends the sequence: the current keyframe is finished too and returned with any not yet taken. With
  // SlamOptions::final_adjustment it then runs AdjustAllKeyframes.
  std::vector<SlamKeyframe> Finish();
  // Finish without the final adjustment, so that the last keyframes can be handed on at once (the
  // caller runs AdjustAllKeyframes after, as SessionPipeline does).
  std::vector<SlamKeyframe> FinishTracking();
  // The final adjustment (SlamOptions::final_adjustment): after Finish, the direct adjustment of every
  // keyframe at once, when there are at most final_adjustment_max_keyframes, then the feature adjustment
  // (final_feature_adjustment); beyond that, up to feature_adjustment_max_keyframes, the feature
  // adjustment alone (else nothing). Moves the
  // keyframes' poses and depth units (KeyframePoses, Trajectory), not the keyframes handed over. For a
  // caller that hands the last keyframes on first (the server's session pipeline: the map is done
  // without waiting for it) with final_adjustment off; runs once (later calls do nothing).
  void AdjustAllKeyframes();
  // The stream's end after FinishTracking (the last keyframes handed on), the one sequence prism-slam,
  // the server and the tests run: AdjustAllKeyframes (SlamOptions::final_adjustment); with `refine` (the
  // keyframes as handed out, kept by the caller) RefineKeyframeDepths on them with
  // SlamOptions::final_refinement_*; with `metric_scale`, EstimateMetricScale.
  SlamStreamEnd FinishStream(bool metric_scale, std::vector<SlamKeyframe>* refine = nullptr);
  // The metres per world unit from the rig's co-moving lights (after Finish): the relit keyframe
  // adjustment (keyframe_ba.h, DirectBaRelit) over the keyframes (at most
  // final_adjustment_max_keyframes, the newest) with log K free, started from the median of
  // EstimateShadingScale over consecutive keyframe pairs, repeated (up to 4 passes) until K moves by less
  // than 0.5%. The adjusted poses and depths are discarded: the SLAM's state does not change. Under a grey
  // albedo; coloured albedo biases it (see the README for the figures). FAILED_PRECONDITION before
  // Finish, with fewer than 3 keyframes, without three point lights, or without usable points.
  StatusOr<MetricScaleEstimate> EstimateMetricScale();
  // After Finish: re-estimates the depth of each of `keyframes` (as handed out; matched by id) at the
  // keyframes' final poses (KeyframePoses): its own depth as the prior (relative sigma
  // `relative_sigma`, counted as 2 observations), one stereo update with each of up to `neighbours`
  // keyframes on either side (those within twice keyframe_distance_fraction + 0.2 of its mean depth and
  // twice keyframe_max_rotation_deg), then regularised; the system's own copy (SemiDenseCloud) becomes the
  // refined depth too. Nothing when neighbours <= 0. With rounds > 1 (SlamOptions::final_refinement_rounds)
  // and the final adjustment available, the adjustment of all keyframes runs again on the refined depths
  // between rounds (KeyframePoses and Trajectory move) and each round starts again from the depths as
  // handed out. prism-slam runs it with SlamOptions::final_refinement_*. With a pool of more than one
  // thread the keyframes are refined in parallel, each on one thread (the same results to the bit).
  void RefineKeyframeDepths(int neighbours, double relative_sigma, int rounds, std::vector<SlamKeyframe>* keyframes);

  // Every processed frame's result, in order (poses of frames tracked against keyframes moved by the
  // pose graph are updated).
  std::vector<SlamFrameResult> Trajectory() const;
  // The semi-dense points of all keyframes in the world frame, with colours.
  PointCloud SemiDenseCloud() const;
  int num_keyframes() const;
  // world_from_keyframe of every keyframe by id, as optimised so far (SlamKeyframe has the pose at
  // hand-over; loop closures move keyframes later).
  std::vector<Sim3d> KeyframePoses() const;
  // Loop-closure edges added to the pose graph so far.
  int num_loop_closures() const;
  // Keyframe-window adjustments applied so far (SlamOptions::keyframe_adjustment), with the one running on
  // its own thread (keyframe_adjustment_async) and the one owed (keyframe_adjustment_max_wait_ms).
  int num_keyframe_adjustments() const;
  // Where ProcessFrame's time went so far.
  SlamTimings timings() const;
  // The feature adjustment's outcome so far (SlamOptions::final_feature_adjustment).
  FeatureAdjustmentReport feature_adjustment() const;
  // The start check's outcome so far.
  StartCheckReport start_check() const {
    StartCheckReport r = start_check_report_;
    r.done = start_check_ == nullptr;
    return r;
  }

 private:
  struct Impl;
  struct StartCheck;
  explicit SlamSystem(std::unique_ptr<Impl> impl);
  static StatusOr<std::unique_ptr<Impl>> NewImpl(const RigCalibration& rig, const SlamOptions& options,
                                                 ThreadPool* pool);
  // SlamOptions::start_check_*: keeps the frame, runs the second start, decides.
  void StepStartCheck(double timestamp, const cv::Mat& rgb, StatusOr<SlamFrameResult>* result);
  // The second start's check after it has processed frame `frame` (its result `second`; its pair shading
  // scales when given, else computed here): true when the check closes there (impl_ is then the start kept).
  bool StepSecondStart(size_t frame, StatusOr<SlamFrameResult>* second, const std::vector<double>* scales = nullptr);
  // The second start on its thread (start_check_async): waits for it to have every frame, then decides
  // as StepSecondStart; `result` (may be null) is the newest frame's, replaced when the second is kept.
  void CloseSecondStart(StatusOr<SlamFrameResult>* result);
  // The pair scales of the start check on its thread (start_check_async; waits for them), with their times
  // in the report.
  std::vector<double> TakeStartCheckScales();
  std::unique_ptr<Impl> impl_;
  std::unique_ptr<StartCheck> start_check_;  // while the start check is open
  StartCheckReport start_check_report_;
};

}  // namespace prism
