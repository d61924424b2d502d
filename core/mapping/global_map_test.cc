#include "core/mapping/global_map.h"

#include <cmath>
#include <limits>
#include <random>
#include <set>

#include <gtest/gtest.h>

#include "core/mapping/synthetic_keyframe.h"
#include "core/synth/presets.h"

namespace prism {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

// A dense keyframe cloud of the sphere preset in the world frame.
PointCloud RenderWorldCloud(int frame) {
  synth::PresetOptions o;
  o.width = 256;
  o.height = 256;
  o.frames = 30;
  auto setup = synth::MakePreset("sphere-multicolor-sideways", o);
  PRISM_CHECK(setup.ok()) << setup.status().ToString();
  const Trajectory trajectory = synth::MakeTrajectory(setup->trajectory);
  const Rigid3d world_from_camera = trajectory[frame].world_from_camera;
  return TransformCloud(RenderKeyframeCloud(*setup, world_from_camera, frame + 1), world_from_camera);
}

// Distinct voxels of a cloud's finite points.
std::set<VoxelKey> VoxelsOf(const GlobalMap& map, const PointCloud& cloud) {
  std::set<VoxelKey> keys;
  for (const Eigen::Vector3f& p : cloud.positions) {
    Eigen::Vector3i v;
    if (map.VoxelOf(p, &v)) keys.insert(PackVoxelKey(v));
  }
  return keys;
}

TEST(GlobalMapTest, SameCloudTwiceDoublesObservationsButNotVoxels) {
  const PointCloud cloud = RenderWorldCloud(0);
  ASSERT_GT(cloud.size(), 10000u);
  GlobalMap map;
  auto first = map.Insert(cloud, 1);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->merged_points, cloud.size());
  EXPECT_EQ(first->new_voxels, map.size());
  EXPECT_EQ(first->skipped(), 0u);
  EXPECT_EQ(map.size(), VoxelsOf(map, cloud).size());
  EXPECT_LT(map.size(), cloud.size());  // 2 mm voxels hold several ~1-2 mm pixels
  const MapChunk before = map.TakeChanges();
  const PointCloud before_cloud = map.ToPointCloud();

  auto second = map.Insert(cloud, 2);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(second->new_voxels, 0u);
  EXPECT_EQ(map.size(), before.size());
  const MapChunk after = map.TakeChanges();
  ASSERT_EQ(after.size(), before.size());
  const PointCloud after_cloud = map.ToPointCloud();
  for (size_t i = 0; i < after.size(); ++i) {
    EXPECT_EQ(after.keys[i], before.keys[i]);
    EXPECT_EQ(after.observations[i], 2 * before.observations[i]);
    EXPECT_EQ(map.Observations(after.keys[i]), after.observations[i]);
    EXPECT_NEAR(after.cloud.confidences[i], 2 * before.cloud.confidences[i], 1e-3);
    EXPECT_LT((after.cloud.positions[i] - before.cloud.positions[i]).norm(), /*max_position_change_m=*/1e-6);
    EXPECT_LT((after.cloud.normals[i] - before.cloud.normals[i]).norm(), /*max_normal_change=*/1e-5);
    EXPECT_EQ(after.cloud.colors[i], before.cloud.colors[i]);
    uint64_t keyframe = 0;
    ASSERT_TRUE(map.LastKeyframe(after.keys[i], &keyframe));
    EXPECT_EQ(keyframe, 2u);
  }
  EXPECT_EQ(after_cloud.size(), before_cloud.size());
  EXPECT_EQ(map.totals().merged_points, 2 * cloud.size());
}

