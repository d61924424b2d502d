#include <filesystem>
#include <fstream>
#include <limits>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/eval/normal_metrics.h"
#include "core/photometric/photometric_stereo.h"
#include "core/photometric/superpixels.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/semidense.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// Two sessions (seeds) of a preset at 512x512, keyframes at frames 10, 25, 40, 55 of a 60-frame
// orbit, each with simulated semi-dense SLAM depth in units of 0.37 m (the scale is unknown to the
// estimator; each session takes the median of its keyframes' estimates). Returns the error over
// the object pixels of all keyframes pooled.
struct PooledResult {
  AngularErrorStats error;
  std::vector<double> per_keyframe_median_deg;
  std::vector<double> depth_scale;
};

PooledResult RunOnPreset(const std::string& preset, const PhotometricOptions& base_options_in) {
  const PhotometricOptions& base_options = base_options_in;
  PooledResult out;
  NormalErrorAccumulator acc;
  for (uint32_t seed : {1u, 2u}) {
    synth::PresetOptions o;
    o.frames = 60;
    o.seed = seed;
    const synth::SynthSetup setup = synth::MakePreset(preset, o).value();
    const Trajectory t = synth::MakeTrajectory(setup.trajectory);
    struct Keyframe {
      synth::RenderedFrame frame;
      InverseDepthMap prior;
    };
    std::vector<Keyframe> keyframes;
    SessionDepthScale session_scale;
    for (int frame : {10, 25, 40, 55}) {
      Keyframe k;
      k.frame =
          synth::RenderFrame(setup.scene, setup.rig, t[frame].world_from_camera, setup.render, 100 * seed + frame);
      synth::SemiDenseOptions s;
      s.scale = 0.37;
      s.seed = seed * 7 + frame;
      k.prior = synth::SimulateSemiDenseDepth(k.frame.depth, k.frame.rgb, s);
      // As a session does: every keyframe estimates the scale; the session keeps their median.
      PhotometricOptions estimate = base_options;
      estimate.estimate_depth_scale = true;
      auto r = EstimateNormals(k.frame.rgb, k.prior, setup.rig, estimate);
      EXPECT_TRUE(r.ok()) << r.status();
      if (r.ok()) session_scale.Add(r->depth_scale);
      keyframes.push_back(std::move(k));
    }
    EXPECT_TRUE(session_scale.has_value());
    if (!session_scale.has_value()) continue;
    out.depth_scale.push_back(session_scale.value());
    PhotometricOptions fixed = base_options;
    fixed.estimate_depth_scale = false;
    fixed.depth_scale = session_scale.value();
    for (const Keyframe& k : keyframes) {
      auto r = EstimateNormals(k.frame.rgb, k.prior, setup.rig, fixed);
      EXPECT_TRUE(r.ok()) << r.status();
      if (!r.ok()) continue;
      const cv::Mat object = k.frame.mask == 255;
      EXPECT_TRUE(acc.Add(r->normals, k.frame.normals, object).ok());
      out.per_keyframe_median_deg.push_back(ComputeNormalError(r->normals, k.frame.normals, object).value().median_deg);
    }
  }
  out.error = acc.Summarize();
  std::cout << preset << ": pooled median " << out.error.median_deg << " deg, mean " << out.error.mean_deg
            << " deg over " << out.error.count << " object pixels; per keyframe medians:";
  for (double m : out.per_keyframe_median_deg) std::cout << " " << m;
  std::cout << "; session depth scales (true 0.37):";
  for (double d : out.depth_scale) std::cout << " " << d;
  std::cout << "\n";
  return out;
}

TEST(PhotometricStereoTest, UniformAlbedoSphereFromSemiDenseDepth) {
  const PooledResult r = RunOnPreset("sphere-uniform-sideways", PhotometricOptions());
  EXPECT_LT(r.error.median_deg, /*max_median_normal_error_deg=*/3.0);
  for (double s : r.depth_scale) EXPECT_NEAR(s, 0.37, /*max_depth_scale_error=*/0.37 * 0.1);
}

TEST(PhotometricStereoTest, MultiColouredSphereFromSemiDenseDepth) {
  const PooledResult r = RunOnPreset("sphere-multicolor-sideways", PhotometricOptions());
  // Pooled over these 8 keyframes the estimator reaches 4.0 deg (single keyframes 3.0 to 7.0).
  EXPECT_LT(r.error.median_deg, /*max_median_normal_error_deg=*/5.0);
}

