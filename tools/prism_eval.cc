// prism-eval: metrics of a reconstruction against ground truth, printed as one JSON object on stdout;
// subcommands traj (ATE / RPE), cloud (accuracy / completeness / F-score), normals and depth.
// Errors go to stderr as one readable line; exit status 2 for bad arguments, 1 for unreadable input or
// failed evaluation, 0 on success.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "core/eval/cloud_metrics.h"
#include "core/eval/depth_metrics.h"
#include "core/eval/normal_metrics.h"
#include "core/eval/trajectory_metrics.h"
#include "core/io/image_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

constexpr int kExitOk = 0;
constexpr int kExitFailure = 1;
constexpr int kExitUsage = 2;

int Fail(const std::string& command, int exit_code, const Status& status) {
  std::fprintf(stderr, "prism-eval %s: error: %s\n", command.c_str(), status.message().c_str());
  if (exit_code == kExitUsage) std::fprintf(stderr, "Run 'prism-eval %s --help' for usage.\n", command.c_str());
  return exit_code;
}

// The result as an indented JSON object on stdout (NaN and infinities as null).
void Print(const Json& json) {
  const std::string s = JsonText(json, 2);
  std::fwrite(s.data(), 1, s.size(), stdout);
  std::fflush(stdout);
}

// mask == kMaskObject -> 255, else 0 (for the metrics' "mask != 0" convention).
cv::Mat ObjectMask(const cv::Mat& mask) {
  cv::Mat out = (mask == kMaskObject);
  return out;
}

// ---------------------------------------------------------------------------------------------------
// traj

constexpr char kTrajNotes[] =
    "Computed as the TUM RGB-D benchmark scripts do (associate.py, evaluate_ate.py, evaluate_rpe.py\n"
    "--fixed_delta). Files are TUM ('t tx ty tz qx qy qz qw') or KITTI (12 numbers per line, detected\n"
    "automatically); KITTI poses without --*-times get their line index as timestamp (they associate by\n"
    "index). Also (not in the TUM scripts): the orientation error after the ATE's alignment\n"
    "(orientation_*_deg; needs positions that span more than a line) and the net rotation, first to last\n"
    "pose (net_rotation_gt_deg, net_rotation_est_deg).\n"
    "\n"
    "Prints JSON: ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_min_m, ate_max_m, pairs, scale,\n"
    "rpe_trans_rmse_m, rpe_trans_mean_m, rpe_trans_median_m, rpe_rot_rmse_deg, rpe_rot_mean_deg,\n"
    "rpe_rot_median_deg, rpe_pairs, trajectory_length_m (ground-truth path over associated poses),\n"
    "ate_percent_of_length, and the settings used. When no RPE pair exists the rpe_* values are null\n"
    "and rpe_error says why.";

struct TrajArgs {
  std::string gt, est, align = "se3", delta_unit = "f", gt_times, est_times;
  TrajectoryEvalOptions options;
};

CLI::App* AddTraj(CLI::App* app, TrajArgs* a) {
  CLI::App* sub = app->add_subcommand("traj", "ATE / RPE of an estimated trajectory (TUM or KITTI files)");
  cli::Setup(sub, sub->get_description(), {"prism-eval traj --gt GT.txt --est EST.txt [options]"}, kTrajNotes);
  sub->add_option("--gt", a->gt, "ground-truth trajectory")->type_name("FILE")->required();
  sub->add_option("--est", a->est, "estimated trajectory")->type_name("FILE")->required();
  sub->add_option("--align", a->align, "none|se3|sim3: alignment of the estimate before the ATE")->type_name("MODE");
  sub->add_option("--max-diff", a->options.max_time_difference_s, "max timestamp difference for association, s")
      ->type_name("S");
  sub->add_option("--delta", a->options.rpe_delta, "RPE step")->type_name("N");
  sub->add_option("--delta-unit", a->delta_unit, "f (frames) | s (seconds)")->type_name("U");
  sub->add_option("--gt-times", a->gt_times, "timestamps for a KITTI ground-truth file (one per line)")
      ->type_name("FILE");
  sub->add_option("--est-times", a->est_times, "timestamps for a KITTI estimate file")->type_name("FILE");
  return sub;
}

