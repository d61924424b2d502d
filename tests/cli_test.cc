// The command-line contract of prism-synth and prism-eval, run as real processes: a rendered
// sequence evaluated against itself gives zeros, against a perturbed copy gives the perturbation.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/eval/statistics.h"
#include "core/io/calibration_io.h"
#include "core/io/image_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "tests/test_process.h"
#include "tests/tracking_file.h"

namespace prism {
namespace {
namespace fs = std::filesystem;

using test::Bin;
using test::Execute;
using test::JsonNumber;
using test::ProcessResult;

class CliTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new fs::path(fs::temp_directory_path() / ("prism_cli_test_" + std::to_string(::getpid())));
    fs::remove_all(*dir_);
    fs::create_directories(*dir_);
    const ProcessResult r =
        Execute(Bin("prism-synth") + " --preset sphere-multicolor-sideways --frames 24 --size 128x96 --seed 3" +
                " --out " + Seq() + " --gt-cloud " + (*dir_ / "gt.ply").string());
    ASSERT_EQ(r.exit_code, 0) << r.out;
  }
  static void TearDownTestSuite() {
    fs::remove_all(*dir_);
    delete dir_;
  }
  static std::string Seq() { return (*dir_ / "seq").string(); }
  static std::string P(const std::string& name) { return (*dir_ / name).string(); }
  static fs::path* dir_;
};
fs::path* CliTest::dir_ = nullptr;

TEST_F(CliTest, ListPresetsPrintsOneNamePerLineDemoFirst) {
  const ProcessResult r = Execute(Bin("prism-synth") + " --list-presets");
  ASSERT_EQ(r.exit_code, 0);
  EXPECT_EQ(r.out.substr(0, r.out.find('\n')), "bunny-multicolor-forward");
  EXPECT_GE(std::count(r.out.begin(), r.out.end(), '\n'), 10);
  EXPECT_EQ(r.out.find(' '), std::string::npos) << "names only, one per line";
}

TEST_F(CliTest, BadArgumentsAndInputsFailWithAMessage) {
  const std::pair<std::string, std::string> cases[] = {
      {Bin("prism-synth") + " --frames many --preset x --out /tmp/x", "--frames"},
      {Bin("prism-synth") + " --preset no-such-preset --out " + P("none"), "unknown preset"},
      {Bin("prism-synth") + " --bogus", "unknown argument"},
      {Bin("prism-eval") + " traj --gt " + P("missing.txt") + " --est " + P("missing.txt"), "missing.txt"},
      {Bin("prism-eval") + " traj --gt " + Seq() + "/groundtruth.txt", "--est"},
      {Bin("prism-eval") + " cloud --sequence " + P("nope") + " --cloud " + P("gt.ply"), "nope"},
      {Bin("prism-eval") + " frobnicate", "frobnicate"},
  };
  for (const auto& [cmd, needle] : cases) {
    const ProcessResult r = Execute(cmd);
    EXPECT_NE(r.exit_code, 0) << cmd;
    EXPECT_NE(r.out.find(needle), std::string::npos) << cmd << " said: " << r.out;
  }
  for (const char* tool : {"prism-synth", "prism-eval"}) {
    const ProcessResult r = Execute(Bin(tool) + " --help");
    EXPECT_EQ(r.exit_code, 0) << tool;
    EXPECT_NE(r.out.find("sage:"), std::string::npos) << tool;  // "usage:" or "Usage:"
  }
}

