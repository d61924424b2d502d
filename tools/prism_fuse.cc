// prism-fuse: the dense stage offline on a prism-synth sequence, before SLAM exists. Ground-truth
// poses and a simulated semi-dense SLAM depth (ground-truth depth at high-gradient pixels, with
// noise and an unknown scale) stand in for the SLAM; per keyframe it runs multispectral photometric
// stereo, positions+normals fusion and voxel merging (ICP registration to the map with --icp).
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/eval/normal_metrics.h"
#include "core/fusion/fusion.h"
#include "core/io/image_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/pipeline/dense_stage.h"
#include "core/synth/semidense.h"
#include "core/util/thread_pool.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

constexpr char kNotes[] =
    R"(Simulated semi-dense SLAM depth -> photometric stereo normals -> positions+normals fusion ->
merged map, with ground-truth poses (the sequence needs groundtruth.txt and depth/, as prism-synth
writes them). Writes to DIR: normals/<t>.png (16-bit exact, image_io.h format), normals_vis/<t>.png
(8-bit for looking at), depth/<t>.png (fused depth, TUM 16-bit; these three at the keyframe's image level),
clouds/<t>.ply (dense keyframe
clouds, metres, world frame), map.ply (merged map) and summary.json (also printed).)";

// CV_8U, 255 where a CV_32FC3 normal map has a normal (not all zero).
cv::Mat NonZeroNormals(const cv::Mat& normals) {
  cv::Mat out(normals.size(), CV_8U);
  for (int y = 0; y < normals.rows; ++y)
    for (int x = 0; x < normals.cols; ++x)
      out.at<uint8_t>(y, x) = normals.at<cv::Vec3f>(y, x) == cv::Vec3f(0, 0, 0) ? 0 : 255;
  return out;
}

int Fail(const std::string& m) {
  std::cerr << "prism-fuse: " << m << "\n";
  return 2;
}

std::string Stem(const std::string& file) { return std::filesystem::path(file).stem().string(); }

// RMSE over mask pixels of depth (metres) against the truth; only where both are valid.
double DepthRmse(const cv::Mat& depth_m, const cv::Mat& truth_m, const cv::Mat& mask, int* count) {
  double sum = 0;
  *count = 0;
  for (int y = 0; y < truth_m.rows; ++y)
    for (int x = 0; x < truth_m.cols; ++x) {
      if (!mask.at<uint8_t>(y, x)) continue;
      const float d = depth_m.at<float>(y, x), t = truth_m.at<float>(y, x);
      if (!(d > 0) || !(t > 0)) continue;
      sum += (d - t) * (d - t);
      ++*count;
    }
  return *count ? std::sqrt(sum / *count) : 0.0;
}

// The command line.
struct Settings {
  std::string sequence_dir, out_dir;
  int keyframe_step = 10, max_keyframes = 1 << 30, scale_keyframes = 3, threads = 0;
  double slam_scale = 0.37, depth_noise = 0.01, voxel = 0.002;
  double max_icp_correction_m = 0.01, max_icp_correction_deg = 1.0;
  double max_edge_step = 0.03;
  FusionOptions fusion_options;
  bool icp = false;
  int max_image_level = DenseStageOptions().max_image_level;
  uint32_t seed = 1;
};

// What the keyframes add up to, for summary.json.
struct Totals {
  NormalErrorAccumulator ps_error, fused_error, prior_error;
  // The same comparison restricted to the pixels where both PS and fusion give a normal.
  NormalErrorAccumulator ps_common_error, fused_common_error, corrected_common_error;
  double ps_ms = 0, fusion_ms = 0, icp_ms = 0;
  // Pooled over keyframes: squared depth errors (metres^2) and pixel counts, and coverage.
  double fused_sse = 0, semi_sse = 0, min_coverage = 1.0;
  long long fused_n = 0, semi_n = 0;
  Json per_keyframe = Json::array();
  int keyframes = 0;
};

