#include "core/pipeline/dense_stage.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "core/util/logging.h"

namespace prism {
namespace {

double MsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t).count();
}

Status Violated(const std::string& field, double value, const std::string& rule) {
  return InvalidArgumentError("DenseStageOptions." + field + " = " + std::to_string(value) + "; violated: " + rule);
}

// One pyramid level up: each pixel the inverse-variance mean of the samples of its 2x2 block, or the
// most certain of them when they disagree by more than a depth step (fore- and background).
InverseDepthMap HalveDepth(const InverseDepthMap& depth) {
  constexpr float kMaxSpread = 0.03f;  // relative, as DenseStageOptions::max_edge_step
  const int w = depth.inverse_depth.cols / 2, h = depth.inverse_depth.rows / 2;
  InverseDepthMap half{cv::Mat::zeros(h, w, CV_32F), cv::Mat::zeros(h, w, CV_32F)};
  const bool has_variance = !depth.variance.empty();
  for (int y = 0; y < h; ++y) {
    const float* d[2] = {depth.inverse_depth.ptr<float>(2 * y), depth.inverse_depth.ptr<float>(2 * y + 1)};
    const float* v[2] = {has_variance ? depth.variance.ptr<float>(2 * y) : nullptr,
                         has_variance ? depth.variance.ptr<float>(2 * y + 1) : nullptr};
    float* hd = half.inverse_depth.ptr<float>(y);
    float* hv = half.variance.ptr<float>(y);
    for (int x = 0; x < w; ++x) {
      float weight = 0, sum = 0, lo = 0, hi = 0, best = 0, best_var = 0;
      for (int r = 0; r < 2; ++r)
        for (int c = 2 * x; c < 2 * x + 2; ++c) {
          const float id = d[r][c], var = has_variance ? v[r][c] : 1.0f;
          if (!(id > 0) || !(var > 0)) continue;
          if (weight == 0 || var < best_var) best = id, best_var = var;
          lo = weight == 0 ? id : std::min(lo, id);
          hi = weight == 0 ? id : std::max(hi, id);
          weight += 1 / var;
          sum += id / var;
        }
      if (weight == 0) continue;
      if (hi - lo <= kMaxSpread * lo) {
        hd[x] = sum / weight;
        hv[x] = 1 / weight;
      } else {
        hd[x] = best;
        hv[x] = best_var;
      }
    }
  }
  return half;
}

// The options in pixels at a pyramid level: lengths halve per level, areas quarter (counts of samples
// stay, the level's samples being averages).
DenseStageOptions AtImageLevel(DenseStageOptions o, int level) {
  const double s = 1.0 / (1 << level);
  auto length = [s](int px, int lowest) { return std::max(lowest, static_cast<int>(std::lround(px * s))); };
  PhotometricOptions& p = o.photometric;
  p.plane_radius_px = length(p.plane_radius_px, 2);
  p.image_smoothing_sigma_px *= s;
  p.superpixel_size_px = p.superpixel_size_px > 0 ? length(p.superpixel_size_px, 1) : 0;
  p.min_cluster_pixels = std::max(1, static_cast<int>(std::lround(p.min_cluster_pixels * s * s)));
  p.densify.sigma_px = std::max(0.5, p.densify.sigma_px * s);
  p.prior.step_px = length(p.prior.step_px, 1);
  p.prior.smoothing_sigma_px *= s;
  FusionOptions& f = o.fusion;
  f.correction_sigma_px *= s;
  f.min_unsupported_region_px = std::max(1, static_cast<int>(std::lround(f.min_unsupported_region_px * s * s)));
  return o;
}

}  // namespace