// The pool only spreads the work: fixed chunks, sums added in a fixed order, so the result is the
// same bit for bit with and without threads.
TEST(PhotometricStereoTest, SameResultWithAndWithoutThreadPool) {
  synth::PresetOptions o;
  o.frames = 60;
  const synth::SynthSetup setup = synth::MakePreset("sphere-multicolor-sideways", o).value();
  const Trajectory t = synth::MakeTrajectory(setup.trajectory);
  const synth::RenderedFrame frame =
      synth::RenderFrame(setup.scene, setup.rig, t[40].world_from_camera, setup.render, 7);
  synth::SemiDenseOptions s;
  s.scale = 0.37;
  const InverseDepthMap prior = synth::SimulateSemiDenseDepth(frame.depth, frame.rgb, s);
  for (bool estimate_scale : {false, true}) {
    PhotometricOptions options;
    options.estimate_depth_scale = estimate_scale;
    options.depth_scale = 0.37;
    auto serial = EstimateNormals(frame.rgb, prior, setup.rig, options);
    ThreadPool pool(2);
    auto threaded = EstimateNormals(frame.rgb, prior, setup.rig, options, &pool);
    ASSERT_TRUE(serial.ok() && threaded.ok());
    EXPECT_EQ(serial->depth_scale, threaded->depth_scale);
    EXPECT_EQ(serial->num_clusters, threaded->num_clusters);
    EXPECT_EQ(cv::norm(serial->normals, threaded->normals, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(serial->confidence, threaded->confidence, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(serial->labels, threaded->labels, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(serial->prior_normals, threaded->prior_normals, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(serial->dense_inverse_depth, threaded->dense_inverse_depth, cv::NORM_INF), 0.0);
  }
}

TEST(PhotometricStereoTest, BadInputIsAnError) {
  RigCalibration rig = synth::MakeDefaultRig(64, 48);
  InverseDepthMap prior{cv::Mat(48, 64, CV_32F, cv::Scalar(0)), cv::Mat(48, 64, CV_32F, cv::Scalar(0))};
  EXPECT_EQ(EstimateNormals(cv::Mat(48, 64, CV_8UC1), prior, rig, PhotometricOptions()).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(EstimateNormals(cv::Mat(40, 64, CV_8UC3), prior, rig, PhotometricOptions()).status().code(),
            StatusCode::kInvalidArgument);
  // No depth at all: a clear precondition error, not a crash.
  EXPECT_EQ(EstimateNormals(cv::Mat(48, 64, CV_8UC3, cv::Scalar(100, 100, 100)), prior, rig, PhotometricOptions())
                .status()
                .code(),
            StatusCode::kFailedPrecondition);
  PhotometricOptions bad;
  bad.max_clusters = 0;
  EXPECT_FALSE(bad.Check().ok());
}

// Superpixels follow colour edges: on a noisy image of two colours split by a slanted line no
// superpixel mixes them, and every pixel gets a label.
TEST(SuperpixelTest, SlicRespectsColourEdges) {
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0, 2);
  cv::Mat lab(120, 160, CV_8UC3);
  auto left = [](int x, int y) { return x < 50 + y / 3; };
  for (int y = 0; y < lab.rows; ++y)
    for (int x = 0; x < lab.cols; ++x) {
      const cv::Vec3d base = left(x, y) ? cv::Vec3d(120, 160, 110) : cv::Vec3d(150, 100, 170);
      for (int c = 0; c < 3; ++c) lab.at<cv::Vec3b>(y, x)[c] = cv::saturate_cast<uchar>(base[c] + noise(rng));
    }
  cv::Mat labels;
  const int n = SlicSuperpixels(lab, 10, 5, &labels);
  ASSERT_GT(n, 100);
  std::vector<int> left_count(n, 0), right_count(n, 0);
  for (int y = 0; y < lab.rows; ++y)
    for (int x = 0; x < lab.cols; ++x) {
      const int l = labels.at<int>(y, x);
      ASSERT_TRUE(l >= 0 && l < n);
      (left(x, y) ? left_count : right_count)[l]++;
    }
  int mixed_pixels = 0;
  for (int l = 0; l < n; ++l) mixed_pixels += std::min(left_count[l], right_count[l]);
  EXPECT_LE(mixed_pixels, /*max_pixels_on_the_wrong_side=*/0);
}

// DiLiGenT "ball": three real images (one light per colour channel) make one RGB image; M in c = M n
// is calibrated from a sparse random 2% of the ground-truth normals (standing in for the SLAM prior).
TEST(PhotometricStereoTest, DiligentBallFromThreeLights) {
  const std::string dir = std::string(PRISM_SHARED_DATA_DIR) + "/diligent-ball";
  if (!std::filesystem::exists(dir + "/normal_gt_512x612x3_f32le.bin"))
    GTEST_SKIP() << "real data absent: " << dir << " (see ../shared/data)";
  // Light intensities per image and channel.
  std::vector<Eigen::Vector3d> intensity;
  {
    std::ifstream in(dir + "/light_intensities.txt");
    double r, g, b;
    while (in >> r >> g >> b) intensity.emplace_back(r, g, b);
  }
  ASSERT_EQ(intensity.size(), 96u);
  cv::Mat gt(512, 612, CV_32FC3);
  {
    std::ifstream in(dir + "/normal_gt_512x612x3_f32le.bin", std::ios::binary);
    in.read(reinterpret_cast<char*>(gt.data), 512 * 612 * 3 * 4);
    ASSERT_TRUE(in.good());
  }
  cv::Mat mask = cv::imread(dir + "/mask.png", cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(mask.empty());
  // Three lights (1-based file numbers), one per channel: of the lights within 32 degrees of the view
  // axis, the triple whose direction matrix has the largest smallest singular value (0.61).
  const int lights[3] = {9, 24, 85};
  std::vector<cv::Mat> channels;
  for (int c = 0; c < 3; ++c) {
    char name[32];
    std::snprintf(name, sizeof(name), "/%03d.png", lights[c]);
    cv::Mat img = cv::imread(dir + name, cv::IMREAD_UNCHANGED);  // 16-bit BGR
    ASSERT_EQ(img.type(), CV_16UC3);
    std::vector<cv::Mat> bgr;
    cv::split(img, bgr);
    cv::Mat ch;
    bgr[2 - c].convertTo(ch, CV_64F, 1.0 / (65535.0 * intensity[lights[c] - 1][c]));  // channel c of image c
    channels.push_back(ch);
  }
  double max_v = 0;
  for (auto& ch : channels) max_v = std::max(max_v, cv::norm(ch, cv::NORM_INF));
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Eigen::Vector3d> colors, normals;
  std::vector<std::pair<int, int>> pixels;
  for (int y = 0; y < 512; ++y)
    for (int x = 0; x < 612; ++x) {
      if (mask.at<uint8_t>(y, x) == 0) continue;
      pixels.emplace_back(x, y);
      if (u(rng) > 0.02) continue;
      const cv::Vec3f n = gt.at<cv::Vec3f>(y, x);
      colors.emplace_back(channels[0].at<double>(y, x) / max_v, channels[1].at<double>(y, x) / max_v,
                          channels[2].at<double>(y, x) / max_v);
      normals.emplace_back(n[0], n[1], n[2]);
    }
  Eigen::Matrix3d m;
  ASSERT_TRUE(FitLightingMatrix(colors, normals, &m));
  const Eigen::Matrix3d m_inv = m.inverse();
  cv::Mat est(512, 612, CV_32FC3, cv::Scalar(0, 0, 0));
  for (auto [x, y] : pixels) {
    const Eigen::Vector3d c(channels[0].at<double>(y, x) / max_v, channels[1].at<double>(y, x) / max_v,
                            channels[2].at<double>(y, x) / max_v);
    Eigen::Vector3d n = m_inv * c;
    if (n.norm() < 1e-12) continue;
    n.normalize();
    est.at<cv::Vec3f>(y, x) =
        cv::Vec3f(static_cast<float>(n.x()), static_cast<float>(n.y()), static_cast<float>(n.z()));
  }
  const AngularErrorStats e = ComputeNormalError(est, gt, mask).value();
  std::cout << "DiLiGenT ball, lights " << lights[0] << "/" << lights[1] << "/" << lights[2] << ", " << colors.size()
            << " prior normals: mean " << e.mean_deg << " median " << e.median_deg << " deg over " << e.count
            << " px\n";
  EXPECT_LT(e.mean_deg, /*max_mean_normal_error_deg=*/8.0);
}

}  // namespace
}  // namespace prism

namespace prism {
namespace {

// The first two keyframes of a SLAM session on bunny-multicolor-forward gave these estimates (their
// depth comes from the monocular initialisation); true 0.566 m/unit.
TEST(SessionDepthScaleTest, OutlyingFirstEstimatesDoNotFixTheScale) {
  SessionDepthScale scale;
  EXPECT_FALSE(scale.has_value());
  EXPECT_EQ(scale.agreeing(), 0);
  for (double e : {3.290, 2.787, 0.4415}) scale.Add(e);
  EXPECT_EQ(scale.agreeing(), 2);  // a plain median would now say 2.787
  scale.Add(0.5313);
  EXPECT_EQ(scale.agreeing(), 2);
  scale.Add(0.5238);
  scale.Add(-1.0);  // ignored
  scale.Add(std::numeric_limits<double>::quiet_NaN());
  EXPECT_EQ(scale.count(), 5);
  EXPECT_EQ(scale.agreeing(), 3);
  EXPECT_NEAR(scale.value(), 0.5238, 1e-9);
}

}  // namespace
}  // namespace prism