// Parses the command line into `settings`: cli::kContinue or the exit status.
int ParseCommandLine(int argc, char** argv, Settings* settings) {
  Settings& s = *settings;
  CLI::App app{"", "prism-fuse"};
  cli::Setup(&app, "the dense stage alone on a sequence with ground truth, poses and simulated SLAM depth",
             {"prism-fuse --sequence DIR --out DIR [options]"}, kNotes);
  app.add_option("--sequence", s.sequence_dir, "sequence with ground truth (prism-synth output)")
      ->type_name("DIR")
      ->required();
  app.add_option("--out", s.out_dir, "output folder (created)")->type_name("DIR")->required();
  app.add_option("--keyframe-step", s.keyframe_step, "every K-th frame is a keyframe")
      ->type_name("K")
      ->check(CLI::PositiveNumber);
  app.add_option("--max-keyframes", s.max_keyframes, "stop after N keyframes (default: all)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::PositiveNumber);
  app.add_option("--slam-scale", s.slam_scale, "metres per simulated SLAM depth unit, unknown to the estimators")
      ->type_name("S")
      ->check(CLI::PositiveNumber);
  app.add_option("--depth-noise", s.depth_noise, "relative noise of the simulated inverse depth, 0-0.5")
      ->type_name("R")
      ->check(CLI::Range(0.0, 0.5));
  app.add_option("--scale-keyframes", s.scale_keyframes, "keyframes that estimate the depth scale before it is fixed")
      ->type_name("N")
      ->check(CLI::PositiveNumber);
  app.add_option("--voxel", s.voxel, "map voxel size, metres")->type_name("M")->check(CLI::PositiveNumber);
  app.add_option("--max-edge-step", s.max_edge_step,
                 "remove from the fused depth (so from the clouds and the map) pixels whose\n"
                 "depth differs from a neighbour's by more than R (relative; 0 keeps all):\n"
                 "flying pixels along silhouettes")
      ->type_name("R")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--position-weight", s.fusion_options.position_weight,
                 "fusion: weight of the SLAM positions against the normals")
      ->type_name("W")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--fusion-passes", s.fusion_options.passes, "fusion: solve passes with normal correction between")
      ->type_name("N")
      ->check(CLI::PositiveNumber);
  app.add_option("--correction-sigma", s.fusion_options.correction_sigma_px,
                 "fusion: scale of the normal correction's low-pass filter, pixels")
      ->type_name("PX")
      ->check(CLI::PositiveNumber);
  app.add_option("--max-image-level", s.max_image_level,
                 "the dense stage on each keyframe at the coarsest pyramid level up to L whose\n"
                 "pixel is no wider than a voxel (0 = full size); its fused depth and normals\n"
                 "are compared with the truth at that level")
      ->type_name("L")
      ->check(CLI::Range(0, 3));
  app.add_flag("--icp", s.icp, "register each keyframe cloud to the map with ICP before merging it");
  app.add_option("--max-icp-correction-m", s.max_icp_correction_m,
                 "largest ICP correction applied, metres; larger ones, unconverged ones and\n"
                 "ones pairing < 30% of points are reported, not applied")
      ->type_name("M")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--max-icp-correction-deg", s.max_icp_correction_deg, "largest ICP correction applied, degrees")
      ->type_name("D")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--threads", s.threads, "worker threads, 1-256 (default: all cores)")
      ->type_name("T")
      ->default_str("")
      ->check(CLI::Range(1, 256));
  app.add_option("--seed", s.seed, "seed of the depth simulation")->type_name("S");
  return cli::Parse(&app, argc, argv);
}