Status DenseStageOptions::Check() const {
  PRISM_RETURN_IF_ERROR(photometric.Check());
  PRISM_RETURN_IF_ERROR(fusion.Check());
  PRISM_RETURN_IF_ERROR(map.Check());
  PRISM_RETURN_IF_ERROR(icp.Check());
  if (max_image_level < 0 || max_image_level > 3) return Violated("max_image_level", max_image_level, "in [0, 3]");
  if (scale_keyframes < 1) return Violated("scale_keyframes", scale_keyframes, ">= 1");
  if (max_scale_keyframes < scale_keyframes)
    return Violated("max_scale_keyframes", max_scale_keyframes, ">= scale_keyframes");
  if (!(max_edge_step >= 0)) return Violated("max_edge_step", max_edge_step, ">= 0");
  if (!(max_icp_correction_m >= 0)) return Violated("max_icp_correction_m", max_icp_correction_m, ">= 0");
  if (!(max_icp_correction_deg >= 0)) return Violated("max_icp_correction_deg", max_icp_correction_deg, ">= 0");
  if (!(min_brightness >= 0 && min_brightness <= 255)) return Violated("min_brightness", min_brightness, "in [0, 255]");
  if (remap_max_points < 0) return Violated("remap_max_points", static_cast<double>(remap_max_points), ">= 0");
  if (!(min_icp_inlier_fraction >= 0 && min_icp_inlier_fraction <= 1))
    return Violated("min_icp_inlier_fraction", min_icp_inlier_fraction, "in [0, 1]");
  return Status::Ok();
}

StatusOr<std::unique_ptr<DenseStage>> DenseStage::Create(const RigCalibration& rig, const DenseStageOptions& options,
                                                         ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.Check());
  return std::unique_ptr<DenseStage>(new DenseStage(rig, options, pool));
}

DenseStage::DenseStage(const RigCalibration& rig, const DenseStageOptions& options, ThreadPool* pool)
    : rig_(rig), options_(options), pool_(pool), map_(options.map) {
  for (int level = 0; level <= options.max_image_level; ++level) {
    const DenseStageOptions at_level = AtImageLevel(options, level);
    Level l{rig, at_level.photometric, std::make_unique<DepthNormalFusion>(at_level.fusion, pool)};
    l.rig.camera = rig.camera.AtPyramidLevel(level);
    levels_.push_back(std::move(l));
  }
}

int DenseStage::ChooseLevel(const DenseKeyframe& keyframe) const {
  if (options_.max_image_level == 0 || !depth_scale_.has_value()) return 0;
  std::vector<float> inverse_depths;
  const cv::Mat& id = keyframe.depth.inverse_depth;
  for (int y = 0; y < id.rows; ++y) {
    const float* row = id.ptr<float>(y);
    for (int x = 0; x < id.cols; ++x)
      if (row[x] > 0) inverse_depths.push_back(row[x]);
  }
  if (inverse_depths.empty()) return 0;
  auto median = inverse_depths.begin() + inverse_depths.size() / 2;
  std::nth_element(inverse_depths.begin(), median, inverse_depths.end());
  const double unit = options_.world_in_slam_units ? keyframe.world_from_keyframe.scale : 1.0;
  const double depth_m = depth_scale_.value() * unit / *median;
  const double pixel_m = depth_m / rig_.camera.fx;  // at level 0
  int level = 0;
  while (level < options_.max_image_level && pixel_m * (2 << level) <= options_.map.voxel_m) ++level;
  return level;
}

DenseStage::~DenseStage() = default;

