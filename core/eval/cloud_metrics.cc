#include "core/eval/cloud_metrics.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <sstream>
#include <unordered_map>

#include "core/eval/nearest_neighbor_grid.h"
#include "core/eval/statistics.h"
#include "core/io/image_io.h"

namespace prism {
namespace {

struct VoxelKey {
  int64_t x, y, z;
  bool operator==(const VoxelKey& o) const { return x == o.x && y == o.y && z == o.z; }
};
struct VoxelKeyHash {
  size_t operator()(const VoxelKey& k) const {
    uint64_t h = static_cast<uint64_t>(k.x) * 0x9E3779B97F4A7C15ull;
    h ^= static_cast<uint64_t>(k.y) * 0xC2B2AE3D27D4EB4Full + (h << 6) + (h >> 2);
    h ^= static_cast<uint64_t>(k.z) * 0x165667B19E3779F9ull + (h << 6) + (h >> 2);
    return static_cast<size_t>(h);
  }
};

// Centroid per voxel, accumulated point by point; voxels keep the order of their first point.
class VoxelAccumulator {
 public:
  explicit VoxelAccumulator(double voxel_size_m) : voxel_size_m_(voxel_size_m) {}

  void Add(const Eigen::Vector3d& p) {
    if (!p.allFinite()) return;
    if (voxel_size_m_ <= 0.0) {
      sums_.push_back(p);
      counts_.push_back(1);
      return;
    }
    // Clamped so the integer conversion is defined for any finite input (far points then share voxels).
    constexpr double kMaxIndex = 1e15;
    const Eigen::Vector3d c = (p / voxel_size_m_).array().floor().cwiseMax(-kMaxIndex).cwiseMin(kMaxIndex);
    const VoxelKey key{static_cast<int64_t>(c.x()), static_cast<int64_t>(c.y()), static_cast<int64_t>(c.z())};
    const auto [it, inserted] = index_.try_emplace(key, sums_.size());
    if (inserted) {
      sums_.push_back(p);
      counts_.push_back(1);
    } else {
      sums_[it->second] += p;
      ++counts_[it->second];
    }
  }

  std::vector<Eigen::Vector3f> Centroids() const {
    std::vector<Eigen::Vector3f> out(sums_.size());
    for (size_t i = 0; i < sums_.size(); ++i) out[i] = (sums_[i] / static_cast<double>(counts_[i])).cast<float>();
    return out;
  }

 private:
  double voxel_size_m_;
  std::unordered_map<VoxelKey, size_t, VoxelKeyHash> index_;
  std::vector<Eigen::Vector3d> sums_;
  std::vector<uint32_t> counts_;
};

// Calls visit(point_in_world) for every back-projected pixel of the sampled frames; returns the number
// of frames that contributed.
template <typename Visit>
StatusOr<size_t> ForEachSurfacePoint(const Sequence& sequence, const SurfaceSamplingOptions& options, Visit&& visit) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!sequence.has_calibration)
    return FailedPreconditionError("sequence '" + sequence.root + "' has no camera.yaml (camera intrinsics needed)");
  const PinholeCamera& camera = sequence.calibration.camera;
  PRISM_RETURN_IF_ERROR(camera.Check());

  // Ray (z = 1) through every pixel, computed once for all frames.
  std::vector<Eigen::Vector2d> rays(static_cast<size_t>(camera.width) * camera.height);
  for (int v = 0; v < camera.height; ++v)
    for (int u = 0; u < camera.width; ++u)
      rays[static_cast<size_t>(v) * camera.width + u] = camera.Unproject(Eigen::Vector2d(u, v)).head<2>();

