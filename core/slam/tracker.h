// Direct SE(3) frame-to-keyframe tracking (after LSD-SLAM, Engel et al. 2014, and DSO, Engel et al.
// 2018): the keyframe's semi-dense points, with inverse depth and its variance, are warped into the
// new frame and the photometric error is minimised coarse to fine over an image pyramid by
// Levenberg-Marquardt with Huber weights. Each residual is normalised by its variance, which grows
// with the image gradient along the epipolar direction times the inverse-depth variance (LSD-SLAM's
// variance-normalised residual). The rig's lights move with the camera, so the shading of a surface
// point changes between views: an affine brightness change I_frame = exp(a) * I_keyframe + b
// (DSO) is estimated jointly with the pose.
//
// Images are 8-bit RGB; tracking works on the grey image (mean of the three channels).
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/io/inverse_depth.h"
#include "core/util/status.h"

namespace prism {

// How the tracker copes with the shading change caused by the lights moving with the camera.
enum class ShadingModel {
  // Track the raw grey image; only the affine brightness absorbs the shading change.
  kNone,
  // Track J = 128 * I / (box_mean(I) + floor), a local-mean ratio that cancels shading which is
  // smooth over the box (see local_mean_radius_px).
  kLocalMeanNormalisation,
  // kLocalMeanNormalisation plus a per-point prediction from the rig: the keyframe colour is demixed
  // into per-light bands (crosstalk^-1), each band is scaled by the ratio of its Lambertian shading
  // E_l max(0, n.L_l) at the current pose to that at the keyframe (point and normal from the keyframe's
  // depth map, normal by a plane fit), and remixed; the frame's local mean is predicted from the
  // box-averaged bands with the same ratios. Needs the RigCalibration (Tracker::Create) and metric
  // depth. The ratios are evaluated at each pose tried but not differentiated. Points near depth edges
  // or with grazing normals keep their keyframe value. About as accurate as kLocalMeanNormalisation on
  // the dark-room presets (better on the torus, slightly worse on sphere and bunny; see the tests).
  kPredictedShading,
};

struct TrackerOptions {
  // Pyramid levels, [1, 8] (coarsest >= 8 px a side): more = larger motions caught, coarser start.
  int pyramid_levels = 4;
  // Grey-level gradient a keyframe pixel needs to be tracked, [0, 255]: lower = more, weaker points.
  double min_gradient = 6.0;
  // Tracked points per level (strongest per grid cell), >= 16: more = steadier, slower tracking.
  int max_points_per_level = 3000;
  // Levenberg-Marquardt iterations per pyramid level, in [1, 100].
  int max_iterations = 20;
  // Stop a level when the update's norm (translation in keyframe inverse-depth units plus rotation in
  // radians) falls below this, > 0.
  double convergence_threshold = 1e-5;
  // Image noise, grey levels (standard deviation), > 0: weights the residuals against depth noise.
  double image_noise_sigma = 3.0;
  // Huber threshold on the variance-normalised residual (units of its standard deviation), > 0.
  double huber_threshold = 2.0;
  // A point is an inlier when its normalised residual is below this, > 0.
  double inlier_threshold = 4.0;
  // The co-moving lights' shading change (ShadingModel): none, local_mean_normalisation, predicted_shading.
  ShadingModel shading_model = ShadingModel::kLocalMeanNormalisation;
  // kPredictedShading: half size of the window of the keyframe's depth map the normals are fitted in,
  // pixels at each level, in [1, 8].
  int normal_window_radius_px = 2;
  // kPredictedShading: a point keeps its keyframe grey level (no prediction) when a depth in its normal
  // window differs from its own by more than this fraction (a depth edge), in (0, 1].
  double normal_max_depth_jump = 0.05;
  // kPredictedShading: ... or when |cos| between its normal and the viewing ray is below this
  // (grazing), in [0, 1).
  double normal_min_view_cosine = 0.25;
  // kPredictedShading: per-light shading ratios (frame / keyframe) are clamped to [0, this]; a light
  // giving less than 5% of the point's strongest shading in the keyframe keeps ratio 1, > 1.
  double max_shading_ratio = 4.0;
  // kLocalMeanNormalisation: half size of the box, pixels at each level, in [1, 32].
  int local_mean_radius_px = 5;
  // Added to the local mean, grey levels, > 0 (keeps dark regions from amplifying noise).
  double local_mean_floor = 8.0;
  // Keyframe pixels whose raw local mean (same box) is darker than this are not tracked, grey levels,
  // in [0, 255] (in the dark room most of the background is noise).
  double min_local_mean = 30.0;
  // Estimate the affine brightness change (a, b) jointly with the pose.
  bool estimate_affine_brightness = true;
  // Weak prior keeping (a, b) near (0, 0): added to the normal equations' diagonal (a: per unit of a,
  // b: per grey level), >= 0.
  double affine_prior_a = 10.0;
  double affine_prior_b = 1e-3;
  // Tracking is reported lost when, at the finest level, fewer than this fraction of the keyframe's
  // points project into the frame, in [0, 1].
  double min_visible_fraction = 0.25;
  // ... or fewer than this fraction of visible points are inliers (lost), [0, 1]: higher = lost sooner.
  double min_inlier_fraction = 0.5;
  // ... or the estimated contrast gain exp(a) leaves [1 / max_affine_gain, max_affine_gain] (a blank or
  // unrelated frame is otherwise "explained" by a gain near zero), > 1.
  double max_affine_gain = 2.0;
  // ... or the RMS of the inlier residuals exceeds this, grey levels, > 0.
  double max_residual_rms = 25.0;
  // Points that move with the camera (cast-shadow edges and shading of the co-moving lights): after
  // each tracked frame, every keyframe point whose predicted motion is at least
  // camera_attached_min_flow_px (full-resolution pixels) votes: "attached" when the frame at the
  // point's own keyframe pixel matches it clearly better than the frame at its projection (residual
  // below camera_attached_residual_ratio of it, and the projection's residual above 2 noise sigmas),
  // else "moving". A point with at least camera_attached_min_votes attached votes, and more attached
  // than moving ones, is left out of the cost until the keyframe image changes. 0 = off, >= 0.
  int camera_attached_min_votes = 0;
  double camera_attached_min_flow_px = 2.0;     // > 0
  double camera_attached_residual_ratio = 0.5;  // in (0, 1]

