// The dense stage of one session (paper §3.3-3.4): per finished SLAM keyframe, multispectral
// photometric stereo with the session depth scale, positions+normals fusion, removal of depth-edge
// (flying) pixels, the dense keyframe cloud, ICP against the map with a plausibility guard, and the
// merge into the GlobalMap; it hands back the map voxels that changed (an incremental chunk). It keeps
// each merged cloud in its keyframe's frame, so that Remap can rebuild the whole map once the keyframe
// poses have moved (the end of a session: final adjustment, loop closures).
//
// Thread safety: not internally synchronised; one thread at a time calls Process (the keyframes of
// a session are processed in order). The heavy loops run on the ThreadPool given at construction,
// which may be shared by many DenseStages; call Process from a thread that is not one of its workers.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "core/fusion/fusion.h"
#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/io/calibration_io.h"
#include "core/io/inverse_depth.h"
#include "core/mapping/global_map.h"
#include "core/mapping/icp.h"
#include "core/photometric/photometric_stereo.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"

namespace prism {

struct DenseStageOptions {
  // Photometric stereo; estimate_depth_scale and depth_scale are set per keyframe by the stage.
  PhotometricOptions photometric;
  FusionOptions fusion;
  // The map's output keeps voxels seen by at least 2 keyframes (MapOptions::min_keyframes; 1 for
  // MapOptions alone). Measured with prism-slam --dense on the 9 presets, seed 1: see README, "The map
  // keeps what two keyframes saw".
  MapOptions map{/*voxel_m=*/0.002, /*min_keyframes=*/2};
  IcpOptions icp;
  // Each keyframe goes through the stage at the coarsest pyramid level, up to this one, whose pixel at
  // the keyframe's median depth is no wider than a map voxel (map.voxel_m): a finer level only adds
  // samples within the same voxels. Each level halves the image: the colour image by 2x2 averaging,
  // the semi-dense depth by its samples' inverse-variance mean. Until the session has a depth scale,
  // level 0. In [0, 3]; 0 = always the camera's resolution. The options in pixels below are at the
  // camera's resolution (the stage scales them to the level).
  int max_image_level = 1;
  // Register each keyframe cloud to the map with ICP before merging it. Off: with the SLAM's poses the
  // guard keeps about half of the corrections out, the rest move the map's F-score by under 0.006 (5
  // presets and 6 family scenes), and ICP was 62-66% of the stage's time. For poses from elsewhere.
  bool icp_enabled = false;
  // The first max_scale_keyframes keyframes estimate the depth scale (metres per SLAM unit) from the
  // shading (SessionDepthScale: the median of the largest group that agrees). The map fixes its scale
  // as soon as scale_keyframes of the estimates agree, or all max_scale_keyframes have estimated, and
  // Remap brings it to the session's final estimate. 1 <= scale_keyframes <= max_scale_keyframes.
  int scale_keyframes = 3;
  int max_scale_keyframes = 8;
  // Pixels whose fused depth differs from a neighbour's by more than this (relative) are removed from
  // the keyframe's depth and cloud (flying pixels along silhouettes), >= 0; 0 keeps every pixel.
  double max_edge_step = 0.03;
  // Pixels darker than this (mean of the three channels, 8-bit levels) stay out of the keyframe cloud:
  // in the dark room they are the far ground and background the lights barely reach, whose normals
  // are noise, in [0, 255]; 0 keeps every pixel.
  double min_brightness = 0.0;
  // Largest ICP correction applied, metres and degrees, >= 0. Larger ones, unconverged ones and ones
  // pairing fewer than min_icp_inlier_fraction of the points are reported but not applied (symmetric
  // geometry, such as a sphere on a plane, lets ICP slide).
  double max_icp_correction_m = 0.01;
  double max_icp_correction_deg = 1.0;
  // In [0, 1].
  double min_icp_inlier_fraction = 0.3;
  // true: DenseKeyframe::world_from_keyframe maps into the SLAM world (SLAM units) and the stage maps
  // it to metres with the session depth scale (the live pipeline). The clouds of the keyframes that
  // estimate it wait until that scale is fixed (see scale_keyframes), so that every cloud enters
  // the map with the same scale. false: it already maps into a metric world (prism-fuse with
  // ground-truth poses) and each cloud is merged at once.
  bool world_in_slam_units = true;
  // Every merged keyframe cloud is also kept in its keyframe's own frame, so that Remap can rebuild
  // the map once the keyframe poses have moved (a loop closure, the final adjustment), up to this many
  // points over the session (DenseStage::kKeptBytesPerPoint each: 8M points is about 190 MB). Past it
  // every kept cloud is thinned to every other point, and later clouds likewise (logged; the rebuilt
  // map then has fewer samples per voxel), down to one point in 64. 0 keeps none.
  int64_t remap_max_points = 8000000;
  // Remap registers each cloud to the rebuilt map again with ICP (the guard as above); false places
  // each at its moved pose alone. Measured with prism-slam --dense on the 9 presets x seeds 1-2: the
  // same F-scores to 0.002 either way (the guard keeps most corrections out), at 2-20 s per rebuild
  // with ICP against 0.14-0.53 s without.
  bool remap_icp = false;