TEST(GlobalMapTest, TakeChangesReturnsOnlyChangedVoxels) {
  const PointCloud cloud = RenderWorldCloud(0);
  GlobalMap map;
  ASSERT_TRUE(map.Insert(cloud, 1).ok());
  EXPECT_EQ(map.pending_changes(), map.size());
  const MapChunk all = map.TakeChanges();
  EXPECT_EQ(all.sequence, 1u);
  EXPECT_EQ(all.size(), map.size());
  EXPECT_EQ(all.cloud.size(), all.size());
  EXPECT_TRUE(all.cloud.IsConsistent());
  EXPECT_EQ(std::set<VoxelKey>(all.keys.begin(), all.keys.end()).size(), all.size());

  const MapChunk none = map.TakeChanges();
  EXPECT_EQ(none.sequence, 2u);
  EXPECT_TRUE(none.empty());

  // A few existing points plus a few far from the map.
  PointCloud update;
  std::mt19937 rng(3);
  std::uniform_int_distribution<size_t> pick(0, cloud.size() - 1);
  for (int i = 0; i < 40; ++i) {
    const size_t j = pick(rng);
    update.positions.push_back(cloud.positions[j]);
    update.normals.push_back(cloud.normals[j]);
    update.colors.push_back(cloud.colors[j]);
    update.confidences.push_back(0.5f);
  }
  for (int i = 0; i < 5; ++i) {
    update.positions.emplace_back(5.0f + 0.1f * i, -3.0f, 1.0f);
    update.normals.emplace_back(0, 0, 1);
    update.colors.emplace_back(10, 20, 30);
    update.confidences.push_back(1.0f);
  }
  const size_t size_before = map.size();
  auto stats = map.Insert(update, 7);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->new_voxels, 5u);
  EXPECT_EQ(map.size(), size_before + 5);
  const MapChunk changes = map.TakeChanges();
  EXPECT_EQ(changes.sequence, 3u);
  const std::set<VoxelKey> expected = VoxelsOf(map, update);
  EXPECT_EQ(std::set<VoxelKey>(changes.keys.begin(), changes.keys.end()), expected);
  EXPECT_EQ(changes.size(), expected.size());
  for (size_t i = 0; i < changes.size(); ++i) {
    uint64_t keyframe = 0;
    ASSERT_TRUE(map.LastKeyframe(changes.keys[i], &keyframe));
    EXPECT_EQ(keyframe, 7u);
    // The chunk carries each voxel's whole state, not just the update.
    EXPECT_EQ(changes.observations[i], map.Observations(changes.keys[i]));
  }
  EXPECT_TRUE(map.TakeChanges().empty());
}

// Clear (a map rebuilt from moved keyframes): no voxel survives, the next chunk says it replaces the
// map and goes on with the sequence, and the same cloud inserted again builds the same voxels anew (the
// cache of recent voxels must not hand back a cleared one).
TEST(GlobalMapTest, ClearEmptiesTheMapAndTheNextChunkReplacesIt) {
  const PointCloud cloud = RenderWorldCloud(0);
  GlobalMap map;
  ASSERT_TRUE(map.Insert(cloud, 1).ok());
  const MapChunk first = map.TakeChanges();
  EXPECT_FALSE(first.replaces_map);
  const size_t voxels = map.size();
  ASSERT_GT(voxels, 0u);
  map.Clear();
  EXPECT_TRUE(map.empty());
  EXPECT_EQ(map.pending_changes(), 0u);
  EXPECT_EQ(map.totals().merged_points, 0u);
  ASSERT_TRUE(map.Insert(cloud, 2).ok());
  EXPECT_EQ(map.size(), voxels);
  const MapChunk rebuilt = map.TakeChanges();
  EXPECT_TRUE(rebuilt.replaces_map);
  EXPECT_EQ(rebuilt.sequence, first.sequence + 1);
  ASSERT_EQ(rebuilt.size(), voxels);
  for (size_t i = 0; i < rebuilt.size(); ++i) {
    EXPECT_EQ(rebuilt.observations[i], first.observations[i]);
    EXPECT_EQ(rebuilt.keys[i], first.keys[i]);
    EXPECT_EQ(rebuilt.cloud.positions[i], first.cloud.positions[i]);
  }
  ASSERT_TRUE(map.Insert(cloud, 3).ok());
  EXPECT_FALSE(map.TakeChanges().replaces_map);  // only the first chunk after Clear
}

// MapOptions::min_keyframes: a voxel enters the output (ToPointCloud, TakeChanges, output_size) only
// once a second keyframe adds to it; inserts of one keyframe count once. A voxel held back is sent
// with the chunk of the keyframe that completes it.
TEST(GlobalMapTest, VoxelsSeenByOneKeyframeStayOutOfTheOutput) {
  const PointCloud first = RenderWorldCloud(0), second = RenderWorldCloud(3);
  MapOptions options;
  options.min_keyframes = 2;
  GlobalMap map(options);
  ASSERT_TRUE(map.Insert(first, 1).ok());
  ASSERT_TRUE(map.Insert(first, 1).ok());  // the same keyframe again
  EXPECT_GT(map.size(), 0u);
  EXPECT_EQ(map.output_size(), 0u);
  EXPECT_TRUE(map.ToPointCloud().empty());
  EXPECT_TRUE(map.TakeChanges().empty());
  ASSERT_TRUE(map.Insert(second, 2).ok());
  const std::set<VoxelKey> a = VoxelsOf(map, first), b = VoxelsOf(map, second);
  size_t shared = 0;
  for (VoxelKey k : b) shared += a.count(k);
  ASSERT_GT(shared, 1000u);
  EXPECT_EQ(map.output_size(), shared);
  EXPECT_EQ(map.ToPointCloud().size(), shared);
  const MapChunk chunk = map.TakeChanges();
  EXPECT_EQ(chunk.size(), shared);
  for (VoxelKey k : chunk.keys) EXPECT_TRUE(a.count(k) && b.count(k));
  options.min_keyframes = 0;
  EXPECT_FALSE(options.Check().ok());
}