StatusOr<DenseKeyframeResult> DenseStage::Process(const DenseKeyframe& keyframe) {
  const PinholeCamera& camera = rig_.camera;
  const cv::Size size(camera.width, camera.height);
  if (keyframe.rgb.type() != CV_8UC3 || keyframe.rgb.size() != size)
    return InvalidArgumentError("keyframe " + std::to_string(keyframe.id) + ": rgb must be CV_8UC3 of " +
                                std::to_string(size.width) + "x" + std::to_string(size.height));
  if (keyframe.depth.inverse_depth.type() != CV_32F || keyframe.depth.inverse_depth.size() != size)
    return InvalidArgumentError("keyframe " + std::to_string(keyframe.id) +
                                ": inverse depth must be CV_32F of the camera's size");
  if (!keyframe.depth.variance.empty() &&
      (keyframe.depth.variance.type() != CV_32F || keyframe.depth.variance.size() != size))
    return InvalidArgumentError("keyframe " + std::to_string(keyframe.id) +
                                ": inverse depth variance must be empty or CV_32F of the camera's size");
  if (!(keyframe.world_from_keyframe.scale > 0) || !std::isfinite(keyframe.world_from_keyframe.scale))
    return InvalidArgumentError("keyframe " + std::to_string(keyframe.id) + ": world_from_keyframe scale must be > 0");

  DenseKeyframeResult result;
  result.keyframe_id = keyframe.id;
  result.image_level = ChooseLevel(keyframe);
  const Level& at = levels_[static_cast<size_t>(result.image_level)];
  const PinholeCamera& level_camera = at.rig.camera;
  cv::Mat rgb = keyframe.rgb;
  InverseDepthMap depth = keyframe.depth;
  for (int level = 0; level < result.image_level; ++level) {
    cv::resize(rgb, rgb, cv::Size(rgb.cols / 2, rgb.rows / 2), 0, 0, cv::INTER_AREA);
    depth = HalveDepth(depth);
  }

  // Photometric stereo: the first keyframes estimate the depth scale, then the session fixes it.
  auto t0 = std::chrono::steady_clock::now();
  PhotometricOptions ps_options = at.photometric;
  result.estimated_depth_scale = depth_scale_.count() < options_.max_scale_keyframes;
  ps_options.estimate_depth_scale = result.estimated_depth_scale;
  // The photometric depth scale is metres per unit of this keyframe's depth; the session's is metres
  // per SLAM world unit. They differ by the keyframe's Sim(3) scale (1 until a loop closure).
  const double unit = options_.world_in_slam_units ? keyframe.world_from_keyframe.scale : 1.0;
  if (!result.estimated_depth_scale) ps_options.depth_scale = depth_scale_.value() * unit;
  PRISM_ASSIGN_OR_RETURN(result.photometric, EstimateNormals(rgb, depth, at.rig, ps_options, pool_));
  result.photometric_ms = MsSince(t0);
  if (result.estimated_depth_scale) {
    depth_scale_.Add(result.photometric.depth_scale / unit);
    if (map_metres_per_unit_ == 0 && ScaleSettled()) map_metres_per_unit_ = depth_scale_.value();
    PRISM_LOG(INFO) << "dense: keyframe " << keyframe.id << " depth scale estimate "
                    << result.photometric.depth_scale / unit << " m/unit (session " << depth_scale_.value() << ", "
                    << depth_scale_.agreeing() << " of " << depth_scale_.count() << " estimates agree)";
  }
  result.metres_per_unit = map_metres_per_unit_ > 0   ? map_metres_per_unit_
                           : depth_scale_.has_value() ? depth_scale_.value()
                                                      : result.photometric.depth_scale;

  // Fusion of the SLAM positions and the PS normals.
  t0 = std::chrono::steady_clock::now();
  FusionInput input;
  input.camera = level_camera;
  input.normals = result.photometric.normals;
  input.confidence = result.photometric.confidence;
  input.semi_dense = depth;
  input.prior_inverse_depth = result.photometric.dense_inverse_depth;
  PRISM_ASSIGN_OR_RETURN(result.fusion, at.fusion->Fuse(input));
  result.fusion_ms = MsSince(t0);

  // Pixels along depth steps (flying pixels where the surface bridges a silhouette) leave the
  // keyframe's dense depth and so its cloud.
  result.depth = result.fusion.depth.clone();
  if (options_.max_edge_step > 0) {
    const cv::Mat keep = DepthEdgeFreeMask(result.fusion.depth, options_.max_edge_step);
    result.depth.setTo(0, keep == 0);
  }

  // The keyframe cloud in the metric world, registered to the map.
  t0 = std::chrono::steady_clock::now();
  cv::Mat bright;
  if (options_.min_brightness > 0) {
    cv::Mat grey;
    cv::transform(rgb, grey, cv::Matx13f(1.0f / 3, 1.0f / 3, 1.0f / 3));
    bright = grey >= options_.min_brightness;
  }
  PRISM_ASSIGN_OR_RETURN(PointCloud cloud_in_keyframe,
                         DepthToCloud(result.depth, result.fusion.normals, rgb, level_camera, Sim3d(), 1, bright,
                                      result.photometric.confidence));
  result.cloud = TransformCloud(cloud_in_keyframe, keyframe.world_from_keyframe);
  Keep(keyframe.id, keyframe.world_from_keyframe, cloud_in_keyframe);
  if (!options_.world_in_slam_units) {
    PRISM_RETURN_IF_ERROR(Merge(result.cloud, keyframe.id, options_.icp_enabled, &result));
  } else {
    pending_.push_back({keyframe.id, result.cloud});
    result.pending = map_metres_per_unit_ == 0;
    if (!result.pending) {
      PRISM_RETURN_IF_ERROR(MergePending(map_metres_per_unit_, &result));
      for (Eigen::Vector3f& p : result.cloud.positions) p *= static_cast<float>(map_metres_per_unit_);
    }
  }
  result.changes = map_.TakeChanges();
  result.map_ms = MsSince(t0);
  return result;
}

