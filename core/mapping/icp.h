// ICP registration of a keyframe cloud against the map (paper §3.4, §4.4), on PCL's
// IterativeClosestPoint (point-to-point, SVD), IterativeClosestPointWithNormals (point-to-plane,
// linear least squares) and GeneralizedIterativeClosestPoint (plane-to-plane, Segal et al. 2009).
// PCL stays inside icp.cc: no PCL type appears here.
//
// Typical use, one map snapshot and many keyframes:
//   PRISM_ASSIGN_OR_RETURN(IcpTarget target, IcpTarget::Create(map.ToPointCloud(), options));
//   Rigid3d world_from_keyframe;
//   PRISM_ASSIGN_OR_RETURN(IcpSummary s, AlignIcp(cloud_in_keyframe, target, world_from_keyframe_guess,
//                                                 options, &world_from_keyframe));
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <utility>

#include <Eigen/Core>

#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/util/status.h"

namespace prism {

enum class IcpMethod {
  // Minimises point distances (closed-form SVD step); needs no normals. Suits sparse scans: on dense
  // smooth surfaces it stalls, as nearest-neighbour residuals barely see tangential offsets (measured:
  // 0.8 degrees of a 3-degree motion left after 128 iterations on a 512x512 keyframe).
  kPointToPoint,
  // Minimises distances along the target normals (linearised least squares); needs target normals.
  // The method for keyframe clouds: exact on the synthetic tests, a few iterations per pass.
  kPointToPlane,
  // GICP: plane-to-plane with covariances from the k nearest neighbours of each cloud. With Debian's
  // PCL 1.13 (BFGS step, replaced by a Newton step in PCL 1.14) it stops short on dense keyframes
  // (measured: about half of a 3-degree rotation left) and is ~7x slower than point-to-plane.
  kGeneralized,
};

const char* IcpMethodName(IcpMethod method);

struct IcpOptions {
  // Error metric (see IcpMethod). Point-to-plane converges in a few iterations on dense clouds.
  IcpMethod method = IcpMethod::kPointToPlane;
  // Source points whose nearest target point is farther than this are not paired, metres, > 0.
  // Must exceed the expected misalignment (drift) of the guess.
  double max_correspondence_distance_m = 0.02;
  // When > 0, a second ICP pass from the first one's (converged) result pairs only points this close,
  // metres, in [0, max_correspondence_distance_m]. It drops pairs across occlusion boundaries and into
  // regions the target has not seen, which bias the first pass (measured on the bunny benchmark:
  // 0.86 mrad -> 0.13 mrad worst case). 0 = one pass.
  double refine_correspondence_distance_m = 0.005;
  // Cap on ICP iterations per pass, >= 1.
  int max_iterations = 30;
  // Convergence: PCL's transformation epsilon, >= 0. ICP stops when the last increment translates by
  // at most sqrt(eps) metres and rotates by at most acos(1 - eps) (PCL compares the squared
  // translation and 1 - cos). For kGeneralized it becomes GICP's translation epsilon sqrt(eps) m and
  // rotation epsilon sqrt(2 eps) rad, the same thresholds.
  double transformation_epsilon = 1e-10;
  // Convergence: stop when the mean squared correspondence distance changes by less than this fraction
  // between iterations; 0 disables it (PCL's default). >= 0. Ignored by kGeneralized.
  double euclidean_fitness_epsilon = 0.0;
  // Edge of the voxels the source is downsampled with before ICP (centroid per voxel), metres;
  // 0 = no downsampling. >= 0.
  double source_voxel_m = 0.0;
  // Random subset of at most this many (downsampled) source points used by ICP; 0 = all. >= 0.
  // Without downsampling the indices are drawn first and non-finite picks dropped (O(subset size)).
  // A dense 512x512 keyframe has ~2.5e5 points; 3000 constrain 6 DoF to well below 1e-3 (benchmark).
  int max_source_points = 3000;
  // Seed of the random subset: the same inputs and options give the same result.
  uint32_t seed = 1;
  // kGeneralized: neighbours per point covariance, in [3, 100].
  int gicp_k_neighbors = 20;

