#include "server/session_store.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

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

}  // namespace
}  // namespace prism::server
