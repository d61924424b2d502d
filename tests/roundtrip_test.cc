// The networked round trip: prism-synth renders a sequence, a real prism-server reconstructs it,
// prism-client streams it and writes trajectory.txt, map.ply and chunks/*.drc; the trajectory and
// the map are checked against the ground truth (Sim(3)-aligned through the trajectory, then
// prism-eval cloud on the object).
#include <prism/client/client.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/eval/statistics.h"
#include "core/io/calibration_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "tests/server_process.h"
#include "tests/sim3_from_trajectory.h"
#include "tests/test_process.h"
#include "tests/tracking_file.h"
#include "tools/client_rig.h"

namespace prism {
namespace {
namespace fs = std::filesystem;
using test::Bin;
using test::Execute;
using test::JsonNumber;
using test::ProcessResult;
using test::ServerProcess;

// Sanitizer builds (PRISM_SANITIZED_BUILD, defined for every target with PRISM_SANITIZE): the dense
// stage runs several times slower under TSan/ASan than prism-client's credit wait (20 s), its close
// wait (300 s) and the server's idle timeout (30 s) allow, so only there these waits are stretched.
// The frames and every assertion stay the same; in other builds no flag is added.
#ifdef PRISM_SANITIZED_BUILD
constexpr int kSanitizerWaitScale = 20;
#else
constexpr int kSanitizerWaitScale = 1;
#endif
// Extra prism-server and prism-client flags for the stretched waits (none in plain builds).
std::vector<std::string> WithServerWaitFlags(std::vector<std::string> flags) {
  if (kSanitizerWaitScale == 1) return flags;
  flags.push_back("--idle-timeout-ms");
  flags.push_back(std::to_string(30000 * kSanitizerWaitScale));
  return flags;
}
std::string ClientWaitFlags() {
  if (kSanitizerWaitScale == 1) return "";
  return " --timeout-ms " + std::to_string(20000 * kSanitizerWaitScale) + " --close-timeout-ms " +
         std::to_string(300000 * kSanitizerWaitScale);
}
// How long ServerProcess::Stop waits for the server to exit after SIGTERM (its default is 20 s).
constexpr int kServerStopTimeoutMs = 20000 * kSanitizerWaitScale;

class RoundTripTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("prism_roundtrip_test_" + std::to_string(getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  std::string P(const std::string& name) const { return (dir_ / name).string(); }
  // prism-client streaming the fixture's sequence (P("seq")) to `server`, without --out.
  std::string StreamCommand(const ServerProcess& server) const {
    return Bin("prism-client") + " stream --server " + server.endpoint() + " --sequence " + P("seq") +
           ClientWaitFlags();
  }
  fs::path dir_;
};

TEST_F(RoundTripTest, StreamedSequenceGivesTheTrajectoryAndAMapOfTheObject) {
  constexpr int kFrames = 60;
  ProcessResult r = Execute(Bin("prism-synth") + " --preset bunny-multicolor-forward --frames " +
                            std::to_string(kFrames) + " --out " + P("seq"));
  if (r.exit_code != 0 && r.out.find("not found") != std::string::npos) GTEST_SKIP() << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  ServerProcess server(P("data"), WithServerWaitFlags({"--keyframe-queue", "16"}), P("server.log"));
  ASSERT_TRUE(server.ok());
  r = Execute(StreamCommand(server) + " --out " + P("out"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "poses"), kFrames) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "errors"), 0) << r.out;
  const double chunks = JsonNumber(r.out, "chunks");
  ASSERT_GE(chunks, 1) << r.out;
  size_t drc = 0;
  std::string first_drc;
  for (const auto& e : fs::directory_iterator(P("out/chunks")))
    if (e.path().extension() == ".drc" && ++drc == 1) first_drc = e.path().string();
  EXPECT_EQ(static_cast<double>(drc), chunks);
  if (access("/usr/bin/draco_decoder", X_OK) == 0) {
    const ProcessResult d = Execute("/usr/bin/draco_decoder -i " + first_drc + " -o " + P("chunk.ply"));
    EXPECT_EQ(d.exit_code, 0) << d.out;
  }
  EXPECT_EQ(server.Stop(kServerStopTimeoutMs), 0);
  // The final adjustment moved the keyframes, so the server rebuilt its map at the final poses and sent
  // it as one chunk that replaces the map: the client's map is the server's, voxel for voxel in number
  // (the server's map.ply, written at the session's end, and the summary's map_points).
  EXPECT_NE(r.out.find("\"map_replaced\":true"), std::string::npos) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "map_points"), JsonNumber(r.out, "server_map_points")) << r.out;
  size_t server_maps = 0;
  for (const auto& e : fs::recursive_directory_iterator(P("data")))
    if (e.path().filename() == "map.ply") {
      ++server_maps;
      StatusOr<PointCloud> server_map = ReadPointCloudPly(e.path().string());
      ASSERT_TRUE(server_map.ok()) << server_map.status();
      EXPECT_EQ(static_cast<double>(server_map->size()), JsonNumber(r.out, "map_points"));
    }
  EXPECT_EQ(server_maps, 1u);

  // Align the streamed trajectory (metres per the session scale) to the ground truth.
  StatusOr<Sequence> seq = LoadSequence(P("seq"));
  ASSERT_TRUE(seq.ok());
  StatusOr<Trajectory> est = ReadTumTrajectory(P("out/trajectory.txt"));
  ASSERT_TRUE(est.ok()) << est.status();
  // Every frame is tracked once the initialisation frames' poses were refined at the end of the
  // session (lost ones would be left out of trajectory.txt).
  EXPECT_GE(JsonNumber(r.out, "refined_poses"), 1) << r.out;
  ASSERT_EQ(est->size(), static_cast<size_t>(kFrames));
  // Each frame's alignment came over the wire (PoseUpdate.tracking) for every frame tracked after the
  // initialisation: prism-client's tracking.txt, as prism-slam's (cli_test checks its figures against
  // the truth). The clean rendered scene keeps nearly every point an inlier.
  {
    constexpr int kMinTrackedRows = 40;        // of 60 frames, those after the initialisation
    constexpr double kMinMedianInliers = 0.9;  // as cli_test
    std::vector<test::TrackingRow> rows;
    std::string bad_line;
    ASSERT_TRUE(test::ReadTrackingFile(P("out/tracking.txt"), &rows, &bad_line)) << "tracking.txt: " << bad_line;
    std::vector<double> inliers;
    for (const test::TrackingRow& row : rows) {
      EXPECT_GE(row.keyframe_id, 0) << row.line;
      EXPECT_TRUE(row.visible_fraction > 0 && row.visible_fraction <= 1 && row.inlier_fraction > 0 &&
                  row.inlier_fraction <= 1 && row.step > 0 && row.iterations > 0)
          << row.line;
      inliers.push_back(row.inlier_fraction);
    }
    ASSERT_GE(static_cast<int>(inliers.size()), kMinTrackedRows);
    EXPECT_LE(inliers.size(), static_cast<size_t>(kFrames));
    EXPECT_GE(Median(inliers), kMinMedianInliers);
  }
  // Sim(3) from the trajectory (tests/sim3_from_trajectory.h): rotation from the camera orientations,
  // then scale and translation from the camera centres.
  const test::TrajectoryAlignment alignment = test::AlignTrajectory(*est, seq->groundtruth);
  ASSERT_TRUE(alignment.ok);
  ASSERT_EQ(alignment.pairs, est->size());
  const Sim3d& gt_from_est = alignment.gt_from_est;
  const double ate = alignment.ate_rmse_m, path = alignment.path_m;
  std::cout << "round trip: ATE " << ate << " m over a " << path << " m path, Sim(3) scale " << gt_from_est.scale
            << ", " << alignment.pairs << " tracked frames\n";

  // The map in the ground-truth frame, scored on the object.
  StatusOr<PointCloud> map = ReadPointCloudPly(P("out/map.ply"));
  ASSERT_TRUE(map.ok()) << map.status();
  ASSERT_GT(map->size(), 1000u);
  for (Eigen::Vector3f& p : map->positions) p = (gt_from_est * p.cast<double>()).cast<float>();
  map->normals.clear();
  ASSERT_TRUE(WritePointCloudPly(P("aligned.ply"), *map).ok());
  r = Execute(Bin("prism-eval") + " cloud --object-only --sequence " + P("seq") + " --cloud " + P("aligned.ply"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const double fscore = JsonNumber(r.out, "fscore"), accuracy = JsonNumber(r.out, "accuracy_median_m");
  std::cout << "round trip: " << kFrames << " frames, " << chunks << " chunks, " << map->size() << " map points; ATE "
            << ate << " m (" << 100 * ate / path << "% of the path); map on the object: F-score " << fscore
            << " at tau " << JsonNumber(r.out, "tau_m") << " m, accuracy median " << accuracy << " m, completeness "
            << JsonNumber(r.out, "completeness") << "\n";
  // The bars follow the SLAM's current accuracy (prism-slam alone: ATE 8% of the path on this preset,
  // positions-only alignment); they check that poses, scale and chunks put the map on the object
  // (a frame or scale mistake in the pipeline puts it tens of centimetres away: F-score 0).
  EXPECT_LT(ate / path, /*max_ate_fraction_of_path=*/0.35);
  EXPECT_LT(accuracy, /*max_map_accuracy_median_m=*/0.06);
  EXPECT_GE(fscore, /*min_map_fscore_at_1pct_of_object=*/0.05);
}

// A lens with distortion through the real server: prism-client sends the calibration with its
// distortion (camera.yaml of a sequence rendered through the lens), the server undistorts every frame
// (before, the session could not be opened), and the streamed poses follow the ground truth.
// Measured: 90 of 90 poses, ATE 0.33% of the path.
TEST_F(RoundTripTest, ADistortedCameraStreamsThroughTheServer) {
  constexpr int kFrames = 90;
  ProcessResult r = Execute(Bin("prism-synth") + " --preset armadillo-textured-forward --size 256x256 --frames " +
                            std::to_string(kFrames) + " --distortion -0.25,0.08,0,0,0 --out " + P("seq"));
  if (r.exit_code != 0 && r.out.find("mesh") != std::string::npos) GTEST_SKIP() << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  ServerProcess server(P("data"), WithServerWaitFlags({"--input-policy", "upload", "--keyframe-queue", "32"}),
                       P("server.log"));
  ASSERT_TRUE(server.ok());
  r = Execute(StreamCommand(server) + " --out " + P("out"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "poses"), kFrames) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "errors"), 0) << r.out;
  EXPECT_GE(JsonNumber(r.out, "chunks"), 1) << r.out;
  EXPECT_EQ(server.Stop(kServerStopTimeoutMs), 0);
  StatusOr<Sequence> seq = LoadSequence(P("seq"));
  ASSERT_TRUE(seq.ok());
  ASSERT_TRUE(seq->calibration.camera.HasDistortion());
  StatusOr<Trajectory> est = ReadTumTrajectory(P("out/trajectory.txt"));
  ASSERT_TRUE(est.ok()) << est.status();
  const test::TrajectoryAlignment alignment = test::AlignTrajectory(*est, seq->groundtruth);
  ASSERT_TRUE(alignment.ok);
  const double percent = 100.0 * alignment.ate_rmse_m / alignment.path_m;
  std::cout << "round trip, distorted lens: " << est->size() << " poses, ATE " << percent << "% of the path\n";
  EXPECT_LT(percent, /*max_ate_percent_of_path, the SLAM bar=*/1.0);
}