// Reads the sequence, checks it has a calibration and ground truth, and creates the output folders:
// cli::kContinue or the exit status.
int OpenInput(const Settings& s, Sequence* sequence) {
  StatusOr<Sequence> seq = LoadSequence(s.sequence_dir);
  if (!seq.ok()) return Fail(seq.status().ToString());
  if (!seq->has_calibration) return Fail("sequence has no camera.yaml (the rig calibration is needed)");
  if (seq->groundtruth.empty()) return Fail("sequence has no groundtruth.txt (poses stand in for the SLAM)");
  std::error_code ec;
  for (const char* sub : {"", "/normals", "/normals_vis", "/depth", "/clouds"}) {
    std::filesystem::create_directories(s.out_dir + sub, ec);
    if (ec) return Fail("cannot create '" + s.out_dir + sub + "': " + ec.message());
  }
  *sequence = std::move(seq).value();
  return cli::kContinue;
}

DenseStageOptions MakeDenseOptions(const Settings& s) {
  DenseStageOptions dense_options;
  dense_options.fusion = s.fusion_options;
  dense_options.map.voxel_m = s.voxel;
  dense_options.icp_enabled = s.icp;
  dense_options.scale_keyframes = s.scale_keyframes;
  dense_options.max_edge_step = s.max_edge_step;
  dense_options.max_icp_correction_m = s.max_icp_correction_m;
  dense_options.max_icp_correction_deg = s.max_icp_correction_deg;
  dense_options.world_in_slam_units = false;  // ground-truth poses with the simulated scale: metric
  dense_options.max_image_level = s.max_image_level;
  return dense_options;
}

// Frame i as a keyframe of the simulated SLAM: its ground-truth pose with the SLAM scale, and the
// simulated semi-dense depth.
DenseKeyframe SimulateKeyframe(const Settings& s, size_t i, const cv::Mat& rgb, const cv::Mat& truth_depth,
                               const Rigid3d& pose) {
  synth::SemiDenseOptions sd;
  sd.scale = s.slam_scale;
  sd.relative_noise = s.depth_noise;
  sd.seed = s.seed * 1000003u + static_cast<uint32_t>(i);
  DenseKeyframe keyframe;
  keyframe.id = static_cast<uint64_t>(i);
  keyframe.rgb = rgb;
  keyframe.world_from_keyframe = Sim3d(s.slam_scale, pose.rotation, pose.translation);
  keyframe.depth = synth::SimulateSemiDenseDepth(truth_depth, rgb, sd);
  return keyframe;
}

// The keyframe's normals (photometric stereo, fused, prior) against the truth over `mask` into the
// totals; the medians of PS and fused stay -1 without true normals.
void CompareNormals(const cv::Mat& truth_normals, const cv::Mat& mask, const DenseKeyframeResult& dense, Totals* totals,
                    double* ps_median, double* fused_median) {
  const PhotometricResult* ps = &dense.photometric;
  const FusionResult* fused = &dense.fusion;
  (void)totals->ps_error.Add(ps->normals, truth_normals, mask);
  (void)totals->fused_error.Add(fused->normals, truth_normals, mask);
  (void)totals->prior_error.Add(ps->prior_normals, truth_normals, mask);
  cv::Mat common = NonZeroNormals(ps->normals) & NonZeroNormals(fused->normals);
  if (!mask.empty()) common &= mask;
  (void)totals->ps_common_error.Add(ps->normals, truth_normals, common);
  (void)totals->fused_common_error.Add(fused->normals, truth_normals, common);
  if (!fused->corrected_normals.empty())
    (void)totals->corrected_common_error.Add(fused->corrected_normals, truth_normals, common);
  if (auto e = ComputeNormalError(ps->normals, truth_normals, mask); e.ok()) *ps_median = e->median_deg;
  if (auto e = ComputeNormalError(fused->normals, truth_normals, mask); e.ok()) *fused_median = e->median_deg;
}