StatusOr<Trajectory> ReadTrajectoryArg(const std::string& path, const std::string& times_path) {
  if (!times_path.empty()) return ReadKittiTrajectory(path, times_path);
  return ReadTrajectoryAutoDetect(path);
}

int RunTraj(TrajArgs& args) {
  const std::string cmd = "traj";
  TrajectoryEvalOptions& options = args.options;
  auto align = ParseAlignmentModel(args.align);
  if (!align.ok()) return Fail(cmd, kExitUsage, align.status());
  options.alignment = *align;
  auto unit = ParseRpeDeltaUnit(args.delta_unit);
  if (!unit.ok()) return Fail(cmd, kExitUsage, unit.status());
  options.rpe_delta_unit = *unit;
  if (Status s = options.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);

  auto gt = ReadTrajectoryArg(args.gt, args.gt_times);
  if (!gt.ok()) return Fail(cmd, kExitFailure, gt.status());
  auto est = ReadTrajectoryArg(args.est, args.est_times);
  if (!est.ok()) return Fail(cmd, kExitFailure, est.status());

  auto ate = ComputeAte(*gt, *est, options);
  if (!ate.ok()) return Fail(cmd, kExitFailure, ate.status());
  const auto rpe = ComputeRpe(*gt, *est, options, ate->gt_from_est.scale);

  Json json;
  json["ate_rmse_m"] = ate->error_m.rmse;
  json["ate_mean_m"] = ate->error_m.mean;
  json["ate_median_m"] = ate->error_m.median;
  json["ate_std_m"] = ate->error_m.std_dev;
  json["ate_min_m"] = ate->error_m.min;
  json["ate_max_m"] = ate->error_m.max;
  json["pairs"] = ate->pairs;
  json["align"] = AlignmentModelName(options.alignment);
  json["scale"] = ate->gt_from_est.scale;
  // Not in the TUM scripts: the orientations after the alignment, and the net rotation (first to last).
  json["orientation_rmse_deg"] = ate->orientation_error_deg.rmse;
  json["orientation_max_deg"] = ate->orientation_error_deg.max;
  json["net_rotation_gt_deg"] = ate->net_rotation_deg_gt;
  json["net_rotation_est_deg"] = ate->net_rotation_deg_est;
  if (rpe.ok()) {
    json["rpe_trans_rmse_m"] = rpe->trans_error_m.rmse;
    json["rpe_trans_mean_m"] = rpe->trans_error_m.mean;
    json["rpe_trans_median_m"] = rpe->trans_error_m.median;
    json["rpe_rot_rmse_deg"] = rpe->rot_error_deg.rmse;
    json["rpe_rot_mean_deg"] = rpe->rot_error_deg.mean;
    json["rpe_rot_median_deg"] = rpe->rot_error_deg.median;
    json["rpe_pairs"] = rpe->pairs;
  } else {
    for (const char* key : {"rpe_trans_rmse_m", "rpe_trans_mean_m", "rpe_trans_median_m", "rpe_rot_rmse_deg",
                            "rpe_rot_mean_deg", "rpe_rot_median_deg"})
      json[key] = nullptr;
    json["rpe_pairs"] = 0;
    json["rpe_error"] = rpe.status().message();
  }
  json["rpe_delta"] = options.rpe_delta;
  json["rpe_delta_unit"] = RpeDeltaUnitName(options.rpe_delta_unit);
  json["max_diff_s"] = options.max_time_difference_s;
  json["trajectory_length_m"] = ate->trajectory_length_m;
  if (ate->trajectory_length_m > 0.0)
    json["ate_percent_of_length"] = 100.0 * ate->error_m.rmse / ate->trajectory_length_m;
  else json["ate_percent_of_length"] = nullptr;
  json["gt_poses"] = gt->size();
  json["est_poses"] = est->size();
  Print(json);
  return kExitOk;
}

// ---------------------------------------------------------------------------------------------------
// cloud

constexpr char kCloudNotes[] =
    "Ground-truth surface samples are the ground-truth depth of every K-th frame back-projected with its\n"
    "ground-truth pose, voxel-downsampled to tau / 4.\n"
    "\n"
    "Prints JSON: accuracy_m (mean), accuracy_median_m, precision, completeness, fscore, points,\n"
    "non_finite_points, tau_m, tau_source (given | bbox_diagonal_1pct | default_5mm), gt_samples,\n"
    "gt_frames, gt_voxel_m, frame_step, object_only.";