double DenseStage::MapCoverage(const DenseKeyframe& keyframe) const {
  const double metres = options_.world_in_slam_units ? map_metres_per_unit_ : 1.0;
  const cv::Mat& id = keyframe.depth.inverse_depth;
  if (!(metres > 0) || map_.empty() || id.type() != CV_32F) return 0;
  const PinholeCamera& c = rig_.camera;
  const Sim3d& pose = keyframe.world_from_keyframe;
  constexpr int kStep = 4;
  constexpr int kReach = 2;  // voxels: the semi-dense depth's noise (a few mm at 1 m)
  const uint32_t min_keyframes = static_cast<uint32_t>(options_.map.min_keyframes);
  const float voxel = static_cast<float>(options_.map.voxel_m);
  size_t points = 0, covered = 0;
  for (int y = 0; y < id.rows; y += kStep) {
    const float* row = id.ptr<float>(y);
    for (int x = 0; x < id.cols; x += kStep) {
      if (!(row[x] > 0)) continue;
      const Eigen::Vector3d ray((x - c.cx) / c.fx, (y - c.cy) / c.fy, 1.0);
      const Eigen::Vector3f p = (metres * (pose * (ray / row[x]))).cast<float>();
      Eigen::Vector3i v;
      if (!map_.VoxelOf(p, &v)) continue;
      ++points;
      bool found = false;
      for (int dz = -kReach; dz <= kReach && !found; ++dz)
        for (int dy = -kReach; dy <= kReach && !found; ++dy)
          for (int dx = -kReach; dx <= kReach && !found; ++dx)
            found = map_.VoxelOf(p + voxel * Eigen::Vector3f(dx, dy, dz), &v) &&
                    map_.Keyframes(PackVoxelKey(v)) >= min_keyframes;
      covered += found;
    }
  }
  return points > 0 ? static_cast<double>(covered) / static_cast<double>(points) : 0.0;
}

Status DenseStage::Merge(const PointCloud& cloud, uint64_t keyframe_id, bool icp, DenseKeyframeResult* result) {
  Rigid3d correction;  // map_from_cloud; identity unless ICP passes the guard
  result->icp_attempted = false;
  result->icp_applied = false;
  result->icp_estimate = Rigid3d();
  if (icp && !map_.empty()) {
    StatusOr<IcpTarget> target = IcpTarget::Create(map_.ToPointCloud(), options_.icp);
    if (target.ok()) {
      StatusOr<IcpSummary> s = AlignIcp(cloud, *target, Rigid3d(), options_.icp, &result->icp_estimate);
      if (s.ok()) {
        result->icp_attempted = true;
        result->icp = *s;
        const bool plausible =
            result->icp_estimate.translation.norm() <= options_.max_icp_correction_m &&
            RotationAngle(result->icp_estimate.rotation) * 180 / M_PI <= options_.max_icp_correction_deg;
        result->icp_applied = s->converged && s->inlier_fraction >= options_.min_icp_inlier_fraction && plausible;
        if (result->icp_applied) correction = result->icp_estimate;
      }
    }
  }
  PRISM_ASSIGN_OR_RETURN(MapInsertStats stats, map_.Insert(cloud, correction, keyframe_id));
  result->insert += stats;
  return Status::Ok();
}

