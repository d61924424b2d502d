// Fusion of the SLAM positions and the photometric-stereo normals of one keyframe into a dense depth
// map (paper §3.4; Nehab, Rusinkiewicz, Davis, Ramamoorthi, "Efficiently combining positions and
// normals for precise 3D geometry", SIGGRAPH 2005), and the keyframe's dense cloud in the world.
//
// Unknowns: the depth Z (z in the camera frame, SLAM units) of every pixel that has a normal or a
// SLAM depth. P(u) = Z(u) r(u) with r the pixel's ray at z = 1. Depth rather than inverse depth
// because then every row below is linear and measures a metric quantity (Nehab's choice): the
// tangent condition n . (P_j - P_i) = 0 is linear in Z, and the position residual is a distance along
// the ray, which is what the depth error (and the cloud) is judged by. The SLAM inverse depth and its
// variance are converted per sample (Zm = 1 / rho, relative variance var_rho / rho^2).
//
// Least-squares rows, each divided by the prior depth Zp of its pixel(s) so that every residual is
// relative (dimensionless) and the system does not depend on the unknown SLAM scale:
//   tangent   sqrt(c_ij) cos(s_ij) n_ij . (Z_j r_j - Z_i r_i) / Zp_ij   for 4-neighbours i, j,
//             n_ij the normalised mean of the two normals, s_ij its slant against the ray, c_ij the
//             mean confidence. The cos(s) factor makes the residual the angle between normal and
//             tangent, whose noise does not grow at grazing angles (without it a grazing surface's
//             normals, whose slope error grows like 1 / cos^2, would dominate its SLAM depth);
//   position  sqrt(w_i) (Z_i - Zm_i) / Zp_i                   where SLAM depth Zm exists,
//             w_i = position_weight / rho * min(10, median SLAM variance / variance_i),
//             rho = (unknowns with SLAM depth) / (unknowns), variances relative (of Z / Zm);
//   prior     sqrt(prior_weight) (Z_i - Zp_i) / Zp_i          on every unknown (keeps regions without
//             SLAM depth from collapsing to Z = 0; they follow the densified prior at low frequencies).
// Measured in pixel footprints (u = Z f / Zp, f the focal length in pixels), a fronto-parallel tangent
// row is (du/dx - slope given by the normal) / f and a position row (u - u_m) / f: the weights are
// those of a screened Poisson problem |grad u - g|^2 + position_weight |u - u_m|^2 per pixel, so
// position_weight is a screening strength in 1/pixel^2 that does not depend on the focal length,
// the image size, the density of SLAM depth or the SLAM scale. Depth detail shorter than about
// 2 pi / sqrt(position_weight) pixels comes from the normals, longer from the SLAM depth.
//
// Depth discontinuities: no tangent row joins two pixels across a crease, an occluding contour or a
// step that the SLAM depth (or the previous pass) shows but the normals do not predict (see the
// options). A connected region left without SLAM depth is dropped when small, else held by the prior.
//
// Solver: the normal equations form a symmetric 5-point stencil, solved by conjugate gradients in
// float, matrix-free (three stencil coefficients per pixel, no sparse matrix), preconditioned by one
// multigrid V-cycle (Galerkin coarse grids of 2x2 aggregates, red-black Gauss-Seidel), parallel over
// row blocks, warm-started from the prior, a given initial depth or the previous pass. Reductions are
// summed in a fixed order, so the result does not depend on the number of threads.
//
// Passes: pass 1 solves with the input normals. Each later pass (a) also cuts the pairs whose depth
// step in the previous solution contradicts their normals (joins across depth edges that the a-priori
// tests missed) and (b) with normal_correction, uses Nehab's corrected normals: the input normals'
// low frequencies (edge-aware low-pass of correction_sigma_px) replaced by those of the previous fused
// surface, by rotating each normal with the rotation taking its low-passed direction to the fused
// surface's, and (c) then weights the positions by corrected_pass_position_scale. Then it solves
// again, warm-started.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/io/inverse_depth.h"
#include "core/photometric/depth_prior.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