TEST_F(CliTest, TrajectoryAgainstItselfIsZeroAndAgainstAPerturbedCopyIsThePerturbation) {
  const std::string gt = Seq() + "/groundtruth.txt";
  ProcessResult r = Execute(Bin("prism-eval") + " traj --gt " + gt + " --est " + gt + " --align none");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "ate_rmse_m"), 0.0);
  EXPECT_EQ(JsonNumber(r.out, "rpe_trans_rmse_m"), 0.0);
  EXPECT_EQ(JsonNumber(r.out, "rpe_rot_rmse_deg"), 0.0);
  EXPECT_EQ(JsonNumber(r.out, "pairs"), 24);

  // Every position moved by 1 cm: unaligned ATE is exactly 1 cm, RPE stays 0, SE(3) alignment removes it.
  Trajectory traj = ReadTumTrajectory(gt).value();
  for (TimedPose& p : traj) p.world_from_camera.translation += Eigen::Vector3d(0.006, 0.0, 0.008);
  ASSERT_TRUE(WriteTumTrajectory(P("shifted.txt"), traj).ok());
  r = Execute(Bin("prism-eval") + " traj --gt " + gt + " --est " + P("shifted.txt") + " --align none");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NEAR(JsonNumber(r.out, "ate_rmse_m"), 0.01, /*file rounding=*/1e-6);
  EXPECT_NEAR(JsonNumber(r.out, "rpe_trans_rmse_m"), 0.0, 1e-6);
  r = Execute(Bin("prism-eval") + " traj --gt " + gt + " --est " + P("shifted.txt") + " --align se3");
  EXPECT_NEAR(JsonNumber(r.out, "ate_rmse_m"), 0.0, 1e-6);

  // A similarity transform (scale 2.5) is undone by Sim(3) alignment, which reports the scale.
  const Sim3d s(2.5, Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, -2, 0.5).normalized())),
                Eigen::Vector3d(1, 2, -3));
  traj = ReadTumTrajectory(gt).value();
  for (TimedPose& p : traj) p.world_from_camera = s.TransformPose(p.world_from_camera);
  ASSERT_TRUE(WriteTumTrajectory(P("sim3.txt"), traj).ok());
  r = Execute(Bin("prism-eval") + " traj --gt " + gt + " --est " + P("sim3.txt") + " --align sim3");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NEAR(JsonNumber(r.out, "ate_rmse_m"), 0.0, 1e-5);
  EXPECT_NEAR(JsonNumber(r.out, "scale"), 1 / 2.5, 1e-6);
  EXPECT_NEAR(JsonNumber(r.out, "orientation_rmse_deg"), 0.0, /*file rounding=*/1e-3);
  EXPECT_NEAR(JsonNumber(r.out, "net_rotation_est_deg"), JsonNumber(r.out, "net_rotation_gt_deg"), 1e-3);

  // Every camera turned by 3 degrees about its own axis: the positions and the ATE stay, the orientation
  // error is the turn.
  traj = ReadTumTrajectory(gt).value();
  for (TimedPose& p : traj)
    p.world_from_camera.rotation = p.world_from_camera.rotation *
                                   Eigen::Quaterniond(Eigen::AngleAxisd(3.0 * M_PI / 180, Eigen::Vector3d::UnitY()));
  ASSERT_TRUE(WriteTumTrajectory(P("turned.txt"), traj).ok());
  r = Execute(Bin("prism-eval") + " traj --gt " + gt + " --est " + P("turned.txt") + " --align se3");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NEAR(JsonNumber(r.out, "ate_rmse_m"), 0.0, 1e-5);
  EXPECT_NEAR(JsonNumber(r.out, "orientation_rmse_deg"), 3.0, 1e-3);
  EXPECT_NEAR(JsonNumber(r.out, "orientation_max_deg"), 3.0, 1e-3);
}

TEST_F(CliTest, NormalsAgainstItselfIsZeroAndRotatedByFiveDegreesIsFive) {
  ProcessResult r = Execute(Bin("prism-eval") + " normals --sequence " + Seq() + " --normals " + Seq() + "/normals");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "mean_deg"), 0.0);
  EXPECT_EQ(JsonNumber(r.out, "frames"), 24);

  const Sequence seq = LoadSequence(Seq()).value();
  fs::create_directories(P("rotated"));
  for (size_t i = 0; i < seq.frames.size(); i += 6) {
    cv::Mat n = seq.ReadNormals(i).value();
    // A plain loop, not cv::Mat::forEach: OpenCV joins its TBB workers inside uninstrumented libraries,
    // so under TSan every pixel written in the lambda looked like a race with WriteNormalPng's reads.
    for (auto it = n.begin<cv::Vec3f>(); it != n.end<cv::Vec3f>(); ++it) {
      cv::Vec3f& v = *it;
      if (v[0] == 0 && v[1] == 0 && v[2] == 0) continue;
      // Rotate by 5 degrees about an axis perpendicular to the normal: the angle is exactly 5.
      const Eigen::Vector3f normal(v[0], v[1], v[2]);
      Eigen::Vector3f axis = normal.cross(Eigen::Vector3f::UnitX());
      if (axis.norm() < 1e-3f) axis = normal.cross(Eigen::Vector3f::UnitY());
      const Eigen::Vector3f w = Eigen::AngleAxisf(5.0f * static_cast<float>(M_PI) / 180.f, axis.normalized()) * normal;
      v = cv::Vec3f(w.x(), w.y(), w.z());
    }
    ASSERT_TRUE(WriteNormalPng(P("rotated/") + fs::path(seq.frames[i].normal_file).filename().string(), n).ok());
  }
  r = Execute(Bin("prism-eval") + " normals --sequence " + Seq() + " --normals " + P("rotated") + " --object-only");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NEAR(JsonNumber(r.out, "mean_deg"), 5.0, /*quantisation=*/0.01);
  EXPECT_NEAR(JsonNumber(r.out, "median_deg"), 5.0, 0.01);
  EXPECT_EQ(JsonNumber(r.out, "frames"), 4);
}