Status DenseStage::MergePending(double metres_per_unit, DenseKeyframeResult* result) {
  std::vector<PendingCloud> pending;
  pending.swap(pending_);
  for (PendingCloud& p : pending) {
    for (Eigen::Vector3f& x : p.cloud_in_slam_world.positions) x *= static_cast<float>(metres_per_unit);
    PRISM_RETURN_IF_ERROR(Merge(p.cloud_in_slam_world, p.keyframe_id, options_.icp_enabled, result));
  }
  return Status::Ok();
}

bool DenseStage::ScaleSettled() const {
  return depth_scale_.agreeing() >= options_.scale_keyframes || depth_scale_.count() >= options_.max_scale_keyframes;
}

StatusOr<MapChunk> DenseStage::Flush() {
  if (pending_.empty() || !depth_scale_.has_value()) return MapChunk();
  if (map_metres_per_unit_ == 0) map_metres_per_unit_ = depth_scale_.value();
  DenseKeyframeResult scratch;
  PRISM_RETURN_IF_ERROR(MergePending(map_metres_per_unit_, &scratch));
  return map_.TakeChanges();
}

namespace {

// Every other element, from the first.
template <typename T>
void KeepEveryOther(std::vector<T>* v) {
  size_t n = 0;
  for (size_t i = 0; i < v->size(); i += 2) (*v)[n++] = (*v)[i];
  v->resize(n);
  v->shrink_to_fit();
}

}  // namespace

void DenseStage::KeptCloud::Thin() {
  KeepEveryOther(&positions);
  KeepEveryOther(&normals);
  KeepEveryOther(&colors);
  KeepEveryOther(&confidences);
}

PointCloud DenseStage::KeptCloud::ToPointCloud() const {
  PointCloud cloud;
  cloud.positions = positions;
  cloud.normals.reserve(normals.size());
  for (const Eigen::Matrix<int16_t, 3, 1>& n : normals) cloud.normals.push_back(n.cast<float>() / 32767.0f);
  cloud.colors = colors;
  cloud.confidences = confidences;
  return cloud;
}

void DenseStage::Keep(uint64_t keyframe_id, const Sim3d& world_from_keyframe, const PointCloud& cloud_in_keyframe) {
  if (kept_overflow_ || options_.remap_max_points == 0) return;
  constexpr int kMaxStride = 64;
  KeptCloud k;
  k.keyframe_id = keyframe_id;
  k.world_from_keyframe = world_from_keyframe;
  const bool has_normals = cloud_in_keyframe.HasNormals(), has_colors = cloud_in_keyframe.HasColors(),
             has_confidences = cloud_in_keyframe.HasConfidences();
  const size_t stride = static_cast<size_t>(kept_stride_);
  const size_t n = (cloud_in_keyframe.size() + stride - 1) / stride;
  k.positions.reserve(n);
  if (has_normals) k.normals.reserve(n);
  if (has_colors) k.colors.reserve(n);
  if (has_confidences) k.confidences.reserve(n);
  for (size_t i = 0; i < cloud_in_keyframe.size(); i += stride) {
    k.positions.push_back(cloud_in_keyframe.positions[i]);
    if (has_normals) {
      const Eigen::Vector3f n = cloud_in_keyframe.normals[i].cwiseMax(-1.0f).cwiseMin(1.0f) * 32767.0f;
      k.normals.push_back(n.array().round().cast<int16_t>().matrix());
    }
    if (has_colors) k.colors.push_back(cloud_in_keyframe.colors[i]);
    if (has_confidences) k.confidences.push_back(cloud_in_keyframe.confidences[i]);
  }
  kept_points_ += static_cast<int64_t>(k.size());
  kept_.push_back(std::move(k));
  while (kept_points_ > options_.remap_max_points) {
    if (kept_stride_ >= kMaxStride) {
      PRISM_LOG(WARNING) << "dense: the clouds kept for a remap pass " << options_.remap_max_points
                         << " points (remap_max_points) even at one point in " << kept_stride_
                         << ": freed, the map will not follow moved keyframe poses";
      kept_.clear();
      kept_.shrink_to_fit();
      kept_points_ = 0;
      kept_overflow_ = true;
      return;
    }
    kept_stride_ *= 2;
    kept_points_ = 0;
    for (KeptCloud& c : kept_) {
      c.Thin();
      kept_points_ += static_cast<int64_t>(c.size());
    }
    PRISM_LOG(WARNING) << "dense: keyframe " << keyframe_id << " took the clouds kept for a remap past "
                       << options_.remap_max_points << " points (remap_max_points): thinned to one point in "
                       << kept_stride_ << " (" << kept_points_ << " points in " << kept_.size() << " clouds)";
  }
}