// The fused and the semi-dense depth of a keyframe against the truth, over the mask's pixels (all
// pixels without a mask).
struct DepthComparison {
  cv::Mat fused_m;  // the fused depth, metres
  double fused_rmse = 0, semi_rmse = 0;
  int n_fused = 0, n_semi = 0;  // pixels compared
  int eval_pixels = 0;          // evaluated pixels with a true depth
};

// The semi-dense depth is at the camera's size, the fused depth at the dense stage's level: each is
// compared with the truth (and mask) of its size.
DepthComparison CompareDepth(double slam_scale, const InverseDepthMap& semi_dense, const cv::Mat& fused_depth,
                             const cv::Mat& truth_depth, const cv::Mat& mask, const cv::Mat& level_truth_depth,
                             const cv::Mat& level_mask) {
  cv::Mat semi_dense_m(truth_depth.size(), CV_32F, cv::Scalar(0));
  for (int y = 0; y < semi_dense_m.rows; ++y)
    for (int x = 0; x < semi_dense_m.cols; ++x) {
      const float id = semi_dense.inverse_depth.at<float>(y, x);
      if (id > 0) semi_dense_m.at<float>(y, x) = static_cast<float>(slam_scale / id);
    }
  DepthComparison c;
  c.fused_m = fused_depth * slam_scale;
  const cv::Mat eval_mask = mask.empty() ? cv::Mat(truth_depth.size(), CV_8U, cv::Scalar(255)) : mask;
  const cv::Mat level_eval_mask =
      level_mask.empty() ? cv::Mat(level_truth_depth.size(), CV_8U, cv::Scalar(255)) : level_mask;
  c.fused_rmse = DepthRmse(c.fused_m, level_truth_depth, level_eval_mask, &c.n_fused);
  c.semi_rmse = DepthRmse(semi_dense_m, truth_depth, eval_mask, &c.n_semi);
  c.eval_pixels = cv::countNonZero(level_eval_mask & (level_truth_depth > 0));
  return c;
}

// normals/, normals_vis/, depth/ and clouds/ of one keyframe.
void WriteKeyframeOutputs(const std::string& out_dir, const std::string& name, const DenseKeyframeResult& dense,
                          const cv::Mat& fused_m) {
  const PhotometricResult* ps = &dense.photometric;
  const FusionResult* fused = &dense.fusion;
  (void)WriteNormalPng(out_dir + "/normals/" + name + ".png", fused->normals);
  cv::Mat vis(ps->normals.size(), CV_8UC3);
  for (int y = 0; y < vis.rows; ++y)
    for (int x = 0; x < vis.cols; ++x) {
      const cv::Vec3f n = fused->normals.at<cv::Vec3f>(y, x);
      // BGR file: x -> red, -y -> green (up), -z -> blue (towards the camera).
      vis.at<cv::Vec3b>(y, x) = n == cv::Vec3f(0, 0, 0) ? cv::Vec3b(0, 0, 0)
                                                        : cv::Vec3b(cv::saturate_cast<uint8_t>(127.5 * (1 - n[2])),
                                                                    cv::saturate_cast<uint8_t>(127.5 * (1 - n[1])),
                                                                    cv::saturate_cast<uint8_t>(127.5 * (1 + n[0])));
    }
  cv::imwrite(out_dir + "/normals_vis/" + name + ".png", vis);
  (void)WriteDepthPng(out_dir + "/depth/" + name + ".png", fused_m);
  (void)WritePointCloudPly(out_dir + "/clouds/" + name + ".ply", dense.cloud);
}