enum class FusionPreconditioner {
  kJacobi,     // diagonal: cheap iterations, but their number grows with the image size
  kMultigrid,  // one symmetric multigrid V-cycle per iteration
};

struct FusionOptions {
  // Screening strength of the position (SLAM depth) term, 1/pixel^2 (see the file comment): the
  // weight of a median-variance SLAM sample is position_weight / rho, rho the fraction of unknowns
  // with SLAM depth. Larger = trust the SLAM depth more (worse normals), smaller = keep more normal
  // detail. In [0, 10]; 0 only with prior_weight > 0. Default from the sweep in fusion_sweep.cc.
  double position_weight = 3e-4;
  // Weight of the tie of every unknown to the densified prior depth, same units as position_weight
  // (not divided by rho). Only there to make regions without SLAM depth well posed; in [0, 1].
  double prior_weight = 1e-5;
  // Preconditioner of the conjugate gradients.
  FusionPreconditioner preconditioner = FusionPreconditioner::kMultigrid;
  // Conjugate-gradient iterations per pass, in [1, 100000].
  int max_solver_iterations = 200;
  // Stop when |residual| <= solver_tolerance * |right-hand side| (normal equations), in (0, 1).
  double solver_tolerance = 1e-3;
  // Depth discontinuities: no tangent row joins neighbours i, j when any of these holds.
  // (a) Both have SLAM depth and its step differs from the step the normals predict by more than
  //     this (relative): |log(Zm_j / Zm_i) - log((n . r_i) / (n . r_j))| > max_depth_jump; in passes
  //     after the first also when the previous pass's depth step differs this much. In (0, 10].
  double max_depth_jump = 0.05;
  // (b) Crease: the two normals differ by more than this angle, degrees, in (0, 180].
  double max_normal_angle_deg = 30.0;
  // (c) Occluding contour: one normal is slanted more than contour_slant_deg from the viewing ray,
  //     points (in the image) towards the other pixel, and the other's slant is at least
  //     contour_slant_drop_deg smaller (a smooth surface only gets steeper towards its contour).
  //     Degrees, in (0, 90] and [0, 90].
  double contour_slant_deg = 65.0;
  double contour_slant_drop_deg = 10.0;
  // (d) The mean normal is slanted more than this from the ray (the row would be ill-conditioned),
  //     degrees, in (0, 90].
  double max_slant_deg = 85.0;
  // A connected region (over the tangent rows kept) without SLAM depth that has fewer pixels than
  // this is not solved for (depth 0): such slivers along depth edges would only get the blurred
  // prior. Larger regions are solved with the prior tie. >= 1 (1 = solve every region).
  int min_unsupported_region_px = 400;
  // Replace the low frequencies of the input normals by those of the fused surface between passes.
  bool normal_correction = true;
  // Scale of the (edge-aware, exponential) low-pass filter of the normal correction, pixels, in
  // [1, 200]. 8 from `fusion_sweep --ps --settings default --weights 3e-4 --sigma S`, S in 4..16:
  // against 16 it cut the fused depth error on the bunny 5.2 -> 2.9 mm, torus 2.4 -> 2.1 mm,
  // DiLiGenT ball 48 -> 47 mm, and raised it on the multi-coloured sphere 3.5 -> 4.1 mm.
  double correction_sigma_px = 8.0;
  // position_weight is multiplied by this in the passes that solve with corrected normals, in (0, 1].
  // Those normals already carry the SLAM depth's low frequencies (from the previous pass), so full
  // position rows there mostly add the samples' per-pixel noise: on grazing parts of a surface, where
  // a tangent row constrains the depth along the ray only like cos^2(slant), isolated noisy samples
  // dent the surface (uniform sphere at slant 50-65 deg: fused normals 6.8 deg, PS 0.9-1.2 deg).
  // 0.5 from `fusion_sweep --ps --settings default` and prism-fuse on the dense-stage presets: fused
  // normals on the same pixels against 1.0: uniform sphere 1.22 -> 0.98 deg, multi-coloured sphere
  // 3.05 -> 2.85, bunny 5.11 -> 4.88; fused depth 0.81 -> 0.76, 1.82 -> 1.86, 1.89 -> 2.05 mm.
  double corrected_pass_position_scale = 0.5;
  // Solve passes (see the file comment), in [1, 10].
  int passes = 2;
  // Row blocks processed concurrently on the given ThreadPool (0 = all of the pool's threads).
  // Without a pool everything runs on the calling thread. In [0, 256].
  int num_threads = 0;
  // Densification of the SLAM depth when no prior is given.
  DensifyOptions densify;