  Status Check() const;
};

// The tracker's view of a keyframe: its grey pyramid and, per level, the selected points.
struct TrackingKeyframe {
  struct Point {
    float u = 0, v = 0;           // pixel at this level
    float inverse_depth = 0;      // 1 / z, 1/metre (or 1/SLAM unit)
    float inverse_depth_var = 0;  // variance of inverse_depth
    float intensity = 0;          // keyframe grey level at the pixel
    Eigen::Vector3f ray;          // ((u - cx) / fx, (v - cy) / fy, 1)
    // kPredictedShading only (has_shading false: no prediction for this point). The grey level's share
    // per light (sums to `intensity`), the keyframe normal (unit, towards the camera) and the per-light
    // keyframe shading E_l max(0, n.L_l).
    bool has_shading = false;
    Eigen::Vector3f light_share = Eigen::Vector3f::Zero();
    Eigen::Vector3f light_share_mean = Eigen::Vector3f::Zero();  // box mean of the shares
    Eigen::Vector3f normal = Eigen::Vector3f::Zero();
    Eigen::Vector3f keyframe_shading = Eigen::Vector3f::Zero();
  };
  struct Level {
    PinholeCamera camera;  // intrinsics at this level
    cv::Mat grey;          // CV_32F
    std::vector<Point> points;
  };
  std::vector<Level> levels;
};

struct TrackingResult {
  // The estimated pose of the frame: point_in_frame = frame_from_keyframe * point_in_keyframe.
  Rigid3d frame_from_keyframe;
  // Affine brightness: I_frame ~ exp(affine_a) * I_keyframe + affine_b (grey levels).
  double affine_a = 0;
  double affine_b = 0;
  // Iterations run per pyramid level (index = level, 0 = finest).
  std::vector<int> iterations;
  // At the finest level: RMS of the inlier residuals (grey levels), fraction of the keyframe's points
  // projecting into the frame, and fraction of those that are inliers.
  double residual_rms = 0;
  double visible_fraction = 0;
  double inlier_fraction = 0;
  // False when tracking is lost; `lost_reason` then says why.
  bool ok = false;
  std::string lost_reason;
};

namespace internal {

// A level's keyframe points as arrays, which the tracker's vectorised evaluation passes read (filled
// by Tracker::SetKeyframe; the ray's z is 1).
struct TrackerPointArrays {
  std::vector<float> ray_x, ray_y, inverse_depth, inverse_depth_var, intensity;
  std::vector<float> keep;  // 1 = in the cost, 0 = left out (a camera-attached point)
};

// Per point, what one evaluation computes in its passes (resized to the level's points).
struct TrackerScratch {
  std::vector<float> ys_x, ys_y, ys_z, u, v, inside;  // warped point (scaled by rho), pixel, 1 = in image
  std::vector<float> intensity, grad_u, grad_v;       // frame sample (intensity, d/du, d/dv)
  std::vector<float> predicted;                       // keyframe grey level, as predicted for this pose
  std::vector<float> weight, residual;                // Huber weight / variance, residual (0 outside)
  std::vector<float> point_energy, inlier_sq;         // robust cost; r^2 of an inlier, else -1
  std::vector<float> ones;
  std::vector<float> jacobian[7];  // d residual / d (v, w, a); d / d b is -1
};

}  // namespace internal

class Tracker {
 public:
  // Fails on invalid options or a camera with distortion (undistort the images first), and for
  // ShadingModel::kPredictedShading, which needs the rig (use the overload below).
  static StatusOr<Tracker> Create(const PinholeCamera& camera, const TrackerOptions& options);
  // With the rig's lights and crosstalk (needed by ShadingModel::kPredictedShading; the camera is
  // rig.camera). Fails as above or on an invalid rig.
  static StatusOr<Tracker> Create(const RigCalibration& rig, const TrackerOptions& options);