struct CloudArgs {
  std::string sequence, cloud, align_trajectory;
  int threads = 0;
  CloudEvalOptions options;
  SurfaceSamplingOptions sampling;
  CLI::Option* tau = nullptr;
};

CLI::App* AddCloud(CLI::App* app, CloudArgs* a) {
  CLI::App* sub = app->add_subcommand("cloud", "accuracy / completeness / F-score of a reconstructed point cloud");
  cli::Setup(sub, sub->get_description(), {"prism-eval cloud --sequence DIR --cloud FILE.ply [options]"}, kCloudNotes);
  sub->add_option("--sequence", a->sequence, "sequence with camera.yaml, depth/ and groundtruth.txt")
      ->type_name("DIR")
      ->required();
  sub->add_option("--cloud", a->cloud, "reconstructed cloud, PLY, in the ground truth's world frame")
      ->type_name("FILE")
      ->required();
  a->tau = sub->add_option("--tau", a->options.tau_m,
                           "distance threshold, metres (default: 1% of the ground-truth samples'\n"
                           "bounding-box diagonal with --object-only, else 0.005)")
               ->type_name("M")
               ->default_str("");
  sub->add_flag("--object-only", a->sampling.object_only,
                "ground truth from object pixels only (mask == 255), and only the\n"
                "reconstructed points seen on the object in those frames (not hidden\n"
                "more than 3 tau behind its surface)");
  sub->add_option("--frame-step", a->sampling.frame_step, "use every K-th frame for the ground truth")->type_name("K");
  sub->add_option("--threads", a->threads, "threads for the distance queries (0 = all cores)")
      ->type_name("N")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--align-trajectory", a->align_trajectory,
                  "the cloud is in the frame of this estimated trajectory (TUM/KITTI, e.g.\n"
                  "SLAM output): it is moved by the Sim(3) that aligns EST to the ground\n"
                  "truth (as prism-eval traj --align sim3) before it is scored")
      ->type_name("EST");
  return sub;
}