TEST(GlobalMapTest, BadPointsAreSkippedAndCounted) {
  PointCloud cloud;
  auto add = [&](const Eigen::Vector3f& p, float confidence) {
    cloud.positions.push_back(p);
    cloud.confidences.push_back(confidence);
  };
  add({0.0105f, 0.0205f, 0.0305f}, 1.0f);
  add({kNaN, 0.0f, 0.0f}, 1.0f);
  add({0.0f, kNaN, 0.0f}, 1.0f);
  add({0.0f, 0.0f, kInf}, 1.0f);
  add({0.1f, 0.1f, 0.1f}, 0.0f);
  add({0.1f, 0.1f, 0.1f}, -1.0f);
  add({0.1f, 0.1f, 0.1f}, kNaN);
  add({1e6f, 0.0f, 0.0f}, 1.0f);  // 5e8 voxels of 2 mm: beyond the key range
  add({0.0107f, 0.0207f, 0.0307f}, 1.0f);
  GlobalMap map;
  auto stats = map.Insert(cloud, 1);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->merged_points, 2u);
  EXPECT_EQ(stats->skipped_non_finite, 3u);
  EXPECT_EQ(stats->skipped_bad_confidence, 3u);
  EXPECT_EQ(stats->skipped_out_of_range, 1u);
  EXPECT_EQ(stats->skipped(), 7u);
  EXPECT_EQ(map.size(), 1u);
  EXPECT_EQ(map.totals().skipped_non_finite, 3u);
  const PointCloud out = map.ToPointCloud();
  ASSERT_EQ(out.size(), 1u);
  EXPECT_TRUE(out.positions[0].allFinite());
  EXPECT_FALSE(out.HasNormals());
  EXPECT_FALSE(out.HasColors());

  // Mismatched attribute arrays are refused as a whole.
  PointCloud inconsistent = cloud;
  inconsistent.normals.resize(2);
  EXPECT_EQ(map.Insert(inconsistent, 2).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(map.size(), 1u);
  EXPECT_EQ(map.totals().merged_points, 2u);
  Rigid3d nan_pose;
  nan_pose.translation.x() = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(map.Insert(cloud, nan_pose, 2).status().code(), StatusCode::kInvalidArgument);
}

TEST(GlobalMapTest, ConfidenceWeightedMeansAndNormalFilling) {
  GlobalMap map;  // 2 mm voxels
  PointCloud a;
  a.positions = {{0.0002f, 0.0002f, 0.0002f}};
  a.normals = {{0, 0, 0}};  // no normal from this keyframe
  a.colors = {{200, 0, 0}};
  a.confidences = {1.0f};
  PointCloud b;
  b.positions = {{0.0010f, 0.0006f, 0.0014f}};
  b.normals = {{0, 0, 2}};  // not unit: renormalised
  b.colors = {{0, 100, 0}};
  b.confidences = {3.0f};
  PointCloud c;
  c.positions = {{0.0006f, 0.0010f, 0.0010f}};
  c.normals = {{1, 0, 0}};
  c.colors = {{0, 0, 40}};
  c.confidences = {1.0f};

  ASSERT_TRUE(map.Insert(a, 1).ok());
  PointCloud out = map.ToPointCloud();
  ASSERT_EQ(out.size(), 1u);
  ASSERT_TRUE(out.HasNormals());
  EXPECT_TRUE(out.normals[0].isZero()) << "no keyframe gave this voxel a normal yet";

  ASSERT_TRUE(map.Insert(b, 2).ok());
  ASSERT_TRUE(map.Insert(c, 3).ok());
  out = map.ToPointCloud();
  ASSERT_EQ(out.size(), 1u);
  const Eigen::Vector3f mean = (1.0f * a.positions[0] + 3.0f * b.positions[0] + 1.0f * c.positions[0]) / 5.0f;
  EXPECT_LT((out.positions[0] - mean).norm(), /*max_position_error_m=*/1e-7);
  const Eigen::Vector3f normal = Eigen::Vector3f(1, 0, 3).normalized();  // 3 * (0,0,1) + 1 * (1,0,0)
  EXPECT_LT((out.normals[0] - normal).norm(), /*max_normal_error=*/1e-6);
  EXPECT_EQ(out.colors[0], (Eigen::Matrix<uint8_t, 3, 1>(40, 60, 8)));  // (200, 300, 40) / 5
  EXPECT_FLOAT_EQ(out.confidences[0], 5.0f);

  EXPECT_EQ(map.ToPointCloud(/*min_confidence=*/5.5).size(), 0u);
  EXPECT_EQ(map.ToPointCloud(/*min_confidence=*/4.5).size(), 1u);
  EXPECT_EQ(map.ToPointCloud(0.0, /*min_observations=*/3).size(), 1u);
  EXPECT_EQ(map.ToPointCloud(0.0, /*min_observations=*/4).size(), 0u);
}