  Status Check() const;
};

struct FusionInput {
  PinholeCamera camera;
  // CV_32FC3, camera frame, unit length, facing the camera; (0,0,0) = no normal.
  cv::Mat normals;
  // CV_32F in [0, 1], weight of each normal (0 = no normal); empty = all 1.
  cv::Mat confidence;
  // The semi-dense SLAM inverse depth in this keyframe's view (SLAM units) and its variance
  // (CV_32F both; see ProjectCloudToKeyframe to get it from the SLAM's world cloud).
  InverseDepthMap semi_dense;
  // CV_32F densified inverse depth (SLAM units, 0 = none): the prior of the tie rows and the start
  // of the solve. Empty = computed here with DensifyInverseDepth(semi_dense, options.densify).
  cv::Mat prior_inverse_depth;
  // CV_32F depth (SLAM units, 0 = none) to warm-start from, e.g. the previous keyframe's fused depth
  // warped into this view; empty = start from the prior.
  cv::Mat initial_depth;
  // CV_8U, 0 = exclude the pixel; empty = every pixel.
  cv::Mat valid_mask;
};

struct FusionResult {
  cv::Mat depth;    // CV_32F, SLAM units (z), 0 = none
  cv::Mat normals;  // CV_32FC3, normals of the fused surface (camera frame, facing it); 0 = none
  // CV_32FC3, the input normals after the last normal correction (equal to the input without one).
  cv::Mat corrected_normals;
  int iterations = 0;            // conjugate-gradient iterations, summed over the passes
  double residual = 0.0;         // last pass: |residual| / |right-hand side| at the end
  bool converged = false;        // last pass reached solver_tolerance
  int passes = 0;                // passes run
  int unknowns = 0;              // pixels solved for (last pass)
  int position_rows = 0;         // pixels with SLAM depth among them
  int tangent_rows = 0;          // tangent rows used (last pass)
  int dropped_tangent_rows = 0;  // neighbour pairs cut as depth discontinuities (last pass)
  std::vector<int> iterations_per_pass;
};

// Fuses a keyframe's SLAM depth and normals. Keeps its buffers between calls, so a long-lived
// instance does per-keyframe work without allocating (but the result's images). Not thread-safe:
// one instance per thread; the pool may be shared.
class DepthNormalFusion {
 public:
  explicit DepthNormalFusion(const FusionOptions& options = FusionOptions(), ThreadPool* pool = nullptr);
  ~DepthNormalFusion();
  DepthNormalFusion(const DepthNormalFusion&) = delete;
  DepthNormalFusion& operator=(const DepthNormalFusion&) = delete;

  // INVALID_ARGUMENT on bad options, a bad camera or images of the wrong type or size;
  // FAILED_PRECONDITION when there is no SLAM depth at all.
  StatusOr<FusionResult> Fuse(const FusionInput& input);

 private:
  struct Workspace;
  FusionOptions options_;
  ThreadPool* pool_;
  std::unique_ptr<Workspace> workspace_;
};

// One-shot DepthNormalFusion(options, pool).Fuse(input).
StatusOr<FusionResult> FuseDepthAndNormals(const FusionInput& input, const FusionOptions& options,
                                           ThreadPool* pool = nullptr);

