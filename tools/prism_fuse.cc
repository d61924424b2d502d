// prism-fuse: the dense stage offline on a prism-synth sequence, before SLAM exists. Ground-truth
// poses and a simulated semi-dense SLAM depth (ground-truth depth at high-gradient pixels, with
// noise and an unknown scale) stand in for the SLAM; per keyframe it runs multispectral photometric
// stereo, positions+normals fusion, ICP registration to the map and voxel merging.
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>

#include <opencv2/imgcodecs.hpp>

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

constexpr char kNotes[] =
    R"(Simulated semi-dense SLAM depth -> photometric stereo normals -> positions+normals fusion -> ICP
-> merged map, with ground-truth poses (the sequence needs groundtruth.txt and depth/, as prism-synth
writes them). Writes to DIR: normals/<t>.png (16-bit exact, image_io.h format), normals_vis/<t>.png
(8-bit for looking at), depth/<t>.png (fused depth, TUM 16-bit), clouds/<t>.ply (dense keyframe
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

}  // namespace

int main(int argc, char** argv) {
  using namespace prism;
  std::string sequence_dir, out_dir;
  int keyframe_step = 10, max_keyframes = 1 << 30, scale_keyframes = 3, threads = 0;
  double slam_scale = 0.37, depth_noise = 0.01, voxel = 0.002;
  double max_icp_correction_m = 0.01, max_icp_correction_deg = 1.0;
  double max_edge_step = 0.03;
  FusionOptions fusion_options;
  bool no_icp = false;
  uint32_t seed = 1;
  CLI::App app{"", "prism-fuse"};
  cli::Setup(&app, "the dense stage alone on a sequence with ground truth, poses and simulated SLAM depth",
             {"prism-fuse --sequence DIR --out DIR [options]"}, kNotes);
  app.add_option("--sequence", sequence_dir, "sequence with ground truth (prism-synth output)")
      ->type_name("DIR")
      ->required();
  app.add_option("--out", out_dir, "output folder (created)")->type_name("DIR")->required();
  app.add_option("--keyframe-step", keyframe_step, "every K-th frame is a keyframe")
      ->type_name("K")
      ->check(CLI::PositiveNumber);
  app.add_option("--max-keyframes", max_keyframes, "stop after N keyframes (default: all)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::PositiveNumber);
  app.add_option("--slam-scale", slam_scale, "metres per simulated SLAM depth unit, unknown to the estimators")
      ->type_name("S")
      ->check(CLI::PositiveNumber);
  app.add_option("--depth-noise", depth_noise, "relative noise of the simulated inverse depth, 0-0.5")
      ->type_name("R")
      ->check(CLI::Range(0.0, 0.5));
  app.add_option("--scale-keyframes", scale_keyframes, "keyframes that estimate the depth scale before it is fixed")
      ->type_name("N")
      ->check(CLI::PositiveNumber);
  app.add_option("--voxel", voxel, "map voxel size, metres")->type_name("M")->check(CLI::PositiveNumber);
  app.add_option("--max-edge-step", max_edge_step,
                 "remove from the fused depth (so from the clouds and the map) pixels whose\n"
                 "depth differs from a neighbour's by more than R (relative; 0 keeps all):\n"
                 "flying pixels along silhouettes")
      ->type_name("R")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--position-weight", fusion_options.position_weight,
                 "fusion: weight of the SLAM positions against the normals")
      ->type_name("W")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--fusion-passes", fusion_options.passes, "fusion: solve passes with normal correction between")
      ->type_name("N")
      ->check(CLI::PositiveNumber);
  app.add_option("--correction-sigma", fusion_options.correction_sigma_px,
                 "fusion: scale of the normal correction's low-pass filter, pixels")
      ->type_name("PX")
      ->check(CLI::PositiveNumber);
  app.add_flag("--no-icp", no_icp, "merge keyframe clouds at their poses without ICP");
  app.add_option("--max-icp-correction-m", max_icp_correction_m,
                 "largest ICP correction applied, metres; larger ones, unconverged ones and\n"
                 "ones pairing < 30% of points are reported, not applied")
      ->type_name("M")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--max-icp-correction-deg", max_icp_correction_deg, "largest ICP correction applied, degrees")
      ->type_name("D")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--threads", threads, "worker threads, 1-256 (default: all cores)")
      ->type_name("T")
      ->default_str("")
      ->check(CLI::Range(1, 256));
  app.add_option("--seed", seed, "seed of the depth simulation")->type_name("S");
  if (const int exit = cli::Parse(&app, argc, argv); exit != cli::kContinue) return exit;
  const bool icp = !no_icp;

  StatusOr<Sequence> seq = LoadSequence(sequence_dir);
  if (!seq.ok()) return Fail(seq.status().ToString());
  if (!seq->has_calibration) return Fail("sequence has no camera.yaml (the rig calibration is needed)");
  if (seq->groundtruth.empty()) return Fail("sequence has no groundtruth.txt (poses stand in for the SLAM)");
  std::error_code ec;
  for (const char* sub : {"", "/normals", "/normals_vis", "/depth", "/clouds"}) {
    std::filesystem::create_directories(out_dir + sub, ec);
    if (ec) return Fail("cannot create '" + out_dir + sub + "': " + ec.message());
  }

  const RigCalibration& rig = seq->calibration;
  ThreadPool pool(threads);
  DenseStageOptions dense_options;
  dense_options.fusion = fusion_options;
  dense_options.map.voxel_m = voxel;
  dense_options.icp_enabled = icp;
  dense_options.scale_keyframes = scale_keyframes;
  dense_options.max_edge_step = max_edge_step;
  dense_options.max_icp_correction_m = max_icp_correction_m;
  dense_options.max_icp_correction_deg = max_icp_correction_deg;
  dense_options.world_in_slam_units = false;  // ground-truth poses with the simulated scale: metric
  StatusOr<std::unique_ptr<DenseStage>> stage = DenseStage::Create(rig, dense_options, &pool);
  if (!stage.ok()) return Fail(stage.status().ToString());
  NormalErrorAccumulator ps_error, fused_error, prior_error;
  // The same comparison restricted to the pixels where both PS and fusion give a normal.
  NormalErrorAccumulator ps_common_error, fused_common_error, corrected_common_error;
  double ps_ms = 0, fusion_ms = 0, icp_ms = 0;
  // Pooled over keyframes: squared depth errors (metres^2) and pixel counts, and coverage.
  double fused_sse = 0, semi_sse = 0, min_coverage = 1.0;
  long long fused_n = 0, semi_n = 0;
  Json per_keyframe = Json::array();
  int keyframes = 0;

  for (size_t i = 0; i < seq->frames.size() && keyframes < max_keyframes; i += keyframe_step) {
    StatusOr<cv::Mat> rgb = seq->ReadRgb(i);
    StatusOr<cv::Mat> truth_depth = seq->ReadDepth(i);
    StatusOr<Rigid3d> pose = seq->GroundTruthPose(i);
    if (!rgb.ok()) return Fail(rgb.status().ToString());
    if (!truth_depth.ok()) return Fail("frame " + std::to_string(i) + ": " + truth_depth.status().ToString());
    if (!pose.ok()) return Fail(pose.status().ToString());
    const std::string name = Stem(seq->frames[i].rgb_file);

    synth::SemiDenseOptions sd;
    sd.scale = slam_scale;
    sd.relative_noise = depth_noise;
    sd.seed = seed * 1000003u + static_cast<uint32_t>(i);
    DenseKeyframe keyframe;
    keyframe.id = static_cast<uint64_t>(i);
    keyframe.rgb = *rgb;
    keyframe.world_from_keyframe = Sim3d(slam_scale, pose->rotation, pose->translation);
    keyframe.depth = synth::SimulateSemiDenseDepth(*truth_depth, *rgb, sd);
    const InverseDepthMap& semi_dense = keyframe.depth;

    // Photometric stereo, fusion, depth-edge filter, cloud, ICP and map merge.
    StatusOr<DenseKeyframeResult> dense = (*stage)->Process(keyframe);
    if (!dense.ok()) {
      std::cerr << "prism-fuse: keyframe " << name << " skipped: " << dense.status() << "\n";
      continue;
    }
    ps_ms += dense->photometric_ms;
    fusion_ms += dense->fusion_ms;
    icp_ms += dense->map_ms;
    const PhotometricResult* ps = &dense->photometric;
    const FusionResult* fused = &dense->fusion;

    // Ground-truth comparisons (object pixels when the sequence has masks).
    cv::Mat mask;
    if (StatusOr<cv::Mat> m = seq->ReadMask(i); m.ok()) mask = *m == kMaskObject;
    StatusOr<cv::Mat> truth_normals = seq->ReadNormals(i);
    double ps_median = -1, fused_median = -1;
    if (truth_normals.ok()) {
      (void)ps_error.Add(ps->normals, *truth_normals, mask);
      (void)fused_error.Add(fused->normals, *truth_normals, mask);
      (void)prior_error.Add(ps->prior_normals, *truth_normals, mask);
      cv::Mat common = NonZeroNormals(ps->normals) & NonZeroNormals(fused->normals);
      if (!mask.empty()) common &= mask;
      (void)ps_common_error.Add(ps->normals, *truth_normals, common);
      (void)fused_common_error.Add(fused->normals, *truth_normals, common);
      if (!fused->corrected_normals.empty())
        (void)corrected_common_error.Add(fused->corrected_normals, *truth_normals, common);
      if (auto e = ComputeNormalError(ps->normals, *truth_normals, mask); e.ok()) ps_median = e->median_deg;
      if (auto e = ComputeNormalError(fused->normals, *truth_normals, mask); e.ok()) fused_median = e->median_deg;
    }
    cv::Mat semi_dense_m(truth_depth->size(), CV_32F, cv::Scalar(0));
    for (int y = 0; y < semi_dense_m.rows; ++y)
      for (int x = 0; x < semi_dense_m.cols; ++x) {
        const float id = semi_dense.inverse_depth.at<float>(y, x);
        if (id > 0) semi_dense_m.at<float>(y, x) = static_cast<float>(slam_scale / id);
      }
    const cv::Mat& fused_depth = dense->depth;
    const cv::Mat fused_m = fused_depth * slam_scale;
    const cv::Mat eval_mask = mask.empty() ? cv::Mat(truth_depth->size(), CV_8U, cv::Scalar(255)) : mask;
    int n_fused = 0, n_semi = 0;
    const double fused_rmse = DepthRmse(fused_m, *truth_depth, eval_mask, &n_fused);
    const double semi_rmse = DepthRmse(semi_dense_m, *truth_depth, eval_mask, &n_semi);
    const int eval_pixels = cv::countNonZero(eval_mask & (*truth_depth > 0));
    fused_sse += fused_rmse * fused_rmse * n_fused;
    semi_sse += semi_rmse * semi_rmse * n_semi;
    fused_n += n_fused;
    semi_n += n_semi;
    if (eval_pixels > 0) min_coverage = std::min(min_coverage, static_cast<double>(n_fused) / eval_pixels);

    // Outputs of the keyframe.
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

    const PointCloud* cloud = &dense->cloud;
    (void)WritePointCloudPly(out_dir + "/clouds/" + name + ".ply", *cloud);
    Json icp_json = nullptr;
    if (dense->icp_attempted)
      icp_json = Json{{"converged", dense->icp.converged},
                      {"inlier_rmse_m", dense->icp.inlier_rmse_m},
                      {"inlier_fraction", dense->icp.inlier_fraction},
                      {"correction_m", dense->icp_estimate.translation.norm()},
                      {"correction_deg", RotationAngle(dense->icp_estimate.rotation) * 180 / M_PI}};
    per_keyframe.push_back(Json{{"frame", i},
                                {"timestamp", name},
                                {"ps_median_deg", ps_median},
                                {"fused_median_deg", fused_median},
                                {"semi_dense_rmse_m", semi_rmse},
                                {"fused_rmse_m", fused_rmse},
                                {"semi_dense_coverage", eval_pixels ? static_cast<double>(n_semi) / eval_pixels : 0.0},
                                {"fused_coverage", eval_pixels ? static_cast<double>(n_fused) / eval_pixels : 0.0},
                                {"depth_scale", ps->depth_scale},
                                {"cloud_points", cloud->size()},
                                {"cg_iterations", fused->iterations},
                                {"icp", icp_json}});
    ++keyframes;
    std::cerr << "prism-fuse: keyframe " << keyframes << " (" << name << "): PS " << ps_median << " deg, fused "
              << fused_median << " deg, depth RMSE " << fused_rmse << " m (semi-dense " << semi_rmse << " m)\n";
  }
  if (keyframes == 0) return Fail("no keyframe could be processed");

  const PointCloud merged = (*stage)->map().ToPointCloud();
  if (Status s = WritePointCloudPly(out_dir + "/map.ply", merged); !s.ok()) return Fail(s.ToString());
  const AngularErrorStats ps_stats = ps_error.Summarize(), fused_stats = fused_error.Summarize(),
                          prior_stats = prior_error.Summarize(), ps_common = ps_common_error.Summarize(),
                          fused_common = fused_common_error.Summarize(),
                          corrected_common = corrected_common_error.Summarize();
  Json json;
  json["keyframes"] = keyframes;
  json["map_points"] = merged.size();
  json["session_depth_scale"] = (*stage)->depth_scale().has_value() ? (*stage)->depth_scale().value() : 0.0;
  json["slam_scale_true"] = slam_scale;
  json["ps_median_deg"] = ps_stats.median_deg;
  json["ps_mean_deg"] = ps_stats.mean_deg;
  json["fused_normal_median_deg"] = fused_stats.median_deg;
  json["prior_normal_median_deg"] = prior_stats.median_deg;
  json["ps_median_common_deg"] = ps_common.median_deg;
  json["fused_normal_median_common_deg"] = fused_common.median_deg;
  json["corrected_normal_median_common_deg"] = corrected_common.median_deg;
  json["common_normal_pixels"] = ps_common_error.count();
  json["fused_depth_rmse_m"] = fused_n ? std::sqrt(fused_sse / fused_n) : 0.0;
  json["semi_dense_depth_rmse_m"] = semi_n ? std::sqrt(semi_sse / semi_n) : 0.0;
  json["min_fused_coverage"] = min_coverage;
  json["ps_ms_per_keyframe"] = ps_ms / keyframes;
  json["fusion_ms_per_keyframe"] = fusion_ms / keyframes;
  json["icp_merge_ms_per_keyframe"] = icp_ms / keyframes;
  json["per_keyframe"] = per_keyframe;
  const std::string text = JsonText(json, 2);
  std::cout << text;
  std::ofstream(out_dir + "/summary.json") << text;
  return 0;
}