  Status Check() const;
};

// A finished SLAM keyframe.
struct DenseKeyframe {
  uint64_t id = 0;
  cv::Mat rgb;  // CV_8UC3, RGB, the rig camera's size
  // Keyframe camera (SLAM depth units) -> world (see DenseStageOptions::world_in_slam_units).
  Sim3d world_from_keyframe;
  InverseDepthMap depth;  // semi-dense inverse depth, 1/SLAM unit
};

struct DenseKeyframeResult {
  uint64_t keyframe_id = 0;
  PhotometricResult photometric;       // PS normals, confidence, prior normals, depth_scale used
  bool estimated_depth_scale = false;  // this keyframe estimated the scale (photometric.depth_scale)
  FusionResult fusion;                 // fusion.depth is before the depth-edge filter
  cv::Mat depth;                       // CV_32F fused depth, SLAM units, depth-edge pixels set to 0
  double metres_per_unit = 1.0;        // the map's depth scale after this keyframe (map_metres_per_unit)
  // The keyframe cloud in the (metric) world frame before the ICP correction; confidences from PS.
  // While pending (world_in_slam_units, scale not fixed yet) it is in SLAM units and not in the map.
  PointCloud cloud;
  bool pending = false;
  bool icp_attempted = false;
  IcpSummary icp;
  Rigid3d icp_estimate;      // map_from_cloud found by ICP (identity when not attempted)
  bool icp_applied = false;  // icp_estimate passed the guard and was applied
  MapInsertStats insert;
  MapChunk changes;  // voxels created or changed by this keyframe (GlobalMap::TakeChanges)
  // The pyramid level the keyframe went through the stage at (DenseStageOptions::max_image_level); the
  // images above (normals, depth) are of that level's size.
  int image_level = 0;
  double photometric_ms = 0, fusion_ms = 0, map_ms = 0;
};

class DenseStage {
 public:
  // INVALID_ARGUMENT on bad options or rig. pool may be null (everything inline).
  static StatusOr<std::unique_ptr<DenseStage>> Create(const RigCalibration& rig, const DenseStageOptions& options,
                                                      ThreadPool* pool);
  ~DenseStage();

  // A keyframe whose photometric stereo fails returns that error and changes nothing; one whose fusion
  // fails returns that error after its depth-scale estimate was counted. INVALID_ARGUMENT on images of
  // the wrong type or size.
  StatusOr<DenseKeyframeResult> Process(const DenseKeyframe& keyframe);

  // What the map already holds of what the keyframe sees: the fraction of its semi-dense points (every
  // 4th pixel of every 4th row) that fall within 2 voxels (each axis) of a voxel of the map's output (one
  // with MapOptions::min_keyframes keyframes), at the keyframe's pose and the map's scale. 0 while the map
  // has no scale or no such voxel.
  double MapCoverage(const DenseKeyframe& keyframe) const;

  // Merges the clouds still waiting for the session scale with the current estimate (end of a session
  // before the scale settled) and returns the changed voxels; empty when none wait.
  StatusOr<MapChunk> Flush();

  // Rebuilds the map from the kept keyframe clouds (DenseStageOptions::remap_max_points) at moved
  // keyframe poses: world_from_keyframe[id] for each keyframe id in range, in the units of
  // DenseKeyframe::world_from_keyframe (keyframes beyond the vector keep theirs). Clouds waiting for
  // the session scale are merged first (as Flush). The clouds enter the cleared map in their original
  // order, each registered again with ICP when remap_icp. Returns the whole new map as one chunk with
  // replaces_map = true; an empty chunk (map unchanged) when no keyframe moved by more than
  // min_move_m (metres; rotations count as their arc at 1 m). FAILED_PRECONDITION when the clouds were
  // not kept (over the budget, or remap_max_points = 0). With world_in_slam_units the map is rebuilt at
  // metres_per_world_unit when > 0 (ChooseMetresPerUnit), else at the session's depth scale now
  // (depth_scale().value(), which may have moved since the map fixed its scale); a change of scale
  // counts as a move.
  StatusOr<MapChunk> Remap(const std::vector<Sim3d>& world_from_keyframe, double min_move_m = 1e-6,
                           double metres_per_world_unit = 0);
  // Clouds kept for Remap, their points, and the thinning (1 = every point, 2 = every other, ...).
  size_t kept_clouds() const { return kept_.size(); }
  int64_t kept_points() const { return kept_points_; }
  int kept_stride() const { return kept_stride_; }
  // Memory of a kept point: position (3 floats), normal (3 int16), colour (3 bytes), confidence.
  static constexpr int kKeptBytesPerPoint = 25;