  size_t frames_used = 0;
  for (size_t i = 0; i < sequence.frames.size(); i += static_cast<size_t>(options.frame_step)) {
    const SequenceFrame& frame = sequence.frames[i];
    if (frame.depth_file.empty() || (options.object_only && frame.mask_file.empty())) continue;
    const StatusOr<Rigid3d> pose = sequence.GroundTruthPose(i);
    if (!pose.ok()) continue;
    PRISM_ASSIGN_OR_RETURN(const cv::Mat depth, sequence.ReadDepth(i));
    if (depth.cols != camera.width || depth.rows != camera.height)
      return InvalidArgumentError("depth image '" + frame.depth_file + "' is " + std::to_string(depth.cols) + "x" +
                                  std::to_string(depth.rows) + " but the camera is " + std::to_string(camera.width) +
                                  "x" + std::to_string(camera.height));
    cv::Mat mask;
    if (options.object_only) {
      PRISM_ASSIGN_OR_RETURN(mask, sequence.ReadMask(i));
      if (mask.size() != depth.size())
        return InvalidArgumentError("mask '" + frame.mask_file + "' and its depth image differ in size");
    }
    const Eigen::Matrix3d rotation = pose->RotationMatrix();
    const Eigen::Vector3d& translation = pose->translation;
    bool contributed = false;
    for (int v = 0; v < depth.rows; ++v) {
      const float* d = depth.ptr<float>(v);
      const uint8_t* m = options.object_only ? mask.ptr<uint8_t>(v) : nullptr;
      for (int u = 0; u < depth.cols; ++u) {
        if (!(d[u] > 0.0f) || !std::isfinite(d[u])) continue;
        if (m && m[u] != kMaskObject) continue;
        const Eigen::Vector2d& ray = rays[static_cast<size_t>(v) * camera.width + u];
        const Eigen::Vector3d point_in_camera(ray.x() * d[u], ray.y() * d[u], d[u]);
        visit(Eigen::Vector3d(rotation * point_in_camera + translation));
        contributed = true;
      }
    }
    if (contributed) ++frames_used;
  }
  if (frames_used == 0)
    return FailedPreconditionError("no frame of '" + sequence.root + "' (every " + std::to_string(options.frame_step) +
                                   "th) has ground-truth depth" + (options.object_only ? ", object mask pixels" : "") +
                                   " and a ground-truth pose");
  return frames_used;
}

}  // namespace

Status CloudEvalOptions::Check() const {
  if (!(tau_m > 0.0) || !std::isfinite(tau_m)) {
    std::ostringstream err;
    err << "CloudEvalOptions.tau_m = " << tau_m << "; violated: in (0, inf)";
    return InvalidArgumentError(err.str());
  }
  return Status::Ok();
}

Status SurfaceSamplingOptions::Check() const {
  std::ostringstream err;
  if (frame_step < 1) err << "SurfaceSamplingOptions.frame_step = " << frame_step << "; violated: >= 1";
  else if (!(voxel_size_m >= 0.0) || !std::isfinite(voxel_size_m))
    err << "SurfaceSamplingOptions.voxel_size_m = " << voxel_size_m << "; violated: in [0, inf)";
  if (err.str().empty()) return Status::Ok();
  return InvalidArgumentError(err.str());
}

