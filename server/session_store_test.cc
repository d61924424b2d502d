#include "server/session_store.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/codec/map_chunk_codec.h"
#include "core/io/ply_io.h"

namespace prism::server {
namespace {
namespace fs = std::filesystem;

v1::PoseUpdate Pose(uint64_t sequence, double x, v1::PoseUpdate::TrackingState state, bool refined) {
  v1::PoseUpdate p;
  p.set_frame_sequence_number(sequence);
  p.set_timestamp_ns(static_cast<int64_t>(1000 + sequence) * 1000000000LL);
  p.mutable_world_from_camera()->mutable_translation()->set_x(x);
  p.mutable_world_from_camera()->mutable_rotation()->set_w(1);
  p.set_state(state);
  p.set_refined(refined);
  return p;
}

std::string Read(const std::string& path) {
  std::ifstream f(path);
  std::stringstream s;
  s << f.rdbuf();
  return s.str();
}

// Frames 0-1 initialising, 2-3 tracked; at the end 0, 1 and 3 are refined. trajectory.txt keeps what
// was streamed; trajectory_final.txt has every tracked frame once, with its latest pose, in time order.
TEST(PoseLogTest, FinalTrajectoryHasTheLatestPoseOfEveryFrame) {
  const fs::path root = fs::temp_directory_path() / ("prism_pose_log_test_" + std::to_string(::getpid()));
  const fs::path dir = root / "sessions" / "s1";
  fs::remove_all(root);
  fs::create_directories(dir);
  {
    PoseLog log;
    ASSERT_TRUE(log.Open(dir.string()).ok());
    log.Append(Pose(0, 0.0, v1::PoseUpdate::TRACKING_STATE_INITIALISING, false));
    log.Append(Pose(1, 0.0, v1::PoseUpdate::TRACKING_STATE_INITIALISING, false));
    log.Append(Pose(2, 2.0, v1::PoseUpdate::TRACKING_STATE_TRACKING, false));
    log.Append(Pose(3, 3.0, v1::PoseUpdate::TRACKING_STATE_TRACKING, false));
    ASSERT_TRUE(log.WriteFinalTrajectory().ok());
    EXPECT_FALSE(fs::exists(dir / "trajectory_final.txt")) << "nothing refined yet";
    log.Append(Pose(1, 1.5, v1::PoseUpdate::TRACKING_STATE_TRACKING, true));
    log.Append(Pose(0, 0.5, v1::PoseUpdate::TRACKING_STATE_TRACKING, true));
    log.Append(Pose(3, 3.5, v1::PoseUpdate::TRACKING_STATE_TRACKING, true));
    ASSERT_TRUE(log.WriteFinalTrajectory().ok());
  }
  EXPECT_EQ(Read((dir / "trajectory.txt").string()), "1002.000000 2 0 0 0 0 0 1\n1003.000000 3 0 0 0 0 0 1\n");
  const std::string final_text = Read((dir / "trajectory_final.txt").string());
  EXPECT_EQ(final_text.substr(final_text.find('\n') + 1),
            "1000.000000 0.5 0 0 0 0 0 1\n1001.000000 1.5 0 0 0 0 0 1\n1002.000000 2 0 0 0 0 0 1\n"
            "1003.000000 3.5 0 0 0 0 0 1\n");
  // Resume from frame 3: frame 3 as streamed, then every refined pose whatever the client's cursor.
  const std::vector<v1::PoseUpdate> replay = SessionStore(root.string()).ReadPoses("s1", 3);
  ASSERT_EQ(replay.size(), 4u);
  EXPECT_FALSE(replay[0].refined());
  EXPECT_EQ(replay[0].frame_sequence_number(), 3u);
  for (size_t i = 1; i < replay.size(); ++i) EXPECT_TRUE(replay[i].refined());
  fs::remove_all(root);
}

// A session recovered from disk (the server stopped before its end) rebuilds map.ply from its chunks:
// a chunk with replaces_map (the map rebuilt at the final keyframe poses) voids the voxels before it.
TEST(SessionStoreTest, RebuiltMapStartsAgainAtAChunkThatReplacesTheMap) {
  const fs::path root = fs::temp_directory_path() / ("prism_store_replace_test_" + std::to_string(::getpid()));
  fs::remove_all(root);
  SessionStore store(root.string());
  StoredSession session;
  session.id = "s1-abcdef";
  session.resume_token = "token";
  session.voxel_m = 0.002;
  ASSERT_TRUE(store.Create(session).ok());
  // Three chunks: two voxels, one more voxel, then a rebuilt map of two other voxels.
  const std::vector<std::vector<Eigen::Vector3f>> points = {{{0.0011f, 0.0011f, 0.0011f}, {0.0051f, 0.0011f, 0.0011f}},
                                                            {{0.0091f, 0.0011f, 0.0011f}},
                                                            {{0.0011f, 0.0051f, 0.0011f}, {0.0011f, 0.0091f, 0.0011f}}};
  for (size_t i = 0; i < points.size(); ++i) {
    PointCloud cloud;
    cloud.positions = points[i];
    StatusOr<EncodedMapChunk> encoded = EncodeMapChunk(cloud, MapChunkCodecOptions());
    ASSERT_TRUE(encoded.ok()) << encoded.status();
    v1::MapChunk header;
    header.set_session_id(session.id);
    header.set_chunk_sequence_number(i + 1);
    header.set_num_points(static_cast<uint32_t>(encoded->num_points));
    header.set_payload_bytes(encoded->bytes.size());
    header.set_replaces_map(i == 2);
    ASSERT_TRUE(store.WriteChunk(session.id, header, encoded->bytes).ok());
  }
  StatusOr<size_t> n = store.RebuildMap(session.id, session.voxel_m);
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(*n, 2u);
  StatusOr<PointCloud> map = ReadPointCloudPly(store.Dir(session.id) + "/map.ply");
  ASSERT_TRUE(map.ok()) << map.status();
  ASSERT_EQ(map->size(), 2u);
  for (const Eigen::Vector3f& p : map->positions) EXPECT_GT(p.y(), 0.004f) << "a voxel from before the rebuild";
  fs::remove_all(root);
}

}  // namespace
}  // namespace prism::server