int RunCloud(CloudArgs& args) {
  const std::string cmd = "cloud";
  CloudEvalOptions& options = args.options;
  SurfaceSamplingOptions& sampling = args.sampling;
  const int threads = args.threads;
  std::string tau_source = args.tau->count() > 0 ? "given" : "";
  if (Status s = options.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);
  if (Status s = sampling.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);

  auto sequence = LoadSequence(args.sequence);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto cloud = ReadPointCloudPly(args.cloud);
  if (!cloud.ok()) return Fail(cmd, kExitFailure, cloud.status());
  double alignment_scale = 1.0;
  if (!args.align_trajectory.empty()) {
    auto est = ReadTrajectoryAutoDetect(args.align_trajectory);
    if (!est.ok()) return Fail(cmd, kExitFailure, est.status());
    TrajectoryEvalOptions align_options;
    align_options.alignment = AlignmentModel::kSim3;
    auto ate = ComputeAte(sequence->groundtruth, *est, align_options);
    if (!ate.ok()) return Fail(cmd, kExitFailure, ate.status());
    const Sim3d& t = ate->gt_from_est;
    alignment_scale = t.scale;
    for (auto& p : cloud->positions) p = (t * p.cast<double>()).cast<float>();
    for (auto& n : cloud->normals) n = (t.rotation * n.cast<double>()).cast<float>();
  }

  if (tau_source.empty()) {
    if (sampling.object_only) {
      auto bounds = GroundTruthSurfaceBounds(*sequence, sampling);
      if (!bounds.ok()) return Fail(cmd, kExitFailure, bounds.status());
      options.tau_m = 0.01 * bounds->diagonal().norm();
      tau_source = "bbox_diagonal_1pct";
      if (!(options.tau_m > 0.0))
        return Fail(cmd, kExitFailure, FailedPreconditionError("the ground-truth object samples have zero extent"));
    } else {
      tau_source = "default_5mm";
    }
  }
  sampling.voxel_size_m = options.tau_m / 4.0;
  auto samples = SampleGroundTruthSurface(*sequence, sampling);
  if (!samples.ok()) return Fail(cmd, kExitFailure, samples.status());

  std::unique_ptr<ThreadPool> pool;
  if (threads != 1) pool = std::make_unique<ThreadPool>(threads);
  // Object-only: the reconstruction is restricted to the points seen on the object (see
  // SelectPointsSeenOnObject), so the floor around it neither helps nor hurts.
  std::vector<Eigen::Vector3f> evaluated = cloud->positions;
  if (sampling.object_only) {
    auto selected = SelectPointsSeenOnObject(*sequence, cloud->positions, sampling, 3.0 * options.tau_m);
    if (!selected.ok()) return Fail(cmd, kExitFailure, selected.status());
    evaluated.clear();
    for (size_t i : *selected) evaluated.push_back(cloud->positions[i]);
    if (evaluated.empty() && !cloud->positions.empty())
      return Fail(cmd, kExitFailure,
                  FailedPreconditionError("--object-only: none of the " + std::to_string(cloud->positions.size()) +
                                          " reconstructed points is seen on the object in the ground-truth frames "
                                          "(is the cloud in the ground truth's world frame? see --align-trajectory)"));
  }
  auto metrics = EvaluateCloud(evaluated, samples->points_in_world, options, pool.get());
  if (!metrics.ok()) return Fail(cmd, kExitFailure, metrics.status());

  Json json;
  json["accuracy_m"] = metrics->accuracy_mean_m;
  json["accuracy_median_m"] = metrics->accuracy_median_m;
  json["precision"] = metrics->precision;
  json["completeness"] = metrics->completeness;
  json["fscore"] = metrics->fscore;
  json["points"] = metrics->points;
  json["cloud_points"] = cloud->size();
  json["non_finite_points"] = metrics->non_finite_points;
  json["tau_m"] = metrics->tau_m;
  json["tau_source"] = tau_source;
  json["gt_samples"] = metrics->gt_samples;
  json["gt_frames"] = samples->frames_used;
  json["gt_voxel_m"] = sampling.voxel_size_m;
  json["frame_step"] = sampling.frame_step;
  json["object_only"] = sampling.object_only;
  if (!args.align_trajectory.empty()) json["aligned_with_scale"] = alignment_scale;
  Print(json);
  return kExitOk;
}

// ---------------------------------------------------------------------------------------------------
// normals and depth: per-frame images in a directory, matched to the sequence by file name.

// Files of `dir` (regular, sorted by name) matched to the sequence frame whose `member` file (e.g.
// normal_file) has the same name. Unmatched names are counted.
struct MatchedFiles {
  std::vector<std::pair<std::string, size_t>> matches;  // (path in dir, frame index)
  size_t unmatched = 0;
};

StatusOr<MatchedFiles> MatchFrames(const std::string& dir, const Sequence& sequence, std::string SequenceFrame::*member,
                                   const std::string& what) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return NotFoundError("'" + dir + "' is not a directory");
  std::map<std::string, size_t> frame_by_name;
  for (size_t i = 0; i < sequence.frames.size(); ++i) {
    const std::string& file = sequence.frames[i].*member;
    if (!file.empty()) frame_by_name.emplace(fs::path(file).filename().string(), i);
  }
  if (frame_by_name.empty()) return FailedPreconditionError("sequence '" + sequence.root + "' has no " + what);
  std::vector<std::string> names;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec))
    if (it->is_regular_file()) names.push_back(it->path().filename().string());
  if (ec) return UnavailableError("cannot list '" + dir + "': " + ec.message());
  std::sort(names.begin(), names.end());
  MatchedFiles out;
  for (const std::string& name : names) {
    const auto it = frame_by_name.find(name);
    if (it == frame_by_name.end()) {
      ++out.unmatched;
      continue;
    }
    out.matches.emplace_back((fs::path(dir) / name).string(), it->second);
  }
  if (out.matches.empty())
    return NotFoundError("no file in '" + dir + "' has the name of one of the sequence's " + what + " (e.g. '" +
                         frame_by_name.begin()->first + "')");
  return out;
}