StatusOr<CloudMetrics> EvaluateCloud(const std::vector<Eigen::Vector3f>& reconstruction,
                                     const std::vector<Eigen::Vector3f>& gt_samples, const CloudEvalOptions& options,
                                     ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  CloudMetrics metrics;
  metrics.tau_m = options.tau_m;
  const double max_coordinate = NearestNeighborGrid::kMaxCellIndex * options.tau_m;

  std::vector<Eigen::Vector3f> points;
  points.reserve(reconstruction.size());
  for (const Eigen::Vector3f& p : reconstruction) {
    if (!p.allFinite()) {
      ++metrics.non_finite_points;
      continue;
    }
    if (p.cwiseAbs().maxCoeff() > max_coordinate)
      return InvalidArgumentError(
          "a reconstructed point lies too far from the origin for tau = " + std::to_string(options.tau_m) + " m");
    points.push_back(p);
  }
  if (points.empty()) return InvalidArgumentError("the reconstruction has no finite point");
  if (gt_samples.empty()) return InvalidArgumentError("there are no ground-truth surface samples");
  for (const Eigen::Vector3f& s : gt_samples)
    if (!s.allFinite() || s.cwiseAbs().maxCoeff() > max_coordinate)
      return InvalidArgumentError("a ground-truth sample is not finite or lies too far from the origin");
  metrics.points = points.size();
  metrics.gt_samples = gt_samples.size();

  auto parallel_for = [pool](size_t n, const std::function<void(std::ptrdiff_t)>& fn) {
    if (pool) pool->ParallelFor(0, static_cast<std::ptrdiff_t>(n), fn, /*grain=*/1024);
    else
      for (size_t i = 0; i < n; ++i) fn(static_cast<std::ptrdiff_t>(i));
  };

  // Both grids are built first so each side can be queried in the other grid's cell order (cache
  // friendly); the statistics do not depend on the order.
  // The reconstruction's cells are a hair larger than tau, so a query bounded by tau is always settled
  // by the 3x3x3 cells around it.
  const NearestNeighborGrid gt_grid(gt_samples, options.tau_m);
  const NearestNeighborGrid cloud_grid(points, options.tau_m * (1.0 + 1e-6));
  points.clear();
  points.shrink_to_fit();

  // Accuracy and precision: reconstruction -> ground truth.
  const std::vector<Eigen::Vector3f>& cloud_points = cloud_grid.points();
  std::vector<double> distances(cloud_points.size());
  parallel_for(cloud_points.size(), [&](std::ptrdiff_t i) { distances[i] = gt_grid.NearestDistance(cloud_points[i]); });
  double sum = 0.0;
  size_t within = 0;
  for (double d : distances) {
    sum += d;
    within += d < options.tau_m;
  }
  metrics.accuracy_mean_m = sum / static_cast<double>(distances.size());
  metrics.precision = static_cast<double>(within) / static_cast<double>(distances.size());
  metrics.accuracy_median_m = Median(std::move(distances));

  // Completeness: ground truth -> reconstruction, only "within tau" matters.
  const std::vector<Eigen::Vector3f>& gt_points = gt_grid.points();
  std::vector<uint8_t> covered(gt_points.size(), 0);
  parallel_for(gt_points.size(), [&](std::ptrdiff_t i) {
    covered[i] = cloud_grid.NearestDistance(gt_points[i], options.tau_m) < options.tau_m;
  });
  size_t covered_count = 0;
  for (uint8_t c : covered) covered_count += c;
  metrics.completeness = static_cast<double>(covered_count) / static_cast<double>(gt_samples.size());
  const double denominator = metrics.precision + metrics.completeness;
  metrics.fscore = denominator > 0.0 ? 2.0 * metrics.precision * metrics.completeness / denominator : 0.0;
  return metrics;
}

std::vector<Eigen::Vector3f> VoxelDownsample(const std::vector<Eigen::Vector3f>& points, double voxel_size_m) {
  if (!(voxel_size_m > 0.0)) return points;
  VoxelAccumulator acc(voxel_size_m);
  for (const Eigen::Vector3f& p : points) acc.Add(p.cast<double>());
  return acc.Centroids();
}

StatusOr<SurfaceSamples> SampleGroundTruthSurface(const Sequence& sequence, const SurfaceSamplingOptions& options) {
  VoxelAccumulator acc(options.voxel_size_m);
  SurfaceSamples samples;
  PRISM_ASSIGN_OR_RETURN(samples.frames_used,
                         ForEachSurfacePoint(sequence, options, [&](const Eigen::Vector3d& p) { acc.Add(p); }));
  samples.points_in_world = acc.Centroids();
  return samples;
}

StatusOr<Eigen::AlignedBox3d> GroundTruthSurfaceBounds(const Sequence& sequence,
                                                       const SurfaceSamplingOptions& options) {
  Eigen::AlignedBox3d box;  // empty
  PRISM_RETURN_IF_ERROR(
      ForEachSurfacePoint(sequence, options, [&](const Eigen::Vector3d& p) { box.extend(p); }).status());
  return box;
}