  // rgb: CV_8UC3 of the camera's size; depth.inverse_depth: CV_32F, 0 = none; depth.variance: CV_32F
  // or empty (then 1% relative standard deviation is assumed). Fails when the sizes or types are wrong
  // or too few points are found.
  Status SetKeyframe(const cv::Mat& rgb, const InverseDepthMap& depth);

  // Tracks a frame against the keyframe, starting from `frame_from_keyframe_guess` (identity, or a
  // constant-velocity prediction). Fails only on invalid input (no keyframe, wrong image size or
  // type); losing track is reported in the result.
  StatusOr<TrackingResult> Track(const cv::Mat& rgb, const Rigid3d& frame_from_keyframe_guess);

  const TrackingKeyframe& keyframe() const { return keyframe_; }
  const TrackerOptions& options() const { return options_; }

  // The image the last Track call tracked at full resolution (CV_32F; empty before the first call): with
  // a shading model other than kNone the normalised grey level J, computed as KeyframeDepth::NormalisedGrey
  // computes it (the same operations), so with the same local_mean_radius_px and local_mean_floor it is
  // the depth filter's input for that frame. Valid until the next Track call.
  const cv::Mat& last_frame_grey() const {
    static const cv::Mat kEmpty;
    return grey_pyramid_.empty() ? kEmpty : grey_pyramid_[0];
  }

 private:
  Tracker(const PinholeCamera& camera, const TrackerOptions& options);

  PinholeCamera camera_;
  TrackerOptions options_;
  bool has_rig_ = false;
  RigCalibration rig_;
  TrackingKeyframe keyframe_;
  bool has_keyframe_ = false;
  // The current frame, per level: CV_32FC3 interleaved (intensity, d/du, d/dv). Reused between calls.
  std::vector<cv::Mat> frame_pyramid_;
  std::vector<cv::Mat> grey_pyramid_;
  // The last keyframe image given to SetKeyframe and its pyramid (per level: grey level, the shading-
  // normalised grey level, its box mean, and with kPredictedShading the colour and each light's share
  // box-averaged), which depend on the image alone.
  struct KeyframeImageLevel {
    cv::Mat raw, grey, bright, colour;
    cv::Mat share_mean[3];
  };
  cv::Mat keyframe_image_;
  std::vector<KeyframeImageLevel> keyframe_image_levels_;
  cv::Mat local_mean_;                                      // scratch for the shading normalisation
  std::vector<internal::TrackerPointArrays> point_arrays_;  // per level
  // Per level, votes of the keyframe's pixels (camera_attached_min_votes): attached / moving, CV_8U.
  std::vector<cv::Mat> attached_votes_, moving_votes_;
  // Fills keyframe_image_ and keyframe_image_levels_ from a new keyframe image (tracker_keyframe.cc).
  void BuildKeyframeImage(const cv::Mat& rgb, bool predict, const Eigen::Matrix3f& demix,
                          const Eigen::RowVector3f& grey_of_light);
  void VoteCameraAttached(const Rigid3d& frame_from_keyframe, double a, double b);
  void UpdateKeep();
  internal::TrackerScratch scratch_;
};

}  // namespace prism