// The object mask of frame i (mask == kMaskObject), or an empty Mat when !object_only.
StatusOr<cv::Mat> FrameMask(const Sequence& sequence, size_t i, bool object_only) {
  if (!object_only) return cv::Mat();
  if (sequence.frames[i].mask_file.empty())
    return NotFoundError("--object-only: frame " + sequence.frames[i].rgb_file + " has no mask");
  PRISM_ASSIGN_OR_RETURN(const cv::Mat mask, sequence.ReadMask(i));
  return ObjectMask(mask);
}

constexpr char kNormalsNotes[] =
    "The --normals directory holds 16-bit PNG normal maps in the sequence format (camera frame,\n"
    "(n+1)/2*65535) named like the files in the sequence's normals/ folder; every matching file is\n"
    "evaluated and the statistics are over all pixels of all files (pixels where both normals are valid).\n"
    "\n"
    "Prints JSON: mean_deg, median_deg, rmse_deg, pct_under_5, pct_under_10, pct_under_20 (percent),\n"
    "pixels, frames, unmatched_files, object_only.";

// normals and depth: a folder of per-frame images scored against the sequence's.
struct MapsArgs {
  std::string sequence, maps, scale_align = "median";
  bool object_only = false;
};

CLI::App* AddNormals(CLI::App* app, MapsArgs* a) {
  CLI::App* sub = app->add_subcommand("normals", "angular error of estimated normal maps");
  cli::Setup(sub, sub->get_description(), {"prism-eval normals --sequence DIR --normals DIR [--object-only]"},
             kNormalsNotes);
  sub->add_option("--sequence", a->sequence, "sequence with normals.txt and normals/")->type_name("DIR")->required();
  sub->add_option("--normals", a->maps, "estimated normal maps")->type_name("DIR")->required();
  sub->add_flag("--object-only", a->object_only, "only object pixels (mask == 255)");
  return sub;
}

int RunNormals(const MapsArgs& args) {
  const std::string cmd = "normals";
  const bool object_only = args.object_only;
  auto sequence = LoadSequence(args.sequence);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto matched = MatchFrames(args.maps, *sequence, &SequenceFrame::normal_file, "normal maps");
  if (!matched.ok()) return Fail(cmd, kExitFailure, matched.status());

  NormalErrorAccumulator acc;
  for (const auto& [path, i] : matched->matches) {
    auto estimate = ReadNormalPng(path);
    if (!estimate.ok()) return Fail(cmd, kExitFailure, estimate.status());
    auto gt = sequence->ReadNormals(i);
    if (!gt.ok()) return Fail(cmd, kExitFailure, gt.status());
    auto mask = FrameMask(*sequence, i, object_only);
    if (!mask.ok()) return Fail(cmd, kExitFailure, mask.status());
    if (Status s = acc.Add(*estimate, *gt, *mask); !s.ok())
      return Fail(cmd, kExitFailure, InvalidArgumentError(path + ": " + s.message()));
  }
  const AngularErrorStats stats = acc.Summarize();
  Json json;
  json["mean_deg"] = stats.count ? stats.mean_deg : NAN;
  json["median_deg"] = stats.count ? stats.median_deg : NAN;
  json["rmse_deg"] = stats.count ? stats.rmse_deg : NAN;
  json["pct_under_5"] = stats.count ? stats.pct_under_5 : NAN;
  json["pct_under_10"] = stats.count ? stats.pct_under_10 : NAN;
  json["pct_under_20"] = stats.count ? stats.pct_under_20 : NAN;
  json["pixels"] = stats.count;
  json["frames"] = matched->matches.size();
  json["unmatched_files"] = matched->unmatched;
  json["object_only"] = object_only;
  Print(json);
  return kExitOk;
}

constexpr char kDepthNotes[] =
    "One scale alignment over all pixels. The --depth directory holds 16-bit PNG depth maps (5000 per\n"
    "metre, 0 = none) named like the files in the sequence's depth/ folder; every matching file is\n"
    "evaluated.\n"
    "\n"
    "Prints JSON: rmse_m, mean_abs_m, median_rel_error, coverage (pixels with both depths / pixels with\n"
    "ground truth), scale, scale_align, pixels, gt_pixels, frames, unmatched_files, object_only.";