TEST_F(CliTest, CloudAgainstTheSurfaceIsPerfectAndAShiftedCopyIsOffByTheShift) {
  ProcessResult r = Execute(Bin("prism-eval") + " cloud --sequence " + Seq() + " --cloud " + P("gt.ply"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_LT(JsonNumber(r.out, "accuracy_m"), /*voxel averaging=*/0.001);
  EXPECT_GT(JsonNumber(r.out, "completeness"), 0.99);
  EXPECT_GT(JsonNumber(r.out, "fscore"), 0.99);

  PointCloud cloud = ReadPointCloudPly(P("gt.ply")).value();
  for (auto& p : cloud.positions) p.z() += 0.02f;  // 2 cm up: far beyond tau = 5 mm
  ASSERT_TRUE(WritePointCloudPly(P("shifted.ply"), cloud).ok());
  r = Execute(Bin("prism-eval") + " cloud --sequence " + Seq() + " --cloud " + P("shifted.ply"));
  ASSERT_EQ(r.exit_code, 0) << r.out;
  // Points on the ground move straight up by 2 cm; object points end nearer other surface.
  EXPECT_GT(JsonNumber(r.out, "accuracy_median_m"), 0.015);
  EXPECT_LE(JsonNumber(r.out, "accuracy_median_m"), 0.0205);
  EXPECT_LT(JsonNumber(r.out, "fscore"), 0.2);
}

}  // namespace
}  // namespace prism

