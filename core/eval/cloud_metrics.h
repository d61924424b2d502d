// Reconstruction quality of a point cloud against ground-truth surface samples, as in the Tanks and
// Temples / DTU style benchmarks:
//   accuracy     distance from each reconstructed point to the nearest ground-truth sample
//   precision    fraction of reconstructed points within tau of the ground truth
//   completeness fraction of ground-truth samples within tau of the reconstruction
//   F-score      harmonic mean of precision and completeness at tau
// Ground-truth samples stand in for the surface: keep their spacing well below tau (default tau / 4),
// then distances to the samples exceed distances to the surface by at most ~spacing * sqrt(3) / 2.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/rigid3.h"
#include "core/io/sequence.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"

namespace prism {

struct CloudEvalOptions {
  // Distance threshold for precision, completeness and F-score, metres. In (0, inf).
  double tau_m = 0.005;
  Status Check() const;
};

struct CloudMetrics {
  double tau_m = 0.0;
  size_t points = 0;             // reconstructed points evaluated (finite ones)
  size_t non_finite_points = 0;  // reconstructed points skipped because a coordinate is NaN/inf
  size_t gt_samples = 0;
  double accuracy_mean_m = 0.0;  // mean distance reconstruction -> ground truth
  double accuracy_median_m = 0.0;
  double precision = 0.0;     // in [0, 1]
  double completeness = 0.0;  // in [0, 1]
  double fscore = 0.0;        // 2 P C / (P + C), 0 when both are 0
};

// INVALID_ARGUMENT when either set is empty (after dropping non-finite reconstructed points), a
// ground-truth sample is not finite, or coordinates are too large for tau (|x| / tau > 1e12).
// The nearest-neighbour queries run on `pool` when given (inline otherwise).
StatusOr<CloudMetrics> EvaluateCloud(const std::vector<Eigen::Vector3f>& reconstruction,
                                     const std::vector<Eigen::Vector3f>& gt_samples, const CloudEvalOptions& options,
                                     ThreadPool* pool = nullptr);

// Replaces the points in each cubic voxel of the given size by their centroid. Output order follows
// the first point of each voxel (deterministic). voxel_size_m <= 0 returns the input unchanged.
// Non-finite points are dropped.
std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_size_m);

struct SurfaceSamplingOptions {
  // Back-project every k-th frame (0, k, 2k, ...). >= 1.
  int frame_step = 10;
  // Keep only object pixels (mask == kMaskObject); the sampled frames then need masks.
  bool object_only = false;
  // Voxel-downsampling spacing of the samples, metres; 0 keeps every back-projected pixel. >= 0.
  // The default is tau / 4 for the default tau of 5 mm.
  double voxel_size_m = 0.00125;
  Status Check() const;
};

struct SurfaceSamples {
  std::vector<Eigen::Vector3f> points_in_world;
  size_t frames_used = 0;
};

// Ground-truth surface samples of a sequence: the ground-truth depth of every frame_step-th frame,
// back-projected with the calibration's camera and the frame's ground-truth pose (world_from_camera),
// then voxel-downsampled. Frames without depth, pose (or mask, with object_only) are skipped.
// FAILED_PRECONDITION without calibration or when no frame contributes a point; image read errors pass
// through.
StatusOr<SurfaceSamples> SampleGroundTruthSurface(const Sequence& sequence, const SurfaceSamplingOptions& options);

// Axis-aligned bounds of the back-projected points SampleGroundTruthSurface would use (before
// downsampling; options.voxel_size_m is ignored). Same errors.
StatusOr<Eigen::AlignedBox3d> GroundTruthSurfaceBounds(const Sequence& sequence, const SurfaceSamplingOptions& options);

struct PixelCoverage {
  size_t object_pixels = 0;   // pixels with mask == kMaskObject
  size_t covered_pixels = 0;  // of those, pixels hit by at least one projected point
  double fraction = 0.0;      // covered / object, 0 when the mask has no object pixel
};

// Projects the points (world frame) into the camera at world_from_camera, rounding to the nearest pixel,
// and counts the object pixels hit. Occlusion is ignored (a point behind the visible surface counts).
// Points behind the camera or outside the image's field of view are skipped. INVALID_ARGUMENT when the
// mask is not CV_8UC1 of the camera's size or the camera is invalid.
StatusOr<PixelCoverage> ObjectPixelCoverage(const std::vector<Eigen::Vector3f>& points_in_world,
                                            const PinholeCamera& camera, const Rigid3d& world_from_camera,
                                            const cv::Mat& mask);

}  // namespace prism

namespace prism {

// For object-only evaluation of a scene reconstruction: the indices of the points that are seen on
// the object, i.e. that project onto an object pixel (mask == kMaskObject) of at least one sampled
// frame (every options.frame_step-th) without lying more than `behind_margin_m` behind the
// ground-truth surface there (a point behind it is hidden in that frame, e.g. floor behind the
// object). Points floating in front of the object are kept, so they still count against precision.
// FAILED_PRECONDITION without calibration, or when no sampled frame has depth, pose and mask.
StatusOr<std::vector<size_t>> SelectPointsSeenOnObject(const Sequence& sequence,
                                                       const std::vector<Eigen::Vector3f>& points_in_world,
                                                       const SurfaceSamplingOptions& options, double behind_margin_m);

}  // namespace prism