StatusOr<MapChunk> DenseStage::Remap(const std::vector<Sim3d>& world_from_keyframe, double min_move_m,
                                     double metres_per_world_unit) {
  if (!(metres_per_world_unit >= 0) || !std::isfinite(metres_per_world_unit))
    return InvalidArgumentError("remap: metres_per_world_unit must be finite and >= 0");
  if (options_.remap_max_points == 0) return FailedPreconditionError("remap: no clouds kept (remap_max_points = 0)");
  if (kept_overflow_)
    return FailedPreconditionError("remap: the kept clouds passed remap_max_points = " +
                                   std::to_string(options_.remap_max_points) + " even thinned, and were freed");
  PRISM_ASSIGN_OR_RETURN(MapChunk flushed, Flush());
  if (options_.world_in_slam_units && !depth_scale_.has_value())
    return FailedPreconditionError("remap: the session has no depth scale (no keyframe estimated it)");
  // The map is at map_metres_per_unit_ (0 only when every keyframe failed before its cloud).
  const double map_metres = !options_.world_in_slam_units ? 1.0
                            : map_metres_per_unit_ > 0    ? map_metres_per_unit_
                                                          : depth_scale_.value();
  const double metres = !options_.world_in_slam_units ? 1.0
                        : metres_per_world_unit > 0   ? metres_per_world_unit
                                                      : depth_scale_.value();
  bool moved = std::abs(metres / map_metres - 1.0) > min_move_m;
  for (const KeptCloud& k : kept_) {
    if (k.keyframe_id >= world_from_keyframe.size()) continue;
    const Sim3d& to = world_from_keyframe[k.keyframe_id];
    const Sim3d& from = k.world_from_keyframe;
    if (!(to.scale > 0) || !std::isfinite(to.scale) || !to.translation.allFinite())
      return InvalidArgumentError("remap: keyframe " + std::to_string(k.keyframe_id) + " has an invalid pose");
    moved = moved || metres * (to.translation - from.translation).norm() > min_move_m ||
            RotationAngle(to.rotation * from.rotation.inverse()) > min_move_m ||
            std::abs(to.scale / from.scale - 1.0) > min_move_m;
  }
  if (!moved) return flushed;
  if (options_.world_in_slam_units) map_metres_per_unit_ = metres;
  map_.Clear();
  DenseKeyframeResult scratch;
  for (KeptCloud& k : kept_) {
    if (k.keyframe_id < world_from_keyframe.size()) k.world_from_keyframe = world_from_keyframe[k.keyframe_id];
    const Sim3d& p = k.world_from_keyframe;
    const PointCloud cloud =
        TransformCloud(k.ToPointCloud(), Sim3d(metres * p.scale, p.rotation, metres * p.translation));
    PRISM_RETURN_IF_ERROR(Merge(cloud, k.keyframe_id, options_.icp_enabled && options_.remap_icp, &scratch));
  }
  return map_.TakeChanges();
}

MetresPerUnit ChooseMetresPerUnit(double dense_stage, double shading, bool shading_consistent) {
  const bool dense_known = dense_stage > 0 && std::isfinite(dense_stage);
  const bool shading_known = shading > 0 && std::isfinite(shading);
  if (!dense_known) return shading_known ? MetresPerUnit{shading, true} : MetresPerUnit{};
  if (shading_known && shading_consistent &&
      std::max(dense_stage, shading) <= kDepthScaleAgreement * std::min(dense_stage, shading))
    return {shading, true};
  return {dense_stage, false};
}

}  // namespace prism
