#include "core/pipeline/dense_stage.h"

#include <chrono>
#include <cmath>
#include <string>

#include "core/util/logging.h"

namespace prism {
namespace {

double MsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t).count();
}

Status Violated(const std::string& field, double value, const std::string& rule) {
  return InvalidArgumentError("DenseStageOptions." + field + " = " + std::to_string(value) + "; violated: " + rule);
}

}  // namespace

Status DenseStageOptions::Check() const {
  PRISM_RETURN_IF_ERROR(photometric.Check());
  PRISM_RETURN_IF_ERROR(fusion.Check());
  PRISM_RETURN_IF_ERROR(map.Check());
  PRISM_RETURN_IF_ERROR(icp.Check());
  if (scale_keyframes < 1) return Violated("scale_keyframes", scale_keyframes, ">= 1");
  if (max_scale_keyframes < scale_keyframes)
    return Violated("max_scale_keyframes", max_scale_keyframes, ">= scale_keyframes");
  if (!(max_edge_step >= 0)) return Violated("max_edge_step", max_edge_step, ">= 0");
  if (!(max_icp_correction_m >= 0)) return Violated("max_icp_correction_m", max_icp_correction_m, ">= 0");
  if (!(max_icp_correction_deg >= 0)) return Violated("max_icp_correction_deg", max_icp_correction_deg, ">= 0");
  if (!(min_brightness >= 0 && min_brightness <= 255)) return Violated("min_brightness", min_brightness, "in [0, 255]");
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
    : rig_(rig), options_(options), pool_(pool), fusion_(options.fusion, pool), map_(options.map) {}

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
  if (!(keyframe.world_from_keyframe.scale > 0) || !std::isfinite(keyframe.world_from_keyframe.scale))
    return InvalidArgumentError("keyframe " + std::to_string(keyframe.id) + ": world_from_keyframe scale must be > 0");

  DenseKeyframeResult result;
  result.keyframe_id = keyframe.id;

  // Photometric stereo: the first keyframes estimate the depth scale, then the session fixes it.
  auto t0 = std::chrono::steady_clock::now();
  PhotometricOptions ps_options = options_.photometric;
  result.estimated_depth_scale = !ScaleSettled();
  ps_options.estimate_depth_scale = result.estimated_depth_scale;
  // The photometric depth scale is metres per unit of this keyframe's depth; the session's is metres
  // per SLAM world unit. They differ by the keyframe's Sim(3) scale (1 until a loop closure).
  const double unit = options_.world_in_slam_units ? keyframe.world_from_keyframe.scale : 1.0;
  if (!result.estimated_depth_scale) ps_options.depth_scale = depth_scale_.value() * unit;
  PRISM_ASSIGN_OR_RETURN(result.photometric, EstimateNormals(keyframe.rgb, keyframe.depth, rig_, ps_options, pool_));
  result.photometric_ms = MsSince(t0);
  if (result.estimated_depth_scale) {
    depth_scale_.Add(result.photometric.depth_scale / unit);
    PRISM_LOG(INFO) << "dense: keyframe " << keyframe.id << " depth scale estimate " << result.photometric.depth_scale
                    << " m/unit (session " << depth_scale_.value() << ", " << depth_scale_.agreeing() << " of "
                    << depth_scale_.count() << " estimates agree)";
  }
  result.metres_per_unit = depth_scale_.has_value() ? depth_scale_.value() : result.photometric.depth_scale;

  // Fusion of the SLAM positions and the PS normals.
  t0 = std::chrono::steady_clock::now();
  FusionInput input;
  input.camera = camera;
  input.normals = result.photometric.normals;
  input.confidence = result.photometric.confidence;
  input.semi_dense = keyframe.depth;
  input.prior_inverse_depth = result.photometric.dense_inverse_depth;
  PRISM_ASSIGN_OR_RETURN(result.fusion, fusion_.Fuse(input));
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
    cv::transform(keyframe.rgb, grey, cv::Matx13f(1.0f / 3, 1.0f / 3, 1.0f / 3));
    bright = grey >= options_.min_brightness;
  }
  PRISM_ASSIGN_OR_RETURN(result.cloud,
                         DepthToCloud(result.depth, result.fusion.normals, keyframe.rgb, camera,
                                      keyframe.world_from_keyframe, 1, bright, result.photometric.confidence));
  if (!options_.world_in_slam_units) {
    PRISM_RETURN_IF_ERROR(Merge(result.cloud, keyframe.id, &result));
  } else {
    pending_.push_back({keyframe.id, result.cloud});
    result.pending = !ScaleSettled();
    if (!result.pending) {
      PRISM_RETURN_IF_ERROR(MergePending(depth_scale_.value(), &result));
      for (Eigen::Vector3f& p : result.cloud.positions) p *= static_cast<float>(depth_scale_.value());
    }
  }
  result.changes = map_.TakeChanges();
  result.map_ms = MsSince(t0);
  return result;
}

Status DenseStage::Merge(const PointCloud& cloud, uint64_t keyframe_id, DenseKeyframeResult* result) {
  Rigid3d correction;  // map_from_cloud; identity unless ICP passes the guard
  result->icp_attempted = false;
  result->icp_applied = false;
  result->icp_estimate = Rigid3d();
  if (options_.icp_enabled && !map_.empty()) {
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
    PRISM_RETURN_IF_ERROR(Merge(p.cloud_in_slam_world, p.keyframe_id, result));
  }
  return Status::Ok();
}

bool DenseStage::ScaleSettled() const {
  return depth_scale_.agreeing() >= options_.scale_keyframes || depth_scale_.count() >= options_.max_scale_keyframes;
}

StatusOr<MapChunk> DenseStage::Flush() {
  if (pending_.empty() || !depth_scale_.has_value()) return MapChunk();
  DenseKeyframeResult scratch;
  PRISM_RETURN_IF_ERROR(MergePending(depth_scale_.value(), &scratch));
  return map_.TakeChanges();
}

}  // namespace prism