StatusOr<PixelCoverage> ObjectPixelCoverage(const std::vector<Eigen::Vector3f>& points_in_world,
                                            const PinholeCamera& camera, const Rigid3d& world_from_camera,
                                            const cv::Mat& mask) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (mask.type() != CV_8UC1 || mask.cols != camera.width || mask.rows != camera.height)
    return InvalidArgumentError("mask must be CV_8UC1 of the camera's size " + std::to_string(camera.width) + "x" +
                                std::to_string(camera.height));
  // Distortion polynomials fold far-off-axis points back into the image; accept only points whose
  // undistorted direction lies within (a margin around) the image's field of view.
  double max_radius = 0.0;
  for (const Eigen::Vector2d& corner :
       {Eigen::Vector2d(0, 0), Eigen::Vector2d(camera.width - 1, 0), Eigen::Vector2d(0, camera.height - 1),
        Eigen::Vector2d(camera.width - 1, camera.height - 1)})
    max_radius = std::max(max_radius, camera.Unproject(corner).head<2>().norm());
  const double max_radius_sq = 1.5 * 1.5 * max_radius * max_radius;

  const Rigid3d camera_from_world = world_from_camera.Inverse();
  const Eigen::Matrix3d rotation = camera_from_world.RotationMatrix();
  std::vector<uint8_t> hit(static_cast<size_t>(camera.width) * camera.height, 0);
  for (const Eigen::Vector3f& p : points_in_world) {
    if (!p.allFinite()) continue;
    const Eigen::Vector3d point_in_camera = rotation * p.cast<double>() + camera_from_world.translation;
    if (!(point_in_camera.z() > 0.0)) continue;
    if (point_in_camera.head<2>().squaredNorm() > max_radius_sq * point_in_camera.z() * point_in_camera.z()) continue;
    const Eigen::Vector2d pixel = camera.Project(point_in_camera);
    const double u = std::round(pixel.x());
    const double v = std::round(pixel.y());
    if (!(u >= 0 && v >= 0 && u < camera.width && v < camera.height)) continue;
    hit[static_cast<size_t>(v) * camera.width + static_cast<size_t>(u)] = 1;
  }
  PixelCoverage coverage;
  for (int y = 0; y < mask.rows; ++y) {
    const uint8_t* m = mask.ptr<uint8_t>(y);
    for (int x = 0; x < mask.cols; ++x) {
      if (m[x] != kMaskObject) continue;
      ++coverage.object_pixels;
      coverage.covered_pixels += hit[static_cast<size_t>(y) * camera.width + x];
    }
  }
  if (coverage.object_pixels > 0)
    coverage.fraction = static_cast<double>(coverage.covered_pixels) / static_cast<double>(coverage.object_pixels);
  return coverage;
}

}  // namespace prism

namespace prism {

StatusOr<std::vector<size_t>> SelectPointsSeenOnObject(const Sequence& sequence,
                                                       const std::vector<Eigen::Vector3f>& points_in_world,
                                                       const SurfaceSamplingOptions& options, double behind_margin_m) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!sequence.has_calibration) return FailedPreconditionError("sequence has no camera.yaml");
  const PinholeCamera& camera = sequence.calibration.camera;
  std::vector<char> keep(points_in_world.size(), 0);
  size_t frames = 0;
  for (size_t i = 0; i < sequence.frames.size(); i += options.frame_step) {
    auto pose = sequence.GroundTruthPose(i);
    auto depth = sequence.ReadDepth(i);
    auto mask = sequence.ReadMask(i);
    if (!pose.ok() || !depth.ok() || !mask.ok()) continue;
    ++frames;
    const Rigid3d camera_from_world = pose->Inverse();
    for (size_t p = 0; p < points_in_world.size(); ++p) {
      if (keep[p] || !points_in_world[p].allFinite()) continue;
      const Eigen::Vector3d pc = camera_from_world * points_in_world[p].cast<double>();
      if (pc.z() <= 0) continue;
      const Eigen::Vector2d uv = camera.Project(pc);
      const int u = static_cast<int>(std::lround(uv.x())), v = static_cast<int>(std::lround(uv.y()));
      if (u < 0 || v < 0 || u >= camera.width || v >= camera.height) continue;
      if (mask->at<uint8_t>(v, u) != kMaskObject) continue;
      const float surface = depth->at<float>(v, u);
      if (surface > 0 && pc.z() > surface + behind_margin_m) continue;  // hidden behind the object here
      keep[p] = 1;
    }
  }
  if (frames == 0) return FailedPreconditionError("no sampled frame has depth, a pose and a mask");
  std::vector<size_t> out;
  for (size_t p = 0; p < keep.size(); ++p)
    if (keep[p]) out.push_back(p);
  return out;
}

}  // namespace prism
