// Windowed direct (photometric) bundle adjustment of the most recent keyframes, after DSO (Engel,
// Koltun, Cremers 2018), used by SlamSystem after each new keyframe.
//
// Why: frame-to-keyframe tracking and the small-baseline depth filter feed each other, and the scale
// drifts from keyframe to keyframe. Keyframes are several per cent of the scene depth apart
// (SlamOptions::keyframe_distance_fraction), so the same surface points seen in several keyframes
// constrain their relative poses far better than consecutive frames do.
//
// Each point is a pixel of a host keyframe with an inverse depth in the host's units; its residuals are
// the differences between the host's shading-normalised grey level (KeyframeDepth::NormalisedGrey) and
// each other keyframe's at the pixel it projects to (bilinear). Unknowns: the keyframe poses and every
// point's inverse depth; Levenberg-Marquardt with Huber weights, the points eliminated by the Schur
// complement (one unknown each). After a first solve, residuals above `outlier` are dropped and the
// problem is solved again.
//
// Gauge (7 degrees of freedom, monocular): the first keyframe is held fixed, and the second may not move
// along the line between the two camera centres (which fixes the scale).
//
// Accuracy limit: J still changes with the co-moving lights between keyframes, so even from the true poses
// and depths the adjustment moves the keyframes by a few per cent of their spacing.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

struct DirectBaPoint {
  int host = 0;             // index into DirectBaProblem::world_from_keyframe
  float u = 0, v = 0;       // pixel in the host
  float inverse_depth = 0;  // 1 / z in the host's units, > 0; in: initial value, out: adjusted
  float intensity = 0;      // the host's normalised grey level at (u, v)
  // With DirectBaRelit::mixed: this point's residuals are relit ones (else J ones). Ignored otherwise.
  bool relit = false;
  bool ok = true;  // out: kept at least one residual and a positive inverse depth
};

// The relit residual (optional): instead of the host's normalised grey level against the target's,
// the target's raw grey level against the one predicted from the rig. The host's colour c at the point
// gives rho n = S(K x_h)^-1 X^-1 c under a grey albedo (one-pixel photometric stereo: S's rows are each
// light's irradiance times its direction at the point, X the crosstalk, K the metres per world unit,
// x_h the point in the host's camera in world units), and the target sees the grey level of
// X max(0, S(K x_t) R rho n) (R: the host's camera to the target's). The co-moving lights' shading
// change between keyframes is then predicted instead of left in the residual. Points whose colour is
// saturated, lit by fewer than all three lights (min_band_fraction) or whose implied normal faces away
// from the camera are left out. The prediction's own dependence on the poses and depths is not
// differentiated (only the image's): at the solution the residuals are noise, so the minimum is the
// same.
struct DirectBaRelit {
  const RigCalibration* rig = nullptr;  // lights and crosstalk; null: the J residual
  // K, > 0. In: the start; out: the adjusted value when estimate_metres_per_world_unit.
  double metres_per_world_unit = 1.0;
  // Adjust log K with the poses and depths (the gauge still fixes the world's unit; K then says how many
  // metres it is). Else K is held.
  bool estimate_metres_per_world_unit = false;
  std::vector<cv::Mat> rgb;         // CV_8UC3 (RGB) per keyframe, the hosts' colours
  double min_band_fraction = 0.15;  // in [0, 1)
  // The albedo's colour (per light band, any scale, all > 0): rho = a * albedo_colour with a unknown per
  // point, so rho n a = S^-1 diag(albedo_colour)^-1 X^-1 c. (1, 1, 1): grey.
  Eigen::Vector3d albedo_colour = Eigen::Vector3d::Ones();
  // Mixed: both residuals in one problem. Points marked DirectBaPoint::relit take the relit residual
  // (against the raw grey level, the mean of `rgb`'s channels, computed here), the others the J one
  // (against grey_j, which then stays the normalised grey level). Each relit residual is multiplied by
  // relit_residual_scale (> 0) before the Huber weight and the outlier test, so its weight is that
  // squared: J pins the directions it sees well, and the relit residual the ones it barely sees (the
  // bas-relief direction of a sideways arc).
  bool mixed = false;
  double relit_residual_scale = 1.0;
};

// The raw grey level the relit residual compares: the mean of a CV_8UC3 image's channels, CV_32F.
cv::Mat MeanOfChannels(const cv::Mat& rgb);

struct DirectBaProblem {
  PinholeCamera camera;  // no distortion
  // world_from_keyframe; the scale is the keyframe's depth unit and is held fixed. In: initial values,
  // out: adjusted ([0] unchanged; see the gauge above).
  std::vector<Sim3d> world_from_keyframe;
  // CV_32F of the camera's size, one per keyframe: the normalised grey level J, or with `relit.rig` (and
  // not relit.mixed) the raw grey level (mean of the channels).
  std::vector<cv::Mat> grey_j;
  std::vector<DirectBaPoint> points;
  DirectBaRelit relit;
};