TEST_F(RoundTripTest, TwoConcurrentSessionsBothComplete) {
  ProcessResult r =
      Execute(Bin("prism-synth") + " --preset bunny-multicolor-forward --frames 24 --size 256x256 --out " + P("seq"));
  if (r.exit_code != 0 && r.out.find("not found") != std::string::npos) GTEST_SKIP() << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  ServerProcess server(P("data"), WithServerWaitFlags({"--max-sessions", "2"}), P("server.log"));
  ASSERT_TRUE(server.ok());
  const std::string client = StreamCommand(server);
  r = Execute("(" + client + " --out " + P("a") + " > " + P("a.json") + " 2>&1 & " + client + " --codec jpeg --out " +
              P("b") + " > " + P("b.json") + " 2>&1 & wait)");
  for (const char* name : {"a.json", "b.json"}) {
    const ProcessResult cat = Execute("cat " + P(name));
    EXPECT_EQ(JsonNumber(cat.out, "poses"), 24) << cat.out;
    EXPECT_EQ(test::JsonString(cat.out, "reason"), "closed by client") << cat.out;
  }
  EXPECT_EQ(server.Stop(kServerStopTimeoutMs), 0);
}

// Bad frames in the middle of a stream lose nothing else: prism-client does not send a frame it cannot
// decode (a warning, frames_unreadable), the server refuses one of the wrong size with an error the
// client counts, and the session goes on to its summary with a pose for every other frame.
TEST_F(RoundTripTest, AnUndecodableAndAWrongSizeFrameCostOnlyThemselves) {
  constexpr int kFrames = 24, kUndecodable = 12, kWrongSize = 16;
  ProcessResult r = Execute(Bin("prism-synth") + " --preset torus-textured-forward --frames " +
                            std::to_string(kFrames) + " --size 256x256 --out " + P("seq"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  StatusOr<Sequence> seq = LoadSequence(P("seq"));
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_EQ(seq->frames.size(), static_cast<size_t>(kFrames));
  std::ofstream(seq->Path(seq->frames[kUndecodable].rgb_file), std::ios::trunc) << "not a PNG";
  ASSERT_TRUE(cv::imwrite(seq->Path(seq->frames[kWrongSize].rgb_file), cv::Mat(96, 128, CV_8UC3, cv::Scalar::all(90))));
  ServerProcess server(P("data"), WithServerWaitFlags({"--input-policy", "upload"}), P("server.log"));
  ASSERT_TRUE(server.ok());
  r = Execute(StreamCommand(server) + " --out " + P("out"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("frame " + std::to_string(kUndecodable) + ": "), std::string::npos) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "frames_unreadable"), 1) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "frames_sent"), kFrames - 1) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "errors"), 1) << "the wrong-size frame, refused by the server: " << r.out;
  EXPECT_EQ(JsonNumber(r.out, "poses"), kFrames - 2) << r.out;
  EXPECT_EQ(test::JsonString(r.out, "reason"), "closed by client") << r.out;
  StatusOr<Trajectory> est = ReadTumTrajectory(P("out/trajectory.txt"));
  ASSERT_TRUE(est.ok()) << est.status();
  EXPECT_EQ(est->size(), static_cast<size_t>(kFrames - 2)) << "every other frame tracked";
  EXPECT_EQ(server.Stop(kServerStopTimeoutMs), 0);
}