  const GlobalMap& map() const { return map_; }
  // The session's depth scale from the keyframes' estimates (DenseStageOptions::max_scale_keyframes).
  const SessionDepthScale& depth_scale() const { return depth_scale_; }
  // Its value, 0 before any keyframe estimated it.
  double session_metres_per_unit() const { return depth_scale_.has_value() ? depth_scale_.value() : 0.0; }
  // Metres per SLAM unit of the map as it stands (0 before its scale is fixed).
  double map_metres_per_unit() const { return map_metres_per_unit_; }
  const RigCalibration& rig() const { return rig_; }
  const DenseStageOptions& options() const { return options_; }

 private:
  DenseStage(const RigCalibration& rig, const DenseStageOptions& options, ThreadPool* pool);
  // ICP against the map (with the guard) and merge; fills the ICP fields and insert stats of result.
  Status Merge(const PointCloud& cloud_in_world, uint64_t keyframe_id, bool icp, DenseKeyframeResult* result);
  // Keeps a cloud for Remap within the budget (DenseStageOptions::remap_max_points).
  void Keep(uint64_t keyframe_id, const Sim3d& world_from_keyframe, const PointCloud& cloud_in_keyframe);
  Status MergePending(double metres_per_unit, DenseKeyframeResult* result);
  // The session depth scale is fixed (see DenseStageOptions::scale_keyframes).
  bool ScaleSettled() const;

  RigCalibration rig_;
  DenseStageOptions options_;
  ThreadPool* pool_;
  // Per pyramid level up to options_.max_image_level: the rig's camera, the photometric options with
  // their pixel lengths, and the fusion at that level.
  struct Level {
    RigCalibration rig;
    PhotometricOptions photometric;
    std::unique_ptr<DepthNormalFusion> fusion;
  };
  std::vector<Level> levels_;
  // The level for a keyframe (see DenseStageOptions::max_image_level).
  int ChooseLevel(const DenseKeyframe& keyframe) const;
  GlobalMap map_;
  SessionDepthScale depth_scale_;
  double map_metres_per_unit_ = 0;
  struct PendingCloud {
    uint64_t keyframe_id = 0;
    PointCloud cloud_in_slam_world;
  };
  std::vector<PendingCloud> pending_;
  // Every merged or pending cloud in the order it entered the map, in its keyframe's frame (keyframe
  // depth units) with the pose it was made with (DenseKeyframe::world_from_keyframe).
  // Normals are kept as int16 (unit vector * 32767); an empty array = the cloud had none.
  struct KeptCloud {
    uint64_t keyframe_id = 0;
    Sim3d world_from_keyframe;
    std::vector<Eigen::Vector3f> positions;
    std::vector<Eigen::Matrix<int16_t, 3, 1>> normals;
    std::vector<Eigen::Matrix<uint8_t, 3, 1>> colors;
    std::vector<float> confidences;
    size_t size() const { return positions.size(); }
    // Keeps every other point.
    void Thin();
    PointCloud ToPointCloud() const;
  };
  std::vector<KeptCloud> kept_;
  int64_t kept_points_ = 0;
  int kept_stride_ = 1;
  bool kept_overflow_ = false;  // even one point in 64 passed the budget: kept_ is empty and stays so
};

// The session's metres per SLAM unit from two independent estimates: the dense stage's
// (DenseStage::depth_scale, photometric stereo with an albedo per colour cluster) and the SLAM's from
// the co-moving lights (SlamSystem::EstimateMetricScale: many frame pairs, but a grey albedo, so
// coloured surfaces bias it: 51-77% low on the generalisation family where the dense stage's was
// within 30%). The SLAM's is taken when its shading check passed and it agrees with the dense stage's
// within kDepthScaleAgreement; else the dense stage's. 0 = no such estimate; both 0 gives 0.
struct MetresPerUnit {
  double value = 0;
  bool from_shading = false;  // the SLAM's estimate was taken
};
MetresPerUnit ChooseMetresPerUnit(double dense_stage, double shading, bool shading_consistent);

}  // namespace prism