namespace prism {
namespace {

// prism-slam's tracking.txt against the ground truth of its sequence: a line per frame aligned against a
// keyframe (every tracked frame but the first keyframe's, on a run that never relocalises), fractions
// within [0, 1], and the step from the previous frame as a fraction of the keyframe's
// mean depth equal to the true one (the true translation times the true mean inverse depth over the
// keyframe's pixels with a depth) within kStepTolerance in the median. The smooth synthetic path leaves
// the constant-velocity guess little to correct.
void ExpectTrackingFileMatchesTheTruth(const std::string& seq_dir, const std::string& out) {
  constexpr double kStepTolerance = 0.1;        // median ratio of the reported to the true step, minus 1
  constexpr double kMinMedianInliers = 0.9;     // median inlier fraction on a clean rendered scene
  constexpr double kMaxGuessCorrection = 0.25;  // median correction of the guess, in medians of the step
  StatusOr<Sequence> seq = LoadSequence(seq_dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  auto frame_at = [&](double t) {
    for (size_t i = 0; i < seq->frames.size(); ++i)
      if (std::abs(seq->frames[i].timestamp_s - t) < 1e-4) return static_cast<int>(i);
    return -1;
  };
  std::map<int, double> keyframe_timestamp;
  {
    std::ifstream in(out + "/keyframes/keyframes.txt");
    std::string line;
    while (std::getline(in, line)) {
      if (line.empty() || line[0] == '#') continue;
      std::istringstream f(line);
      int id = 0;
      int64_t frame_id = 0;
      double t = 0;
      f >> id >> frame_id >> t;
      keyframe_timestamp[id] = t;
    }
  }
  std::map<int, double> keyframe_mean_inverse_depth;  // true, over the keyframe's estimated pixels
  auto true_mean_inverse_depth = [&](int id) {
    auto it = keyframe_mean_inverse_depth.find(id);
    if (it != keyframe_mean_inverse_depth.end()) return it->second;
    double sum = 0;
    int n = 0;
    const int k = keyframe_timestamp.count(id) ? frame_at(keyframe_timestamp[id]) : -1;
    char name[32];
    std::snprintf(name, sizeof(name), "%06d_idepth.tiff", id);
    const cv::Mat estimated = cv::imread(out + "/keyframes/" + name, cv::IMREAD_UNCHANGED);
    StatusOr<cv::Mat> depth = k >= 0 ? seq->ReadDepth(static_cast<size_t>(k)) : StatusOr<cv::Mat>(cv::Mat());
    if (depth.ok() && !estimated.empty() && estimated.type() == CV_32F && estimated.size() == depth->size())
      for (int y = 0; y < depth->rows; ++y)
        for (int x = 0; x < depth->cols; ++x)
          if (estimated.at<float>(y, x) > 0 && depth->at<float>(y, x) > 0) sum += 1.0 / depth->at<float>(y, x), ++n;
    return keyframe_mean_inverse_depth[id] = n > 0 ? sum / n : 0.0;
  };
  std::vector<test::TrackingRow> rows;
  std::string bad_line;
  ASSERT_TRUE(test::ReadTrackingFile(out + "/tracking.txt", &rows, &bad_line)) << "tracking.txt: " << bad_line;
  std::vector<double> ratios, inliers, steps, corrections;
  for (const test::TrackingRow& row : rows) {
    EXPECT_GE(row.keyframe_id, 0) << row.line;
    EXPECT_TRUE(row.visible_fraction >= 0 && row.visible_fraction <= 1 && row.inlier_fraction >= 0 &&
                row.inlier_fraction <= 1)
        << row.line;
    EXPECT_GT(row.iterations, 0) << row.line;
    const int i = frame_at(row.timestamp);
    ASSERT_GT(i, 0) << row.line;
    StatusOr<Rigid3d> a = seq->GroundTruthPose(static_cast<size_t>(i - 1)),
                      b = seq->GroundTruthPose(static_cast<size_t>(i));
    ASSERT_TRUE(a.ok() && b.ok());
    const double true_step = (b->translation - a->translation).norm() * true_mean_inverse_depth(row.keyframe_id);
    ASSERT_GT(true_step, 0) << row.line;
    ratios.push_back(row.step / true_step);
    inliers.push_back(row.inlier_fraction);
    steps.push_back(row.step);
    corrections.push_back(row.guess_correction);
  }
  // Every frame tracked but the first keyframe's own: the initialisation's buffered frames too (from its
  // last pass; before the forty-fourth round they had no line).
  StatusOr<Trajectory> tracked = ReadTumTrajectory(out + "/trajectory.txt");
  ASSERT_TRUE(tracked.ok()) << tracked.status();
  EXPECT_EQ(rows.size() + 1, tracked->size()) << "a line per tracked frame but the first keyframe's";
  ASSERT_GE(rows.size(), 40u);
  EXPECT_NEAR(Median(ratios), 1.0, kStepTolerance);
  EXPECT_GE(Median(inliers), kMinMedianInliers);
  EXPECT_LT(Median(corrections), kMaxGuessCorrection * Median(steps));
}

// prism-slam on a short rendered sequence: every output file is written and the summary says how
// many frames were tracked; prism-preview renders its semi-dense cloud to a PNG.
TEST(SlamCliTest, WritesTrajectoryKeyframesCloudAndSummary) {
  const fs::path dir = fs::temp_directory_path() / ("prism_slam_cli_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  const std::string seq = (dir / "seq").string(), out = (dir / "out").string();
  ProcessResult r = Execute(Bin("prism-synth") + " --preset bunny-multicolor-forward --frames 150 --out " + seq);
  if (r.exit_code != 0 && r.out.find("mesh") != std::string::npos)
    GTEST_SKIP() << "bunny mesh not installed: " << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  r = Execute(Bin("prism-slam") + " --sequence " + seq + " --out " + out + " --max-frames 60 --log-level debug");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("keyframe adjustment"), std::string::npos) << "--log-level debug prints each adjustment";
  EXPECT_EQ(JsonNumber(r.out, "frames"), 60);
  EXPECT_EQ(JsonNumber(r.out, "lost_frames"), 0);
  EXPECT_GE(JsonNumber(r.out, "keyframes"), 2);
  EXPECT_GT(JsonNumber(r.out, "ate_percent_of_path"), 0);
  StatusOr<Trajectory> traj = ReadTumTrajectory(out + "/trajectory.txt");
  ASSERT_TRUE(traj.ok()) << traj.status();
  EXPECT_EQ(traj->size(), 60u);
  EXPECT_TRUE(fs::exists(out + "/keyframes/keyframes.txt"));
  EXPECT_TRUE(fs::exists(out + "/keyframes/000000_idepth.tiff"));
  EXPECT_TRUE(fs::exists(out + "/states.txt"));
  ExpectTrackingFileMatchesTheTruth(seq, out);
  StatusOr<PointCloud> cloud = ReadPointCloudPly(out + "/semidense.ply");
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  EXPECT_GT(cloud->size(), 1000u);
  r = Execute(Bin("prism-preview") + " --cloud " + out + "/semidense.ply --trajectory " + out +
              "/trajectory.txt --size 200x150 --out " + out + "/preview.png");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  StatusOr<cv::Mat> png = ReadRgbImage(out + "/preview.png");
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_EQ(png->cols, 200);
  EXPECT_LT(cv::mean(*png)[0], 254.0) << "the picture shows points";
  for (const std::string& cmd : {Bin("prism-slam") + " --out " + out,
                                 Bin("prism-slam") + " --sequence " + seq + " --out " + out + " --log-level loud",
                                 Bin("prism-slam") + " --sequence " + (dir / "none").string() + " --out " + out,
                                 Bin("prism-preview") + " --cloud " + (dir / "none.ply").string() + " --out x.png"}) {
    r = Execute(cmd);
    EXPECT_NE(r.exit_code, 0) << cmd;
    EXPECT_FALSE(r.out.empty()) << cmd;
  }
  fs::remove_all(dir);
}

// A frame that cannot be decoded and one of the wrong size, in the middle of a sequence: prism-slam
// skips both with a warning naming them, tracks the rest without loss and within the ATE bar,
// and numbers its keyframes by their frames in the sequence; with --on-bad-frame stop it ends at the
// first one with exit status 1 but still writes the trajectory of the frames before it.
TEST(SlamCliTest, SkipsUndecodableAndWrongSizeFramesOrStopsAtThemKeepingTheRest) {
  constexpr int kFrames = 60, kUndecodable = 19, kWrongSize = 40;
  constexpr double kMaxAtePercent = 1.0;  // the bar, % of the path
  const fs::path dir = fs::temp_directory_path() / ("prism_slam_bad_frames_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  const std::string seq = (dir / "seq").string(), out = (dir / "out").string(), out_stop = (dir / "stop").string();
  ProcessResult r = Execute(Bin("prism-synth") + " --preset torus-textured-forward --frames " +
                            std::to_string(kFrames) + " --out " + seq);
  ASSERT_EQ(r.exit_code, 0) << r.out;
  StatusOr<Sequence> sequence = LoadSequence(seq);
  ASSERT_TRUE(sequence.ok()) << sequence.status();
  ASSERT_EQ(sequence->frames.size(), static_cast<size_t>(kFrames));
  const fs::path undecodable = fs::path(seq) / sequence->frames[kUndecodable].rgb_file;
  std::ofstream(undecodable, std::ios::trunc) << "not a PNG";
  ASSERT_TRUE(cv::imwrite((fs::path(seq) / sequence->frames[kWrongSize].rgb_file).string(),
                          cv::Mat(96, 128, CV_8UC3, cv::Scalar(40, 80, 120))));

  r = Execute(Bin("prism-slam") + " --sequence " + seq + " --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("frame " + std::to_string(kUndecodable) + " "), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("frame " + std::to_string(kWrongSize) + " "), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("128x96"), std::string::npos) << "the wrong size is named";
  EXPECT_EQ(JsonNumber(r.out, "skipped_frames"), 2);
  EXPECT_EQ(JsonNumber(r.out, "frames"), kFrames - 2);
  EXPECT_EQ(JsonNumber(r.out, "lost_frames"), 0);
  EXPECT_LE(JsonNumber(r.out, "ate_percent_of_path"), kMaxAtePercent);
  std::printf("two bad frames skipped: ATE %.3f%% of the path, depth median %.2f%%\n",
              JsonNumber(r.out, "ate_percent_of_path"), 100.0 * JsonNumber(r.out, "depth_median_rel_error"));
  StatusOr<Trajectory> traj = ReadTumTrajectory(out + "/trajectory.txt");
  ASSERT_TRUE(traj.ok()) << traj.status();
  EXPECT_EQ(traj->size(), static_cast<size_t>(kFrames - 2));
  for (const TimedPose& p : *traj) {
    EXPECT_GT(std::abs(p.timestamp_s - sequence->frames[kUndecodable].timestamp_s), 1e-4);
    EXPECT_GT(std::abs(p.timestamp_s - sequence->frames[kWrongSize].timestamp_s), 1e-4);
  }
  // keyframes.txt: id frame_id timestamp ..., frame_id the index in the sequence.
  std::ifstream index(out + "/keyframes/keyframes.txt");
  std::string line;
  int keyframes = 0, after_a_skip = 0;
  while (std::getline(index, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream in(line);
    int id = -1;
    long frame = -1;
    double timestamp = 0;
    ASSERT_TRUE(in >> id >> frame >> timestamp) << line;
    ASSERT_GE(frame, 0) << line;
    ASSERT_LT(frame, kFrames) << line;
    EXPECT_NEAR(timestamp, sequence->frames[static_cast<size_t>(frame)].timestamp_s, 1e-6) << line;
    ++keyframes;
    if (frame > kUndecodable) ++after_a_skip;
  }
  EXPECT_GE(keyframes, 3);
  EXPECT_GE(after_a_skip, 1) << "the check above covers keyframes whose frame ids differ from the SLAM's count";

  r = Execute(Bin("prism-slam") + " --sequence " + seq + " --out " + out_stop + " --on-bad-frame stop");
  EXPECT_EQ(r.exit_code, 1) << r.out;
  EXPECT_NE(r.out.find("stopped at frame " + std::to_string(kUndecodable) + " "), std::string::npos) << r.out;
  traj = ReadTumTrajectory(out_stop + "/trajectory.txt");
  ASSERT_TRUE(traj.ok()) << traj.status();
  EXPECT_EQ(traj->size(), static_cast<size_t>(kUndecodable)) << "every frame before the bad one";
  EXPECT_TRUE(fs::exists(out_stop + "/summary.json"));
  EXPECT_TRUE(fs::exists(out_stop + "/semidense.ply"));
  r = Execute(Bin("prism-slam") + " --sequence " + seq + " --out " + out_stop + " --on-bad-frame ignore");
  EXPECT_NE(r.exit_code, 0) << "skip or stop only";
  // A sequence of nothing but bad frames is an error, not an empty success.
  const fs::path junk = dir / "junk";
  fs::create_directories(junk / "rgb");
  fs::copy_file(fs::path(seq) / "camera.yaml", junk / "camera.yaml");
  std::ofstream junk_index(junk / "rgb.txt");
  for (int i = 0; i < 3; ++i) {
    const std::string name = "rgb/" + std::to_string(i) + ".png";
    junk_index << i << " " << name << "\n";
    std::ofstream(junk / name) << "not a PNG either";
  }
  junk_index.close();
  r = Execute(Bin("prism-slam") + " --sequence " + junk.string() + " --out " + (dir / "junk_out").string());
  EXPECT_EQ(r.exit_code, 1) << r.out;
  EXPECT_NE(r.out.find("none of the sequence's 3 frames could be used"), std::string::npos) << r.out;
  fs::remove_all(dir);
}

// One SLAM configuration for every entry point (core/slam/slam_config.h): prism-slam takes a config
// file and --set, writes every option it ran with to slam_config.txt, and that file run again gives the
// same trajectory; the settings take effect (fewer keyframes at a larger keyframe distance); bad keys,
// values and files are refused with the reason; prism-server reads the same keys.
TEST(SlamCliTest, OneSlamConfigForEveryEntryPoint) {
  const fs::path dir = fs::temp_directory_path() / ("prism_slam_config_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  const std::string seq = (dir / "seq").string();
  ProcessResult r =
      Execute(Bin("prism-synth") + " --preset sphere-multicolor-sideways --frames 60 --size 256x256 --out " + seq);
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::string slam = Bin("prism-slam") + " --no-eval --sequence " + seq + " --out ";

  r = Execute(slam + (dir / "default").string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const double default_keyframes = JsonNumber(r.out, "keyframes");
  const std::string default_config = test::ReadFileText(dir / "default" / "slam_config.txt");
  EXPECT_NE(default_config.find("\nkeyframe_distance_fraction = 0.09\n"), std::string::npos) << default_config;

  {
    std::ofstream cfg(dir / "my.cfg");
    cfg << "# wider keyframe spacing\nkeyframe_distance_fraction = 0.18\nloop-closure = off\n";
  }
  r = Execute(slam + (dir / "a").string() + " --slam-config " + (dir / "my.cfg").string() +
              " --set tracker.min_gradient=5 --no-final-adjustment");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_LT(JsonNumber(r.out, "keyframes"), default_keyframes) << "the keyframe distance took effect";
  const std::string written = test::ReadFileText(dir / "a" / "slam_config.txt");
  for (const char* line : {"\nkeyframe_distance_fraction = 0.18\n", "\nloop_closure = false\n",
                           "\ntracker.min_gradient = 5\n", "\nfinal_adjustment = false\n"})
    EXPECT_NE(written.find(line), std::string::npos) << line << " in\n" << written;
  // The written file reproduces the run.
  r = Execute(slam + (dir / "b").string() + " --slam-config " + (dir / "a" / "slam_config.txt").string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(test::ReadFileText(dir / "b" / "slam_config.txt"), written);
  EXPECT_EQ(test::ReadFileText(dir / "b" / "trajectory.txt"), test::ReadFileText(dir / "a" / "trajectory.txt"));

  const std::pair<std::string, std::string> bad[] = {
      {" --set tracker.min_gradiant=5", "nearest: 'tracker.min_gradient'"},
      {" --set keyframe_window=three", "bad value 'three'"},
      {" --set keyframe_window=2", "keyframe_window must be >= 3"},
      {" --set loop_closure", "--set expects KEY=VALUE"},
      {" --slam-config " + (dir / "none.cfg").string(), "cannot read SLAM config"},
  };
  for (const auto& [args, expect] : bad) {
    r = Execute(slam + (dir / "bad").string() + args);
    EXPECT_NE(r.exit_code, 0) << args;
    EXPECT_NE(r.out.find(expect), std::string::npos) << args << ": " << r.out;
  }
  // prism-server: the same keys as slam.KEY; it refuses bad ones before it listens.
  for (const auto& [args, expect] : std::vector<std::pair<std::string, std::string>>{
           {" --slam.tracker.min_gradiant 5", "nearest: 'tracker.min_gradient'"},
           {" --slam.keyframe_window 2", "keyframe_window must be >= 3"},
           {" --slam-config " + (dir / "none.cfg").string(), "cannot read SLAM config"}}) {
    r = Execute(Bin("prism-server") + " --data-dir " + (dir / "data").string() + args);
    EXPECT_EQ(r.exit_code, 2) << args << ": " << r.out;
    EXPECT_NE(r.out.find(expect), std::string::npos) << args << ": " << r.out;
  }
  fs::remove_all(dir);
}

// A lens with distortion (prism-synth renders through it and writes it to camera.yaml): prism-slam
// remaps every frame into an undistorted pinhole camera, writes that camera to camera.yaml, and the
// trajectory and the keyframe depth (scored in the undistorted camera) stay within the SLAM's bars.
// Measured: 0.29% of the path, depth 3.1% (256x256, 90 frames, armadillo, k1 = -0.25).
TEST(SlamCliTest, ADistortedSequenceIsUndistortedAndTracked) {
  const fs::path dir = fs::temp_directory_path() / ("prism_slam_distorted_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  const std::string seq = (dir / "seq").string(), out = (dir / "out").string();
  ProcessResult r = Execute(Bin("prism-synth") +
                            " --preset armadillo-textured-forward --frames 90 --size 256x256 "
                            "--distortion -0.25,0.08,0,0,0 --out " +
                            seq);
  if (r.exit_code != 0 && r.out.find("mesh") != std::string::npos)
    GTEST_SKIP() << "armadillo mesh not installed: " << r.out;
  ASSERT_EQ(r.exit_code, 0) << r.out;
  StatusOr<RigCalibration> rendered = ReadCalibrationYaml(seq + "/camera.yaml");
  ASSERT_TRUE(rendered.ok()) << rendered.status();
  EXPECT_EQ(rendered->camera.distortion[0], -0.25);
  r = Execute(Bin("prism-slam") + " --sequence " + seq + " --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("\"undistorted\": true"), std::string::npos) << r.out;
  EXPECT_EQ(JsonNumber(r.out, "lost_frames"), 0);
  constexpr double kAtePercentTolerance = 1.0, kDepthTolerance = 0.05;
  EXPECT_LT(JsonNumber(r.out, "ate_percent_of_path"), kAtePercentTolerance);
  EXPECT_LT(JsonNumber(r.out, "depth_median_rel_error"), kDepthTolerance);
  StatusOr<RigCalibration> used = ReadCalibrationYaml(out + "/camera.yaml");
  ASSERT_TRUE(used.ok()) << used.status();
  EXPECT_FALSE(used->camera.HasDistortion());
  EXPECT_LT(used->camera.fx, rendered->camera.fx) << "barrel: a wider pinhole view keeps every pixel valid";
  // The same calibration as a DSO / LSD-SLAM camera.txt given with --camera, the sequence without
  // camera.yaml: the same trajectory, to the byte.
  const fs::path bare = dir / "bare";
  fs::copy(seq, bare, fs::copy_options::recursive);
  fs::remove(bare / "camera.yaml");
  {
    std::ofstream txt(dir / "camera.txt");
    const PinholeCamera& c = rendered->camera;
    txt << std::setprecision(17) << "RadTan " << c.fx << " " << c.fy << " " << c.cx << " " << c.cy << " "
        << c.distortion[0] << " " << c.distortion[1] << " " << c.distortion[2] << " " << c.distortion[3] << "\n"
        << c.width << " " << c.height << "\ncrop\n"
        << c.width << " " << c.height << "\n";
  }
  r = Execute(Bin("prism-slam") + " --sequence " + bare.string() + " --out " + (dir / "bare_out").string());
  EXPECT_NE(r.exit_code, 0) << "no camera.yaml and no --camera";
  EXPECT_NE(r.out.find("--camera"), std::string::npos) << r.out;
  r = Execute(Bin("prism-slam") + " --sequence " + bare.string() + " --camera " + (dir / "camera.txt").string() +
              " --out " + (dir / "bare_out").string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(test::ReadFileText(dir / "bare_out" / "trajectory.txt"),
            test::ReadFileText(fs::path(out) / "trajectory.txt"));

  // The dense stage on the undistorted keyframes: a map of the object, scored against the true surface
  // of the distorted rendering; at the end on the final keyframes (the default), and as they finish
  // (--dense-online, as the server); either way the map is rebuilt at the session's scale (and with
  // --dense-online at the final poses). Measured: F-score 0.731 and 0.738 at tau = 1% of the bounding
  // box.
  for (const std::string mode : {"", " --dense-online"}) {
    SCOPED_TRACE("--dense" + mode);
    const std::string dense_out = (dir / "dense").string();
    r = Execute(Bin("prism-slam") + " --no-eval --dense" + mode + " --sequence " + seq + " --out " + dense_out);
    ASSERT_EQ(r.exit_code, 0) << r.out;
    EXPECT_EQ(JsonNumber(r.out, "dense_failed_keyframes"), 0);
    EXPECT_NE(r.out.find("\"map_remapped\": true"), std::string::npos) << r.out;
    r = Execute(Bin("prism-eval") + " cloud --object-only --sequence " + seq + " --cloud " + dense_out +
                "/map.ply --align-trajectory " + dense_out + "/trajectory_metres.txt");
    ASSERT_EQ(r.exit_code, 0) << r.out;
    std::cout << "--dense" << mode << ": map F-score " << JsonNumber(r.out, "fscore") << "\n";
    constexpr double kMinFscore = 0.3;
    EXPECT_GT(JsonNumber(r.out, "fscore"), kMinFscore) << r.out;
  }
  r = Execute(Bin("prism-synth") + " --preset armadillo-textured-forward --distortion -0.25,0.08 --out " +
              (dir / "x").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.out.find("K1,K2,P1,P2,K3"), std::string::npos) << r.out;
  fs::remove_all(dir);
}

// The real monocular KITTI sequence (../shared/data): the SLAM runs through every frame and
// reports its ATE (the issue asks for the figure; its 1% bar is on the synthetic presets). Until the
// thirty-eighth round the ATE was chaotic: the frame after each new keyframe was tracked from no motion
// (KITTI moves about 7% of the mean depth per frame), 3-4 frames per run fell below the inlier bar and
// relocalised against older keyframes, and changing one tracker parameter by 1e-4 of its value moved
// the ATE between 0.07 and 2.3% of the path. With the constant-velocity guess carried over to the new
// keyframe (SlamOptions::keep_velocity_across_keyframes) eight such runs (image_noise_sigma 2.9997 to
// 3.0004) gave 0.036-0.042% and none relocalised. The bound leaves ten times that; the 2% runs fail it.
TEST(SlamCliTest, RunsThroughKitti06AndReportsItsAte) {
  const std::string data = std::string(PRISM_SHARED_DATA_DIR) + "/kitti-06-first51";
  if (!fs::exists(data + "/calib.txt")) GTEST_SKIP() << "real data absent: " << data << " (see ../shared/data)";
  const fs::path out = fs::temp_directory_path() / ("prism_slam_kitti_" + std::to_string(::getpid()));
  const ProcessResult r = Execute(Bin("prism-slam") + " --kitti " + data + " --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  std::printf("KITTI 06 (51 frames): %s\n", r.out.c_str());
  EXPECT_EQ(JsonNumber(r.out, "frames"), 51);
  EXPECT_EQ(JsonNumber(r.out, "tracking_frames"), 51);
  const double kMaxAtePercentOfPath = 0.5;
  EXPECT_LT(JsonNumber(r.out, "ate_percent_of_path"), kMaxAtePercentOfPath);
  // No frame needed relocalisation (states.txt's message names it).
  std::ifstream states(out / "states.txt");
  ASSERT_TRUE(states.good());
  int relocalised = 0;
  for (std::string line; std::getline(states, line);)
    if (line.find("relocalised") != std::string::npos) ++relocalised;
  EXPECT_EQ(relocalised, 0);
  fs::remove_all(out);
}

}  // namespace
}  // namespace prism
