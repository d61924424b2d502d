// Synthetic keyframes for the fusion tests, the weight sweep and the benchmark: a prism-synth frame with
// its ground truth, simulated semi-dense SLAM depth (unknown scale) and its densified prior, normals
// with a controlled error, and the scores the bars are stated in. Not part of prism_fusion: it lives
// in prism_fusion_testing, which links the renderer and the metrics.
#pragma once

#include <cstdint>
#include <string>

#include <opencv2/core.hpp>

#include "core/fusion/fusion.h"
#include "core/io/calibration_io.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/semidense.h"
#include "core/util/status.h"

namespace prism {

struct FusionTestFrameOptions {
  int width = 512;   // pixels
  int height = 512;  // pixels
  // The keyframe is frame `frame_index` of a `frames`-frame trajectory of the preset.
  int frames = 60;
  int frame_index = 40;
  // Semi-dense simulation; its `scale` is the SLAM unit in metres (depth_slam = depth_m / scale).
  synth::SemiDenseOptions semi_dense = DefaultSemiDense();
  uint32_t seed = 1;  // preset and render noise

  static synth::SemiDenseOptions DefaultSemiDense() {
    synth::SemiDenseOptions o;
    o.scale = 0.37;
    return o;
  }
};

struct FusionTestFrame {
  std::string preset;
  RigCalibration rig;
  Rigid3d world_from_camera;
  synth::RenderedFrame frame;   // ground truth: depth (metres), normals, mask (255 object, 64 ground)
  double slam_scale = 1.0;      // metres per SLAM unit
  InverseDepthMap semi_dense;   // SLAM units
  cv::Mat prior_inverse_depth;  // DensifyInverseDepth(semi_dense, DensifyOptions())
};

// NOT_FOUND when the preset needs a mesh that is missing (callers skip), other errors as MakePreset.
StatusOr<FusionTestFrame> MakeFusionTestFrame(const std::string& preset, const FusionTestFrameOptions& options);

// Ground-truth normals with a realistic error: each normal tilted by a seeded Gaussian per-pixel noise
// (RMS tilt noise_deg) plus a smooth bias field (tilt up to bias_deg, varying over bias_wavelength_px),
// the kind of low-frequency error photometric stereo has (lighting and albedo model errors).
struct NormalNoiseOptions {
  double noise_deg = 4.0;
  double bias_deg = 4.0;
  double bias_wavelength_px = 256.0;
  uint32_t seed = 7;
};
cv::Mat PerturbNormals(const cv::Mat& normals, const NormalNoiseOptions& options);

// The quantities of the fusion bars on the object's pixels (mask 255), depths compared in metres with
// the known SLAM scale (semi-dense input and fused output aligned the same way).
struct FusionScore {
  double input_depth_rmse_m = 0;                 // semi-dense SLAM depth where it exists
  double fused_depth_rmse_m = 0;                 // fused depth where it exists
  double fused_depth_rmse_median_aligned_m = 0;  // same with median-ratio alignment instead
  double input_depth_rmse_median_aligned_m = 0;
  double coverage = 0;  // object pixels with fused depth / object pixels
  double input_normal_median_deg = 0;
  double fused_normal_median_deg = 0;
  double corrected_normal_median_deg = 0;  // the input normals after Nehab's correction
  double input_normal_mean_deg = 0;
  double fused_normal_mean_deg = 0;
};
FusionScore ScoreFusion(const FusionTestFrame& frame, const cv::Mat& input_normals, const FusionResult& result);

// Real photometric-stereo normals: DiLiGenT "ball" (../shared/data/diligent-ball): three real images
// (lights 9, 24, 85, one per colour channel), Lambertian colour PS with its 3x3 lighting matrix fitted
// to a seeded random 2% of the ground-truth normals (standing in for the SLAM prior). The geometry is
// a sphere fitted to the mask, seen by a pinhole camera with focal length focal_px at the image
// centre; its depth is the ground truth, SLAM depth is simulated from it and the 8-bit image as for
// the synthetic frames (scale 1, noise scaled to the same size in pixel footprints). frame.normals holds DiLiGenT's
// ground-truth normals (camera frame). NOT_FOUND when the data is absent.
struct DiligentBallFrame {
  FusionTestFrame frame;
  cv::Mat ps_normals;                  // CV_32FC3, camera frame, (0,0,0) outside the mask
  double sphere_vs_gt_median_deg = 0;  // the fitted sphere's normals against the ground truth
};
StatusOr<DiligentBallFrame> MakeDiligentBallFrame(const std::string& dir, double focal_px = 3800.0);

// The FusionInput of a test frame with the given normals (confidence 1).
FusionInput MakeFusionInput(const FusionTestFrame& frame, const cv::Mat& normals);

}  // namespace prism