// The server's default for a live camera's SLAM that has fallen behind its input
// (ServerOptions::skip_depth_update_backlog_live, 2): it tracks frames without their stereo depth update
// until it has caught up; an upload session's SLAM (skip-depth-update-backlog, 0) updates with every frame.
// Both sessions push the 256x256 dragon as fast as the server's frame credits allow, so once the SLAM
// tracks, frames are always waiting for it. Measured in one run: 59 of the live session's 90 frames
// without their update (the count depends on the machine's timing), none of the upload session's; ATE
// 0.33% (live) and 0.23% (upload) of the path.
TEST_F(RoundTripTest, ALiveSessionBehindItsInputSkipsDepthUpdatesAndAnUploadSessionDoesNot) {
  constexpr int kFrames = 90;
  ProcessResult r = Execute(Bin("prism-synth") + " --preset dragon-multicolor-sideways --size 256x256 --frames " +
                            std::to_string(kFrames) + " --out " + P("seq"));
  if (r.exit_code != 0 && r.out.find("mesh") != std::string::npos) GTEST_SKIP() << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  StatusOr<Sequence> seq = LoadSequence(P("seq"));
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_EQ(seq->frames.size(), static_cast<size_t>(kFrames));
  std::vector<cv::Mat> images;
  for (size_t i = 0; i < seq->frames.size(); ++i) {
    StatusOr<cv::Mat> rgb = seq->ReadRgb(i);
    ASSERT_TRUE(rgb.ok()) << rgb.status();
    images.push_back(*rgb);
  }
  ServerProcess server(P("data"), WithServerWaitFlags({"--keyframe-queue", "32"}), P("server.log"));
  ASSERT_TRUE(server.ok());
  for (const bool live : {true, false}) {
    SCOPED_TRACE(live ? "live" : "upload");
    client::SessionOptions options;
    options.live = live;
    options.timeout_ms = 20000 * kSanitizerWaitScale;
    std::unique_ptr<client::Session> session;
    client::Status st = client::Session::Open(server.endpoint(), ToClientRig(seq->calibration), options, &session);
    ASSERT_TRUE(st.ok()) << st.ToString();
    // The latest pose of each tracked frame (a refined one replaces the first), by timestamp.
    std::map<int64_t, Rigid3d> tracked;
    size_t poses = 0;
    // The scales of the refined poses after the last frame's pose: those of the session's end.
    std::vector<double> end_refined_scales;
    session->SetEventCallback([&](const client::Event& e) {
      if (e.kind != client::Event::Kind::kPose) return;
      poses += !e.pose.refined;
      if (e.pose.refined) end_refined_scales.push_back(e.pose.metres_per_unit);
      else end_refined_scales.clear();
      if (e.pose.state != client::TrackingState::kTracking) {
        tracked.erase(e.pose.timestamp_ns);
        return;
      }
      const auto& q = e.pose.rotation_xyzw;
      Rigid3d p;
      p.rotation = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).normalized();
      p.translation = Eigen::Vector3d(e.pose.translation[0], e.pose.translation[1], e.pose.translation[2]);
      tracked[e.pose.timestamp_ns] = p;
    });
    for (size_t i = 0; i < images.size(); ++i) {
      const int64_t ts = static_cast<int64_t>(std::llround(seq->frames[i].timestamp_s * 1e9));
      st = session->PushFrame(ts, images[i].ptr<uint8_t>(), images[i].cols, images[i].rows,
                              static_cast<int>(images[i].step));
      ASSERT_TRUE(st.ok()) << "frame " << i << ": " << st.ToString();
    }
    client::Summary summary;
    st = session->Close(300000 * kSanitizerWaitScale, &summary);
    ASSERT_TRUE(st.ok()) << st.ToString();
    Trajectory est;
    for (const auto& [ts, pose] : tracked) est.push_back({static_cast<double>(ts) * 1e-9, pose});
    const test::TrajectoryAlignment alignment = test::AlignTrajectory(est, seq->groundtruth);
    ASSERT_TRUE(alignment.ok);
    const double percent = 100.0 * alignment.ate_rmse_m / alignment.path_m;
    std::cout << (live ? "live" : "upload")
              << " session pushed as fast as credit allows: " << summary.frames_depth_update_skipped << " of "
              << kFrames << " frames without their depth update, " << summary.frames_dropped << " dropped, "
              << est.size() << " tracked, ATE " << percent << "% of the path\n";
    // A frame the live queue dropped has no pose; every other one has.
    EXPECT_EQ(poses + summary.frames_dropped, static_cast<size_t>(kFrames));
    // One scale at the end: the refined poses carry the summary's (the rebuilt map's), not an earlier
    // estimate. The initialisation frames' poses, provisional when sent, are always among them.
    EXPECT_GT(summary.metres_per_unit, 0);
    EXPECT_FALSE(end_refined_scales.empty());
    for (const double scale : end_refined_scales) EXPECT_EQ(scale, summary.metres_per_unit);
    if (live) {
      EXPECT_GT(summary.frames_depth_update_skipped, 0u);
    } else {
      EXPECT_EQ(summary.frames_depth_update_skipped, 0u);
      EXPECT_EQ(summary.frames_dropped, 0u);
    }
    EXPECT_GE(est.size(), static_cast<size_t>(kFrames) * 2 / 3);
    EXPECT_LT(percent, /*max_ate_percent_of_path, the SLAM bar=*/1.0);
  }
  EXPECT_EQ(server.Stop(kServerStopTimeoutMs), 0);
}

}  // namespace
}  // namespace prism