TEST(GlobalMapTest, InsertWithPoseMatchesInsertOfTransformedCloud) {
  synth::PresetOptions o;
  o.width = 128;
  o.height = 128;
  o.frames = 30;
  auto setup = synth::MakePreset("sphere-multicolor-sideways", o);
  ASSERT_TRUE(setup.ok()) << setup.status();
  const Rigid3d world_from_camera = synth::MakeTrajectory(setup->trajectory)[3].world_from_camera;
  const PointCloud in_camera = RenderKeyframeCloud(*setup, world_from_camera, 1);
  GlobalMap direct, posed;
  ASSERT_TRUE(direct.Insert(TransformCloud(in_camera, world_from_camera), 1).ok());
  ASSERT_TRUE(posed.Insert(in_camera, world_from_camera, 1).ok());
  const PointCloud a = direct.ToPointCloud();
  const PointCloud b = posed.ToPointCloud();
  // Float rounding may move a point across a voxel face: compare sizes loosely, shared voxels exactly.
  EXPECT_NEAR(static_cast<double>(a.size()), static_cast<double>(b.size()), 0.001 * a.size() + 2);
  const MapChunk ca = direct.TakeChanges();
  size_t compared = 0;
  for (size_t i = 0; i < ca.size(); ++i) {
    if (posed.Observations(ca.keys[i]) != ca.observations[i]) continue;
    ++compared;
  }
  EXPECT_GT(compared, ca.size() * 99 / 100);
}

TEST(GlobalMapTest, VoxelKeysRoundTrip) {
  for (const Eigen::Vector3i& v : {Eigen::Vector3i(0, 0, 0), Eigen::Vector3i(-1, 2, -3),
                                   Eigen::Vector3i(kMaxVoxelCoordinate, kMinVoxelCoordinate, 17),
                                   Eigen::Vector3i(kMinVoxelCoordinate, -1, kMaxVoxelCoordinate)}) {
    EXPECT_EQ(UnpackVoxelKey(PackVoxelKey(v)), v);
  }
  EXPECT_NE(PackVoxelKey({1, 0, 0}), PackVoxelKey({0, 1, 0}));
  EXPECT_THROW(PackVoxelKey({kMaxVoxelCoordinate + 1, 0, 0}), CheckError);

  GlobalMap map;
  Eigen::Vector3i v;
  ASSERT_TRUE(map.VoxelOf({-0.0001f, 0.0039f, 0.004f}, &v));
  EXPECT_EQ(v, Eigen::Vector3i(-1, 1, 2));
  EXPECT_FALSE(map.VoxelOf({kNaN, 0, 0}, &v));
  EXPECT_FALSE(map.VoxelOf({0, 3000.0f, 0}, &v));
}

TEST(GlobalMapTest, OptionsAreChecked) {
  MapOptions o;
  EXPECT_TRUE(o.Check().ok());
  o.voxel_m = 0;
  EXPECT_EQ(o.Check().code(), StatusCode::kInvalidArgument);
  o.voxel_m = std::nan("");
  EXPECT_EQ(o.Check().code(), StatusCode::kInvalidArgument);
  EXPECT_THROW(GlobalMap{o}, CheckError);
}

TEST(GlobalMapTest, ManyVoxelsSurviveRehashing) {
  GlobalMap map(MapOptions{0.01});
  PointCloud cloud;
  for (int x = -40; x < 40; ++x) {
    for (int y = -40; y < 40; ++y) {
      for (int z = 0; z < 4; ++z)
        cloud.positions.emplace_back(0.01f * x + 0.005f, 0.01f * y + 0.005f, 0.01f * z + 0.005f);
    }
  }
  ASSERT_TRUE(map.Insert(cloud, 1).ok());
  EXPECT_EQ(map.size(), cloud.size());
  ASSERT_TRUE(map.Insert(cloud, 2).ok());
  EXPECT_EQ(map.size(), cloud.size());
  for (const Eigen::Vector3f& p : cloud.positions) {
    Eigen::Vector3i v;
    ASSERT_TRUE(map.VoxelOf(p, &v));
    EXPECT_EQ(map.Observations(PackVoxelKey(v)), 2u);
  }
  EXPECT_EQ(map.Observations(PackVoxelKey({1000, 1000, 1000})), 0u);
}

}  // namespace
}  // namespace prism
