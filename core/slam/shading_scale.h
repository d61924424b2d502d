// Metric scale of monocular depth from the lights that move with the camera.
//
// A monocular SLAM's depth has an arbitrary unit that drifts from keyframe to keyframe. The rig's three
// point lights, though, sit at known places in metres on the camera (about 0.2 m from the lens), and a
// surface point's shading between two views depends on where the point is relative to them in metres:
// the irradiance falls with the square of the distance and the light directions turn. So the change of
// the shading between a keyframe and a frame tracked on it tells the metres per depth unit.
//
// Model (Lambertian, point lights, the rig's crosstalk X; see core/synth/renderer.cc): a keyframe pixel
// with colour c and a point x (depth units) at k metres per unit has demixed bands s = X^-1 c =
// diag(rho) S(k x) n, where S(p)'s rows are E_l(p) L_l(p)^T (irradiance times the unit direction to
// light l). With a grey albedo (rho the same in every band) the pixel's own colour gives rho n =
// S(k x)^-1 s (one-pixel photometric stereo), and the frame at frame_from_keyframe (R, t) sees
//   c' = X max(0, S(k (R x + t)) R rho n)   at the projection of R x + t.
// The grey residual (mean of the channels) is minimised over log k and each frame's pose, jointly
// (Levenberg-Marquardt, Huber weights, outliers cut), from the best k of a coarse scan.
//
// Measured against prism-synth ground truth (true depth in arbitrary units, true poses, one frame 8
// frames after the keyframe; shading_scale_test): k within a few % on grey-albedo scenes (uniform and
// textured objects on a textured floor), from starts 2x off. Coloured albedo breaks the one-pixel
// photometric stereo (the multi-coloured presets come out 20-30% low), so the estimate is only as good
// as the grey-albedo assumption; `grey_albedo_fraction` in the result is a hint, not a guarantee.
#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/util/status.h"

namespace prism {

struct ShadingScaleOptions {
  // One point per cell x cell block of the keyframe: the strongest grey gradient among the usable
  // pixels, in [1, 64].
  int cell_px = 6;
  // Minimum grey gradient (central differences, grey levels per pixel) of a point, >= 0. Flat points
  // carry the shading change too, but the pose needs gradients.
  double min_gradient = 2.0;
  // Minimum grey level of a point (the dark room's dim pixels are mostly noise), in [0, 255].
  double min_level = 20.0;
  // Pixels with a channel at or above this are saturated and not used, in (0, 255].
  double saturation_level = 250.0;
  // A point's weakest demixed band must be at least this fraction of its strongest (else it is in one
  // light's shadow, which the model does not predict), in [0, 1).
  double min_band_fraction = 0.15;
  // The implied normal (rho n normalised) must face the camera: cosine with the direction to the camera
  // at least this, in [-1, 1).
  double min_view_cosine = 0.1;
  // Coarse scan of k before the joint refinement: this many values, log-spaced over [k0 / f, k0 * f]
  // with k0 = initial_metres_per_unit and f = scan_factor; >= 1 (1 = start at k0), f > 1.
  int scan_steps = 25;
  double scan_factor = 8.0;
  double initial_metres_per_unit = 1.0;  // > 0
  // Levenberg-Marquardt iterations, in [1, 200].
  int max_iterations = 40;
  // Huber threshold and outlier cut in units of the residuals' robust standard deviation (MAD at the
  // start), > 0 and cut > huber.
  double huber_sigmas = 2.0;
  double outlier_sigmas = 5.0;
  // Refine each frame's pose jointly (else only k moves).
  bool refine_poses = true;
  // Projections closer than this to the image border are skipped, pixels, >= 2.
  int border_px = 3;
  // Minimum points kept for a result, >= 10.
  int min_points = 200;

  Status Check() const;
};

struct ShadingScaleFrame {
  cv::Mat rgb;                  // CV_8UC3 (RGB), the keyframe's size
  Rigid3d frame_from_keyframe;  // in the keyframe's depth units
};

struct ShadingScaleResult {
  double metres_per_unit = 0;
  // Standard deviation of log(metres_per_unit) from the final normal equations (residual sigma times
  // the inverse Hessian's diagonal); a statistical bound only: it does not see model errors.
  double log_sigma = 0;
  std::vector<Rigid3d> frame_from_keyframe;  // refined (or as given with refine_poses = false)
  int points = 0;                            // keyframe points used
  int residuals = 0;                         // inlier residuals at the end
  double residual_sigma = 0;                 // robust sigma at the start of the refinement, grey levels
  double final_rms = 0;                      // RMS of the inlier residuals at the end, grey levels
  int iterations = 0;
  // Fraction of the candidate pixels whose implied normal passed the view test: near 1 on grey albedo;
  // strongly coloured albedo turns many implied normals away from the camera.
  double grey_albedo_fraction = 0;
};

// keyframe_rgb: CV_8UC3 (RGB); keyframe_inverse_depth: CV_32F of the same size, 0 = none, in 1 / depth
// unit; rig: the camera (no distortion) and the lights and crosstalk. INVALID_ARGUMENT on bad options,
// sizes or types, no frames, or a camera with distortion; FAILED_PRECONDITION when fewer than
// options.min_points points are usable or the refinement has no inliers.
StatusOr<ShadingScaleResult> EstimateShadingScale(const RigCalibration& rig, const cv::Mat& keyframe_rgb,
                                                  const cv::Mat& keyframe_inverse_depth,
                                                  const std::vector<ShadingScaleFrame>& frames,
                                                  const ShadingScaleOptions& options);

}  // namespace prism