struct DirectBaOptions {
  // Pyramid levels, coarse to fine (one solve per coarser level, two at full resolution), in [1, 5]:
  // more = wider convergence basin, biased result (SlamSystem's starts are close: 1).
  int pyramid_levels = 1;
  // Levenberg-Marquardt iterations per solve, in [1, 100].
  int max_iterations = 10;
  // Huber threshold on the grey-level residual, > 0.
  double huber = 8.0;
  // Residuals above this are dropped after the first solve, > huber.
  double outlier = 30.0;
  // Projections closer than this to the image border are skipped, pixels, >= 2.
  int border_px = 3;
  // A solve stops when the cost decreases by less than this fraction, > 0.
  double function_tolerance = 1e-5;
  // Gradient-dependent residual scale c, grey levels of J per pixel, >= 0 (0 = off): a residual whose host
  // gradient is g is scaled by c / sqrt(c^2 + |g|^2) before the Huber weight and the outlier test (DSO's
  // weight: a small misalignment moves a strong edge's residual most); lower c = strong edges count less.
  double gradient_weight_c = 0.0;
  // LM damping by the gain ratio rho (Nielsen's rule, as in Ceres): lambda x max(1/3, 1 - (2 rho - 1)^3) after an
  // accepted step, x nu (doubling) after a rejected one; false: / 3 and x 5. True = fewer rejected steps (evaluations).
  bool gain_ratio_damping = false;
  // Linearise from the cost evaluation's kept projections and samples: the same bits, fewer image reads, about
  // 2 x 80 bytes per residual more memory. Not with the relit residual (DirectBaRelit), which reads its own.
  bool linearise_from_evaluation = true;
  Status Check() const;
};

struct DirectBaSummary {
  int iterations = 0;
  int evaluations = 0;                    // cost evaluations (the initial one, and one per step tried, accepted or not)
  int residuals = 0;                      // used in the final solve
  long long image_samples = 0;            // residuals whose image value was read (evaluations and linearisations)
  double initial_rms = 0, final_rms = 0;  // grey levels, over the residuals used
};

// Points of one keyframe for the adjustment: in each cell x cell block (4 pixels from the border), the
// pixel with the strongest squared gradient of grey_j (central differences) above min_gradient_squared
// among those with inverse_depth > 0 that usable(x, y) accepts. grey_j and inverse_depth: CV_32F of the
// same size.
template <typename Usable>
void SelectCellPoints(const cv::Mat& grey_j, const cv::Mat& inverse_depth, int host, int cell,
                      float min_gradient_squared, Usable usable, std::vector<DirectBaPoint>* points) {
  for (int cy = 4; cy + cell <= grey_j.rows - 4; cy += cell) {
    for (int cx = 4; cx + cell <= grey_j.cols - 4; cx += cell) {
      int bx = -1, by = -1;
      float best = min_gradient_squared;
      for (int y = cy; y < cy + cell; ++y) {
        for (int x = cx; x < cx + cell; ++x) {
          if (!(inverse_depth.at<float>(y, x) > 0) || !usable(x, y)) continue;
          const float gx = 0.5f * (grey_j.at<float>(y, x + 1) - grey_j.at<float>(y, x - 1));
          const float gy = 0.5f * (grey_j.at<float>(y + 1, x) - grey_j.at<float>(y - 1, x));
          if (gx * gx + gy * gy > best) best = gx * gx + gy * gy, bx = x, by = y;
        }
      }
      if (bx < 0) continue;
      DirectBaPoint p;
      p.host = host;
      p.u = static_cast<float>(bx);
      p.v = static_cast<float>(by);
      p.inverse_depth = inverse_depth.at<float>(by, bx);
      p.intensity = grey_j.at<float>(by, bx);
      points->push_back(p);
    }
  }
}

// The adjustment's parameters of a keyframe pose (world_from_keyframe with rotation R, centre c): a right
// rotation perturbation R exp(w) and the centre, (w, c). For a point x of a host keyframe (x = c_h +
// s_h R_h q, q fixed in the host's camera) seen in a target keyframe at p = R_t^T (x - c_t), the derivative
// of p with respect to the host's parameters is the one with respect to the target's times this matrix:
// d p / d host = (d p / d target) A. So every residual of a (host, target) pair is accumulated in the
// target's parameters alone, and A maps the pair's sums to the host's.
Eigen::Matrix<double, 6, 6> DirectBaHostFromTarget(const Eigen::Matrix3d& host_rotation,
                                                   const Eigen::Vector3d& host_centre,
                                                   const Eigen::Matrix3d& target_rotation,
                                                   const Eigen::Vector3d& target_centre);

// The fraction of a keyframe's depth that keyframe b sees: of the pixels of inverse_depth (CV_32F, the
// camera's size; every step-th pixel in each direction) with an inverse depth > 0, in keyframe a's depth
// units, those that project in front of camera b and inside its image. 1 when no pixel has a depth.
double DepthOverlapFraction(const PinholeCamera& camera, const cv::Mat& inverse_depth, const Sim3d& world_from_a,
                            const Sim3d& world_from_b, int step);

// Fails on invalid options, fewer than 2 keyframes, a grey image of the wrong size or type, a point with
// an out-of-range host or a non-positive inverse depth, or a camera with distortion.
//
// With a pool of more than one thread the residuals are linearised and evaluated target by target in
// parallel (the relit residual too, and its points' implied normals). Every sum is still formed in the
// one-thread order (each target's terms are kept and added target by target afterwards), so the result
// is the same to the last bit with or without the pool.
StatusOr<DirectBaSummary> AdjustKeyframeWindowDirect(const DirectBaOptions& options, DirectBaProblem* problem,
                                                     ThreadPool* pool = nullptr);

}  // namespace prism