CLI::App* AddDepth(CLI::App* app, MapsArgs* a) {
  CLI::App* sub = app->add_subcommand("depth", "scale-aligned error of estimated depth maps");
  cli::Setup(sub, sub->get_description(),
             {"prism-eval depth --sequence DIR --depth DIR [--object-only] [--scale-align MODE]"}, kDepthNotes);
  sub->add_option("--sequence", a->sequence, "sequence with depth.txt and depth/")->type_name("DIR")->required();
  sub->add_option("--depth", a->maps, "estimated depth maps")->type_name("DIR")->required();
  sub->add_flag("--object-only", a->object_only, "only object pixels (mask == 255)");
  sub->add_option("--scale-align", a->scale_align, "median (of gt/est ratios) | least_squares | none")
      ->type_name("MODE");
  return sub;
}

int RunDepth(const MapsArgs& args) {
  const std::string cmd = "depth";
  const bool object_only = args.object_only;
  DepthEvalOptions options;
  auto align = ParseDepthScaleAlignment(args.scale_align);
  if (!align.ok()) return Fail(cmd, kExitUsage, align.status());
  options.scale_alignment = *align;

  auto sequence = LoadSequence(args.sequence);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto matched = MatchFrames(args.maps, *sequence, &SequenceFrame::depth_file, "depth images");
  if (!matched.ok()) return Fail(cmd, kExitFailure, matched.status());

  DepthErrorAccumulator acc;
  for (const auto& [path, i] : matched->matches) {
    auto estimate = ReadDepthPng(path);
    if (!estimate.ok()) return Fail(cmd, kExitFailure, estimate.status());
    auto gt = sequence->ReadDepth(i);
    if (!gt.ok()) return Fail(cmd, kExitFailure, gt.status());
    auto mask = FrameMask(*sequence, i, object_only);
    if (!mask.ok()) return Fail(cmd, kExitFailure, mask.status());
    if (Status s = acc.Add(*estimate, *gt, *mask); !s.ok())
      return Fail(cmd, kExitFailure, InvalidArgumentError(path + ": " + s.message()));
  }
  auto stats = acc.Summarize(options);
  if (!stats.ok()) return Fail(cmd, kExitFailure, stats.status());
  Json json;
  json["rmse_m"] = stats->rmse_m;
  json["mean_abs_m"] = stats->mean_abs_m;
  json["median_rel_error"] = stats->median_rel_error;
  json["coverage"] = stats->coverage;
  json["scale"] = stats->scale;
  json["scale_align"] = DepthScaleAlignmentName(options.scale_alignment);
  json["pixels"] = stats->pixels;
  json["gt_pixels"] = stats->gt_pixels;
  json["frames"] = matched->matches.size();
  json["unmatched_files"] = matched->unmatched;
  json["object_only"] = object_only;
  Print(json);
  return kExitOk;
}

int Main(int argc, char** argv) {
  CLI::App app{"", "prism-eval"};
  cli::Setup(&app, "metrics of a reconstruction against ground truth, one JSON object on stdout",
             {"prism-eval traj|cloud|normals|depth [options]   ('prism-eval COMMAND --help': its options)"},
             "Exit status: 0 success, 1 unreadable input or failed evaluation, 2 bad arguments.");
  app.require_subcommand(1);
  TrajArgs traj;
  CloudArgs cloud;
  MapsArgs normals, depth;
  CLI::App* traj_cmd = AddTraj(&app, &traj);
  CLI::App* cloud_cmd = AddCloud(&app, &cloud);
  CLI::App* normals_cmd = AddNormals(&app, &normals);
  CLI::App* depth_cmd = AddDepth(&app, &depth);
  if (const int exit = cli::Parse(&app, argc, argv, kExitUsage); exit != cli::kContinue) return exit;
  if (traj_cmd->parsed()) return RunTraj(traj);
  if (cloud_cmd->parsed()) return RunCloud(cloud);
  if (normals_cmd->parsed()) return RunNormals(normals);
  if (depth_cmd->parsed()) return RunDepth(depth);
  return kExitUsage;
}

}  // namespace
}  // namespace prism

int main(int argc, char** argv) {
  try {
    return prism::Main(argc, argv);
  } catch (const std::exception& e) {
    // A PRISM_CHECK failure is a bug in prism, not in the input; say so instead of aborting silently.
    std::fprintf(stderr, "prism-eval: internal error: %s\n", e.what());
    return 3;
  }
}