// summary.json's entry of one keyframe.
Json KeyframeJson(size_t i, const std::string& name, double ps_median, double fused_median,
                  const DepthComparison& depth, const DenseKeyframeResult& dense) {
  Json icp_json = nullptr;
  if (dense.icp_attempted)
    icp_json = Json{{"converged", dense.icp.converged},
                    {"inlier_rmse_m", dense.icp.inlier_rmse_m},
                    {"inlier_fraction", dense.icp.inlier_fraction},
                    {"correction_m", dense.icp_estimate.translation.norm()},
                    {"correction_deg", RotationAngle(dense.icp_estimate.rotation) * 180 / M_PI}};
  const int eval_pixels = depth.eval_pixels;
  return Json{{"frame", i},
              {"timestamp", name},
              {"ps_median_deg", ps_median},
              {"fused_median_deg", fused_median},
              {"semi_dense_rmse_m", depth.semi_rmse},
              {"fused_rmse_m", depth.fused_rmse},
              {"semi_dense_coverage", eval_pixels ? static_cast<double>(depth.n_semi) / eval_pixels : 0.0},
              {"fused_coverage", eval_pixels ? static_cast<double>(depth.n_fused) / eval_pixels : 0.0},
              {"depth_scale", dense.photometric.depth_scale},
              {"cloud_points", dense.cloud.size()},
              {"image_level", dense.image_level},
              {"cg_iterations", dense.fusion.iterations},
              {"icp", icp_json}};
}

// Frame i as a keyframe: the dense stage on it, its comparison with the truth into the totals, and its
// outputs: cli::kContinue (also when the dense stage skipped it) or the exit status.
int ProcessKeyframe(const Settings& s, const Sequence& seq, size_t i, DenseStage* stage, Totals* totals) {
  StatusOr<cv::Mat> rgb = seq.ReadRgb(i);
  StatusOr<cv::Mat> truth_depth = seq.ReadDepth(i);
  StatusOr<Rigid3d> pose = seq.GroundTruthPose(i);
  if (!rgb.ok()) return Fail(rgb.status().ToString());
  if (!truth_depth.ok()) return Fail("frame " + std::to_string(i) + ": " + truth_depth.status().ToString());
  if (!pose.ok()) return Fail(pose.status().ToString());
  const std::string name = Stem(seq.frames[i].rgb_file);
  const DenseKeyframe keyframe = SimulateKeyframe(s, i, *rgb, *truth_depth, *pose);

  // Photometric stereo, fusion, depth-edge filter, cloud, ICP and map merge.
  StatusOr<DenseKeyframeResult> dense = stage->Process(keyframe);
  if (!dense.ok()) {
    std::cerr << "prism-fuse: keyframe " << name << " skipped: " << dense.status() << "\n";
    return cli::kContinue;
  }
  totals->ps_ms += dense->photometric_ms;
  totals->fusion_ms += dense->fusion_ms;
  totals->icp_ms += dense->map_ms;

  // Ground-truth comparisons (object pixels when the sequence has masks).
  // The dense stage's outputs are at its image level: the truth there is the nearest full-size pixel.
  cv::Mat mask;
  if (StatusOr<cv::Mat> m = seq.ReadMask(i); m.ok()) mask = *m == kMaskObject;
  const cv::Size level_size = dense->depth.size();
  auto at_level = [&](const cv::Mat& full) {
    if (full.empty() || full.size() == level_size) return full;
    cv::Mat level;
    cv::resize(full, level, level_size, 0, 0, cv::INTER_NEAREST);
    return level;
  };
  const cv::Mat level_mask = at_level(mask);
  StatusOr<cv::Mat> truth_normals = seq.ReadNormals(i);
  double ps_median = -1, fused_median = -1;
  if (truth_normals.ok())
    CompareNormals(at_level(*truth_normals), level_mask, *dense, totals, &ps_median, &fused_median);
  const DepthComparison depth =
      CompareDepth(s.slam_scale, keyframe.depth, dense->depth, *truth_depth, mask, at_level(*truth_depth), level_mask);
  totals->fused_sse += depth.fused_rmse * depth.fused_rmse * depth.n_fused;
  totals->semi_sse += depth.semi_rmse * depth.semi_rmse * depth.n_semi;
  totals->fused_n += depth.n_fused;
  totals->semi_n += depth.n_semi;
  if (depth.eval_pixels > 0)
    totals->min_coverage = std::min(totals->min_coverage, static_cast<double>(depth.n_fused) / depth.eval_pixels);

  WriteKeyframeOutputs(s.out_dir, name, *dense, depth.fused_m);
  totals->per_keyframe.push_back(KeyframeJson(i, name, ps_median, fused_median, depth, *dense));
  ++totals->keyframes;
  std::cerr << "prism-fuse: keyframe " << totals->keyframes << " (" << name << "): PS " << ps_median << " deg, fused "
            << fused_median << " deg, depth RMSE " << depth.fused_rmse << " m (semi-dense " << depth.semi_rmse
            << " m)\n";
  return cli::kContinue;
}

