// Feature bundle adjustment of the keyframes: SIFT features on each keyframe's shading-normalised
// image J, matched between every pair of keyframes that see the same scene, joined into tracks and
// adjusted with the keyframe poses by Levenberg-Marquardt on the reprojection error (Huber), the points
// eliminated by the Schur complement (3 unknowns each).
//
// Why: the direct adjustments (keyframe_ba.h) compare J between keyframes, and J still changes with the
// co-moving lights between views. Along an orbit their cost is nearly flat in the direction that trades
// the turn for an inverse-depth offset of every keyframe's depth (the bas-relief direction): the residuals
// that would pin it are between distant keyframes, where the shading differs most, and their Huber weights
// and outlier tests discard them. A feature's position is set by the albedo texture and barely moves with
// a smooth shading change, and a feature matched across 60 degrees of the orbit still constrains the turn.
//
// Gauge (7 degrees of freedom): the first keyframe is held fixed, and the second may not move along the
// line between the two camera centres (as in keyframe_ba.h). Only rotations and camera centres are
// adjusted; the keyframes' Sim(3) scales (their depth units) are the caller's (see KeyframeFeatureDepths).
#pragma once

#include <functional>
#include <vector>

#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

struct FeatureAdjustmentOptions {
  // SIFT features per keyframe at most (the strongest), >= 16: more = more matches, slower matching (KITTI hits it).
  int max_features = 1500;
  // SIFT's contrast threshold (on J scaled to 8 bits; OpenCV's default is 0.04), in (0, 1).
  double contrast_threshold = 0.02;
  // Features only where J's raw local mean is at least this many grey levels (the dark background is
  // noise), in [0, 255].
  double min_local_mean = 12.0;
  // Lowe's ratio test: the best match's descriptor distance under this fraction of the second best's,
  // in (0, 1].
  double ratio = 0.75;
  // A pair's matches are kept when they agree with a fundamental matrix (RANSAC, this distance to the
  // epipolar line in pixels) and at least min_pair_matches of them do; > 0, >= 8.
  double ransac_threshold_px = 1.0;
  int min_pair_matches = 20;
  // Pairs are matched when their optical axes are within this angle, degrees, in (0, 180].
  double max_pair_angle_deg = 90.0;
  // Huber threshold on the reprojection error, pixels, > 0; after the first solve, observations with a
  // larger error than outlier_px are dropped and the problem solved again, > huber_px.
  double huber_px = 1.0;
  double outlier_px = 3.0;
  // Levenberg-Marquardt iterations per solve, in [1, 500]; a solve stops when the cost decreases by less
  // than function_tolerance of itself, > 0.
  int max_iterations = 50;
  double function_tolerance = 1e-7;
  // A track is triangulated when its rays span at least this angle, degrees, >= 0.
  double min_triangulation_angle_deg = 1.0;
  Status Check() const;
};

// One keyframe's image for the features: its normalised grey level J and raw local mean
// (KeyframeDepth::NormalisedGrey; CV_32F, the camera's size).
struct FeatureImage {
  cv::Mat grey_j;
  cv::Mat local_mean;
};

// Features of the keyframes joined into tracks across keyframe pairs. They depend on the images alone and
// on which pairs were matched (chosen from the poses given to BuildFeatureTracks), so a caller adjusting
// the same keyframes again keeps them.
struct FeatureTracks {
  struct Observation {
    int keyframe = 0;
    float u = 0, v = 0;  // the feature's pixel
  };
  std::vector<std::vector<Observation>> tracks;  // each with at most one observation per keyframe
  int num_keyframes = 0;
  int features = 0;       // over all keyframes
  int pairs_tried = 0;    // keyframe pairs within max_pair_angle_deg
  int pairs_matched = 0;  // of those, the pairs whose matches were kept
};

// Finds SIFT features on every image and matches every pair of keyframes (a, b), a < b, whose optical axes
// are within options.max_pair_angle_deg (world_from_keyframe: one pose per image) and that `pair_filter`
// accepts when given (the caller's view overlap). Images and pairs are processed in parallel over `pool`
// when given (the result is the same). Fails on invalid options, fewer than 3 keyframes, or images of the
// wrong size or type.
StatusOr<FeatureTracks> BuildFeatureTracks(const PinholeCamera& camera, const FeatureAdjustmentOptions& options,
                                           const std::vector<FeatureImage>& images,
                                           const std::vector<Sim3d>& world_from_keyframe, ThreadPool* pool = nullptr,
                                           const std::function<bool(int, int)>& pair_filter = nullptr);

// A track's observation in one keyframe after the adjustment: the feature's pixel and the adjusted
// point's depth (z) in that keyframe's camera, in world units.
struct FeatureObservation {
  float u = 0, v = 0;
  double depth = 0;
};

struct FeatureAdjustmentSummary {
  int features = 0;       // over all keyframes
  int pairs_matched = 0;  // keyframe pairs whose matches were kept
  int tracks = 0;         // triangulated and adjusted
  int observations = 0;   // in the final solve
  double mean_track_length = 0;
  int iterations = 0;
  double initial_rms_px = 0, final_rms_px = 0;  // reprojection error over the final solve's observations
  double initial_median_px = 0, final_median_px = 0;
  // Per keyframe, the observations kept in the final solve (for the caller's depth units).
  std::vector<std::vector<FeatureObservation>> observations_by_keyframe;
};

// Triangulates the tracks at the given poses and adjusts poses and points (world_from_keyframe: in, the
// start; out, adjusted rotations and centres, the scales unchanged). Fails on invalid options, a camera
// with distortion, or poses that do not match the tracks' keyframes; FailedPrecondition for too few
// tracks or keyframes 0 and 1 at one place (no scale gauge). The poses are then unchanged.
StatusOr<FeatureAdjustmentSummary> AdjustKeyframesByFeatures(const PinholeCamera& camera,
                                                             const FeatureAdjustmentOptions& options,
                                                             const FeatureTracks& tracks,
                                                             std::vector<Sim3d>* world_from_keyframe);

}  // namespace prism