  Status Check() const;
};

struct IcpSummary {
  // True when a convergence criterion (transformation or fitness epsilon) stopped ICP (the last pass);
  // false when it ran out of iterations or found too few correspondences. The pose is returned either
  // way.
  bool converged = false;
  // PCL's fitness score at the result: mean squared distance from each used source point to its
  // nearest target point (no distance limit), m^2.
  double fitness_mean_sq_m2 = 0.0;
  // RMS distance of the inliers (nearest target point within max_correspondence_distance_m), metres.
  double inlier_rmse_m = 0.0;
  // Fraction of the used source points that are inliers, in [0, 1].
  double inlier_fraction = 0.0;
  int iterations = 0;  // both passes together
  // Source points ICP used (finite, after downsampling and subsampling).
  size_t source_points = 0;
};

// The target side of ICP for one map snapshot: the PCL cloud and its kd-tree (plus the GICP
// covariances for kGeneralized), built once and reused by every AlignIcp call against it.
// Immutable after Create; copies share the same data. AlignIcp only runs const kd-tree searches on
// it (the tree is never rebuilt), so several threads may align against one IcpTarget at once.
// Building one costs ~9 ms for a 1.3e5-point map on this machine (FLANN kd-tree): build it once per
// map snapshot, and keep the snapshot local (recent keyframes) as the map grows.
class IcpTarget {
 public:
  // INVALID_ARGUMENT when the cloud is inconsistent or has no finite point; for kPointToPlane when it
  // has no normals or no point with a valid normal (points without one, zero or non-finite, are left
  // out); for kGeneralized when it has fewer than gicp_k_neighbors finite points.
  static StatusOr<IcpTarget> Create(const PointCloud& target, const IcpOptions& options);

  // Points in the kd-tree.
  size_t size() const;
  // Points of the input left out (non-finite positions; missing normals for kPointToPlane).
  size_t dropped_points() const;
  IcpMethod method() const;
  int gicp_k_neighbors() const;

 private:
  struct Impl;
  explicit IcpTarget(std::shared_ptr<const Impl> impl) : impl_(std::move(impl)) {}
  friend StatusOr<IcpSummary> AlignIcp(const PointCloud&, const IcpTarget&, const Rigid3d&, const IcpOptions&,
                                       Rigid3d*);
  std::shared_ptr<const Impl> impl_;
};

// Aligns `source` to `target` starting from target_from_source_guess and writes the estimate to
// *target_from_source (also when not converged; see IcpSummary::converged). Only the source's
// positions are used. INVALID_ARGUMENT on bad options, an empty or inconsistent source, no finite
// source point, a target built for another method (or another gicp_k_neighbors), or for
// kGeneralized a source with fewer than gicp_k_neighbors points after subsampling;
// *target_from_source is then left unchanged.
StatusOr<IcpSummary> AlignIcp(const PointCloud& source, const IcpTarget& target,
                              const Rigid3d& target_from_source_guess, const IcpOptions& options,
                              Rigid3d* target_from_source);

// Same, building the IcpTarget for this call (use the overload above to reuse it).
StatusOr<IcpSummary> AlignIcp(const PointCloud& source, const PointCloud& target,
                              const Rigid3d& target_from_source_guess, const IcpOptions& options,
                              Rigid3d* target_from_source);

struct NormalEstimationOptions {
  // Neighbours fitted by the plane (PCA), including the point itself, in [3, 100].
  int k_neighbors = 10;
  // Neighbours farther than this are ignored, metres, > 0. Keeps planes from bridging depth gaps.
  double max_radius_m = 0.01;

  Status Check() const;
};

// Fills the missing normals of a cloud (paper: regions where photometric stereo gave no normal):
// each point whose normal is zero or non-finite (every point when the cloud has no normals) gets the
// normal of the plane through its nearest neighbours, oriented towards `viewpoint` (the camera
// centre, in the cloud's frame). Points with fewer than 3 neighbours within max_radius_m keep a zero
// normal. Returns the number of normals filled. INVALID_ARGUMENT on bad options or an inconsistent
// cloud.
StatusOr<size_t> FillMissingNormals(const Eigen::Vector3d& viewpoint, const NormalEstimationOptions& options,
                                    PointCloud* cloud);

}  // namespace prism