// Writes map.ply and summary.json (also printed): the exit status.
int WriteSummary(const Settings& s, const DenseStage& stage, const Totals& t) {
  const int keyframes = t.keyframes;
  const PointCloud merged = stage.map().ToPointCloud();
  if (Status st = WritePointCloudPly(s.out_dir + "/map.ply", merged); !st.ok()) return Fail(st.ToString());
  const AngularErrorStats ps_stats = t.ps_error.Summarize(), fused_stats = t.fused_error.Summarize(),
                          prior_stats = t.prior_error.Summarize(), ps_common = t.ps_common_error.Summarize(),
                          fused_common = t.fused_common_error.Summarize(),
                          corrected_common = t.corrected_common_error.Summarize();
  Json json;
  json["keyframes"] = keyframes;
  json["map_points"] = merged.size();
  json["session_depth_scale"] = stage.session_metres_per_unit();
  json["slam_scale_true"] = s.slam_scale;
  json["ps_median_deg"] = ps_stats.median_deg;
  json["ps_mean_deg"] = ps_stats.mean_deg;
  json["fused_normal_median_deg"] = fused_stats.median_deg;
  json["prior_normal_median_deg"] = prior_stats.median_deg;
  json["ps_median_common_deg"] = ps_common.median_deg;
  json["fused_normal_median_common_deg"] = fused_common.median_deg;
  json["corrected_normal_median_common_deg"] = corrected_common.median_deg;
  json["common_normal_pixels"] = t.ps_common_error.count();
  json["fused_depth_rmse_m"] = t.fused_n ? std::sqrt(t.fused_sse / t.fused_n) : 0.0;
  json["semi_dense_depth_rmse_m"] = t.semi_n ? std::sqrt(t.semi_sse / t.semi_n) : 0.0;
  json["min_fused_coverage"] = t.min_coverage;
  json["ps_ms_per_keyframe"] = t.ps_ms / keyframes;
  json["fusion_ms_per_keyframe"] = t.fusion_ms / keyframes;
  json["icp_merge_ms_per_keyframe"] = t.icp_ms / keyframes;
  json["per_keyframe"] = t.per_keyframe;
  const std::string text = JsonText(json, 2);
  std::cout << text;
  std::ofstream(s.out_dir + "/summary.json") << text;
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Settings settings;
  if (const int exit = ParseCommandLine(argc, argv, &settings); exit != cli::kContinue) return exit;
  Sequence seq;
  if (const int exit = OpenInput(settings, &seq); exit != cli::kContinue) return exit;
  ThreadPool pool(settings.threads);
  StatusOr<std::unique_ptr<DenseStage>> stage = DenseStage::Create(seq.calibration, MakeDenseOptions(settings), &pool);
  if (!stage.ok()) return Fail(stage.status().ToString());
  Totals totals;
  for (size_t i = 0; i < seq.frames.size() && totals.keyframes < settings.max_keyframes; i += settings.keyframe_step) {
    if (const int exit = ProcessKeyframe(settings, seq, i, stage->get(), &totals); exit != cli::kContinue) return exit;
  }
  if (totals.keyframes == 0) return Fail("no keyframe could be processed");
  return WriteSummary(settings, **stage, totals);
}