// Back-projects a depth map (SLAM units, 0 = none) of the keyframe into the world frame:
// point_in_world = world_from_keyframe * (Z r(u)) (the Sim3 carries the SLAM scale), normals rotated
// by its rotation, colours from `rgb` (CV_8UC3 RGB, may be empty), confidences from `confidence`
// (CV_32F, may be empty = 1). Every `stride`-th pixel in x and y where depth > 0, mask != 0 (CV_8U,
// may be empty) and, when normals are given (CV_32FC3, may be empty), the normal is non-zero.
// INVALID_ARGUMENT on wrong types or sizes, stride < 1 or a non-positive scale.
StatusOr<PointCloud> DepthToCloud(const cv::Mat& depth, const cv::Mat& normals, const cv::Mat& rgb,
                                  const PinholeCamera& camera, const Sim3d& world_from_keyframe, int stride = 1,
                                  const cv::Mat& mask = cv::Mat(), const cv::Mat& confidence = cv::Mat());

// Pixels safe to put in a map: depth > 0 and no 8-neighbour whose depth differs by more than
// max_relative_step (relative). Pixels along depth discontinuities ("flying pixels", where a
// surface fit bridges a silhouette) are the least reliable of a dense depth map. CV_8U, 255 = keep.
cv::Mat DepthEdgeFreeMask(const cv::Mat& depth, double max_relative_step);

// The SLAM's semi-dense cloud (world frame) seen from a keyframe: each point is mapped by
// keyframe_from_world (Sim3, into the keyframe's camera frame in SLAM units), projected, and the
// nearest point per pixel kept as inverse depth. Variance = 1 / confidence when the cloud has
// confidences (read as inverse variances of inverse depth), else default_variance. INVALID_ARGUMENT
// on a bad camera, an inconsistent cloud or default_variance <= 0.
StatusOr<InverseDepthMap> ProjectCloudToKeyframe(const PointCloud& cloud_in_world, const Sim3d& keyframe_from_world,
                                                 const PinholeCamera& camera, double default_variance);

namespace internal {

// The normal equations of one pass as a symmetric 5-point stencil over the image (exposed for the
// direct-solver test oracle). Pixels that are not unknowns have diag = 1, rhs = 0 and no coupling.
struct FusionStencil {
  int width = 0;
  int height = 0;
  std::vector<float> diag;       // A(i, i)
  std::vector<float> right;      // A(i, i + 1), 0 in the last column and where the pair is cut
  std::vector<float> down;       // A(i, i + width), 0 in the last row and where the pair is cut
  std::vector<float> rhs;        // b(i)
  std::vector<uint8_t> unknown;  // 1 where pixel i is solved for
};

// The first pass's stencil for validated inputs, the normals to use and the prior depth (CV_32F,
// SLAM units).
FusionStencil BuildFusionStencil(const FusionInput& input, const cv::Mat& normals, const cv::Mat& prior_depth,
                                 const FusionOptions& options);

struct CgSummary {
  int iterations = 0;
  double relative_residual = 0.0;
  bool converged = false;
};

// Preconditioned conjugate gradients on the stencil, on the calling thread, starting from x (size
// width * height).
CgSummary SolveStencilCg(const FusionStencil& stencil, int max_iterations, double tolerance,
                         FusionPreconditioner preconditioner, std::vector<float>* x);

// Nehab's normal correction: rotates each input normal by the rotation taking its low-passed
// direction to the low-passed direction of `reference` (both filtered over the pixels where both
// exist). The low-pass is an edge-aware exponential filter of scale sigma_px along the tangent rows of
// `links` when given, else a Gaussian. Pixels without a usable low-pass keep their normal.
cv::Mat CorrectNormals(const cv::Mat& input, const cv::Mat& reference, double sigma_px,
                       const FusionStencil* links = nullptr);

}  // namespace internal
}  // namespace prism
