// prism-eval: metrics of a reconstruction against ground truth, printed as one JSON object on stdout.
//
//   prism-eval traj    --gt GT.txt --est EST.txt [--align none|se3|sim3] ...   ATE / RPE (TUM tools' numbers)
//   prism-eval cloud   --sequence DIR --cloud FILE.ply [--tau M] ...           accuracy / completeness / F-score
//   prism-eval normals --sequence DIR --normals DIR [--object-only]            normal angular error
//   prism-eval depth   --sequence DIR --depth DIR [--object-only] ...          scale-aligned depth error
//
// Errors go to stderr as one readable line; exit status 2 for bad arguments, 1 for unreadable input or
// failed evaluation, 0 on success.
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <memory>
#include <set>
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
#include "core/util/json_text.h"
#include "core/util/status.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

namespace fs = std::filesystem;

constexpr int kExitOk = 0;
constexpr int kExitFailure = 1;
constexpr int kExitUsage = 2;

// ---------------------------------------------------------------------------------------------------
// A flat JSON object writer: keys in insertion order, numbers with 9 significant digits, non-finite
// numbers as null.
class JsonObject {
 public:
  void Number(const std::string& key, double value) {
    if (!std::isfinite(value)) return Raw(key, "null");
    char buf[64];
    std::snprintf(buf, sizeof(buf), "%.9g", value);
    Raw(key, buf);
  }
  void Integer(const std::string& key, long long value) { Raw(key, std::to_string(value)); }
  void Bool(const std::string& key, bool value) { Raw(key, value ? "true" : "false"); }
  void Null(const std::string& key) { Raw(key, "null"); }
  void String(const std::string& key, const std::string& value) { Raw(key, JsonQuote(value)); }

  std::string ToString() const {
    std::string out = "{\n";
    for (size_t i = 0; i < fields_.size(); ++i) {
      out += "  " + JsonQuote(fields_[i].first) + ": " + fields_[i].second;
      out += i + 1 < fields_.size() ? ",\n" : "\n";
    }
    return out + "}\n";
  }

 private:
  void Raw(const std::string& key, std::string value) { fields_.emplace_back(key, std::move(value)); }

  std::vector<std::pair<std::string, std::string>> fields_;
};

// ---------------------------------------------------------------------------------------------------
// Command-line flags: "--name value", "--name=value" or a bare "--name" for switches.
class Flags {
 public:
  // `valued`: flags that take a value; `switches`: flags without one.
  static StatusOr<Flags> Parse(const std::vector<std::string>& args, const std::set<std::string>& valued,
                               const std::set<std::string>& switches) {
    Flags flags;
    for (size_t i = 0; i < args.size(); ++i) {
      const std::string& arg = args[i];
      if (arg.rfind("--", 0) != 0) return InvalidArgumentError("unexpected argument '" + arg + "'");
      std::string name = arg.substr(2);
      std::string value;
      bool has_value = false;
      const size_t eq = name.find('=');
      if (eq != std::string::npos) {
        value = name.substr(eq + 1);
        name = name.substr(0, eq);
        has_value = true;
      }
      if (switches.count(name)) {
        if (has_value) return InvalidArgumentError("--" + name + " takes no value");
        flags.values_[name] = "true";
      } else if (valued.count(name)) {
        if (!has_value) {
          if (i + 1 >= args.size()) return InvalidArgumentError("--" + name + " needs a value");
          value = args[++i];
        }
        flags.values_[name] = value;
      } else {
        return InvalidArgumentError("unknown option '--" + name + "'");
      }
    }
    return flags;
  }

  bool Has(const std::string& name) const { return values_.count(name) > 0; }
  std::string Get(const std::string& name, const std::string& fallback = "") const {
    const auto it = values_.find(name);
    return it == values_.end() ? fallback : it->second;
  }
  StatusOr<std::string> Required(const std::string& name) const {
    if (!Has(name) || Get(name).empty()) return InvalidArgumentError("missing required option --" + name);
    return Get(name);
  }
  StatusOr<double> Double(const std::string& name, double fallback) const {
    if (!Has(name)) return fallback;
    const std::string s = Get(name);
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(s.c_str(), &end);
    if (s.empty() || *end != '\0' || errno == ERANGE || !std::isfinite(v))
      return InvalidArgumentError("--" + name + " expects a number, got '" + s + "'");
    return v;
  }
  StatusOr<int> Int(const std::string& name, int fallback) const {
    if (!Has(name)) return fallback;
    const std::string s = Get(name);
    char* end = nullptr;
    errno = 0;
    const long v = std::strtol(s.c_str(), &end, 10);
    if (s.empty() || *end != '\0' || errno == ERANGE || v < -1000000000L || v > 1000000000L)
      return InvalidArgumentError("--" + name + " expects an integer, got '" + s + "'");
    return static_cast<int>(v);
  }

 private:
  std::map<std::string, std::string> values_;
};

bool WantsHelp(const std::vector<std::string>& args) {
  return std::any_of(args.begin(), args.end(), [](const std::string& a) { return a == "--help" || a == "-h"; });
}

int Fail(const std::string& command, int exit_code, const Status& status) {
  std::fprintf(stderr, "prism-eval %s: error: %s\n", command.c_str(), status.message().c_str());
  if (exit_code == kExitUsage) std::fprintf(stderr, "Run 'prism-eval %s --help' for usage.\n", command.c_str());
  return exit_code;
}

void Print(const JsonObject& json) {
  const std::string s = json.ToString();
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

constexpr char kTrajUsage[] =
    "Usage: prism-eval traj --gt GT.txt --est EST.txt [options]\n"
    "\n"
    "Absolute trajectory error (ATE) and relative pose error (RPE) of an estimated trajectory, computed\n"
    "as the TUM RGB-D benchmark scripts do (associate.py, evaluate_ate.py, evaluate_rpe.py --fixed_delta).\n"
    "Files are TUM ('t tx ty tz qx qy qz qw') or KITTI (12 numbers per line, detected automatically);\n"
    "KITTI poses without --*-times get their line index as timestamp, i.e. they associate by index.\n"
    "Also (not in the TUM scripts): the orientation error after the ATE's alignment (orientation_*_deg;\n"
    "needs positions that span more than a line) and the net rotation, first to last pose\n"
    "(net_rotation_gt_deg, net_rotation_est_deg).\n"
    "\n"
    "Options:\n"
    "  --gt FILE           ground-truth trajectory (required)\n"
    "  --est FILE          estimated trajectory (required)\n"
    "  --align MODE        none | se3 | sim3: alignment of the estimate before the ATE (default se3)\n"
    "  --max-diff S        max timestamp difference for association, seconds (default 0.02)\n"
    "  --delta N           RPE step (default 1)\n"
    "  --delta-unit U      f (frames) | s (seconds) (default f)\n"
    "  --gt-times FILE     timestamps for a KITTI ground-truth file (one per line)\n"
    "  --est-times FILE    timestamps for a KITTI estimate file\n"
    "\n"
    "Prints JSON: ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_min_m, ate_max_m, pairs, scale,\n"
    "rpe_trans_rmse_m, rpe_trans_mean_m, rpe_trans_median_m, rpe_rot_rmse_deg, rpe_rot_mean_deg,\n"
    "rpe_rot_median_deg, rpe_pairs, trajectory_length_m (ground-truth path over associated poses),\n"
    "ate_percent_of_length, and the settings used. When no RPE pair exists the rpe_* values are null\n"
    "and rpe_error says why.\n";

StatusOr<Trajectory> ReadTrajectoryArg(const std::string& path, const std::string& times_path) {
  if (!times_path.empty()) return ReadKittiTrajectory(path, times_path);
  return ReadTrajectoryAutoDetect(path);
}

int RunTraj(const std::vector<std::string>& args) {
  const std::string cmd = "traj";
  if (WantsHelp(args)) {
    std::fputs(kTrajUsage, stdout);
    return kExitOk;
  }
  auto flags =
      Flags::Parse(args, {"gt", "est", "align", "max-diff", "delta", "delta-unit", "gt-times", "est-times"}, {});
  if (!flags.ok()) return Fail(cmd, kExitUsage, flags.status());
  TrajectoryEvalOptions options;
  auto gt_path = flags->Required("gt");
  if (!gt_path.ok()) return Fail(cmd, kExitUsage, gt_path.status());
  auto est_path = flags->Required("est");
  if (!est_path.ok()) return Fail(cmd, kExitUsage, est_path.status());
  auto align = ParseAlignmentModel(flags->Get("align", "se3"));
  if (!align.ok()) return Fail(cmd, kExitUsage, align.status());
  options.alignment = *align;
  auto max_diff = flags->Double("max-diff", options.max_time_difference_s);
  if (!max_diff.ok()) return Fail(cmd, kExitUsage, max_diff.status());
  options.max_time_difference_s = *max_diff;
  auto delta = flags->Double("delta", options.rpe_delta);
  if (!delta.ok()) return Fail(cmd, kExitUsage, delta.status());
  options.rpe_delta = *delta;
  auto unit = ParseRpeDeltaUnit(flags->Get("delta-unit", "f"));
  if (!unit.ok()) return Fail(cmd, kExitUsage, unit.status());
  options.rpe_delta_unit = *unit;
  if (Status s = options.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);

  auto gt = ReadTrajectoryArg(*gt_path, flags->Get("gt-times"));
  if (!gt.ok()) return Fail(cmd, kExitFailure, gt.status());
  auto est = ReadTrajectoryArg(*est_path, flags->Get("est-times"));
  if (!est.ok()) return Fail(cmd, kExitFailure, est.status());

  auto ate = ComputeAte(*gt, *est, options);
  if (!ate.ok()) return Fail(cmd, kExitFailure, ate.status());
  const auto rpe = ComputeRpe(*gt, *est, options, ate->gt_from_est.scale);

  JsonObject json;
  json.Number("ate_rmse_m", ate->error_m.rmse);
  json.Number("ate_mean_m", ate->error_m.mean);
  json.Number("ate_median_m", ate->error_m.median);
  json.Number("ate_std_m", ate->error_m.std_dev);
  json.Number("ate_min_m", ate->error_m.min);
  json.Number("ate_max_m", ate->error_m.max);
  json.Integer("pairs", static_cast<long long>(ate->pairs));
  json.String("align", AlignmentModelName(options.alignment));
  json.Number("scale", ate->gt_from_est.scale);
  // Not in the TUM scripts: the orientations after the alignment, and the net rotation (first to last).
  json.Number("orientation_rmse_deg", ate->orientation_error_deg.rmse);
  json.Number("orientation_max_deg", ate->orientation_error_deg.max);
  json.Number("net_rotation_gt_deg", ate->net_rotation_deg_gt);
  json.Number("net_rotation_est_deg", ate->net_rotation_deg_est);
  if (rpe.ok()) {
    json.Number("rpe_trans_rmse_m", rpe->trans_error_m.rmse);
    json.Number("rpe_trans_mean_m", rpe->trans_error_m.mean);
    json.Number("rpe_trans_median_m", rpe->trans_error_m.median);
    json.Number("rpe_rot_rmse_deg", rpe->rot_error_deg.rmse);
    json.Number("rpe_rot_mean_deg", rpe->rot_error_deg.mean);
    json.Number("rpe_rot_median_deg", rpe->rot_error_deg.median);
    json.Integer("rpe_pairs", static_cast<long long>(rpe->pairs));
  } else {
    for (const char* key : {"rpe_trans_rmse_m", "rpe_trans_mean_m", "rpe_trans_median_m", "rpe_rot_rmse_deg",
                            "rpe_rot_mean_deg", "rpe_rot_median_deg"})
      json.Null(key);
    json.Integer("rpe_pairs", 0);
    json.String("rpe_error", rpe.status().message());
  }
  json.Number("rpe_delta", options.rpe_delta);
  json.String("rpe_delta_unit", RpeDeltaUnitName(options.rpe_delta_unit));
  json.Number("max_diff_s", options.max_time_difference_s);
  json.Number("trajectory_length_m", ate->trajectory_length_m);
  if (ate->trajectory_length_m > 0.0)
    json.Number("ate_percent_of_length", 100.0 * ate->error_m.rmse / ate->trajectory_length_m);
  else json.Null("ate_percent_of_length");
  json.Integer("gt_poses", static_cast<long long>(gt->size()));
  json.Integer("est_poses", static_cast<long long>(est->size()));
  Print(json);
  return kExitOk;
}

// ---------------------------------------------------------------------------------------------------
// cloud

constexpr char kCloudUsage[] =
    "Usage: prism-eval cloud --sequence DIR --cloud FILE.ply [options]\n"
    "\n"
    "Accuracy, precision, completeness and F-score of a reconstructed point cloud (world frame of the\n"
    "sequence's ground truth). Ground-truth surface samples are the ground-truth depth of every K-th frame\n"
    "back-projected with its ground-truth pose, voxel-downsampled to tau / 4.\n"
    "\n"
    "Options:\n"
    "  --sequence DIR      sequence with camera.yaml, depth/ and groundtruth.txt (required)\n"
    "  --cloud FILE        reconstructed cloud, PLY (required)\n"
    "  --tau M             distance threshold in metres (default: 1% of the ground-truth samples'\n"
    "                      bounding-box diagonal with --object-only, else 0.005)\n"
    "  --object-only       ground truth from object pixels only (mask == 255), and only the\n"
    "                      reconstructed points seen on the object in those frames (not hidden\n"
    "                      more than 3 tau behind its surface)\n"
    "  --frame-step K      use every K-th frame for the ground truth (default 10)\n"
    "  --threads N         worker threads for the distance queries (default 0 = all cores)\n"
    "  --align-trajectory EST  the cloud is in the frame of this estimated trajectory (TUM/KITTI, e.g.\n"
    "                      SLAM output): it is moved by the Sim(3) that aligns EST to the ground truth\n"
    "                      (as prism-eval traj --align sim3) before it is scored\n"
    "\n"
    "Prints JSON: accuracy_m (mean), accuracy_median_m, precision, completeness, fscore, points,\n"
    "non_finite_points, tau_m, tau_source (given | bbox_diagonal_1pct | default_5mm), gt_samples,\n"
    "gt_frames, gt_voxel_m, frame_step, object_only.\n";

int RunCloud(const std::vector<std::string>& args) {
  const std::string cmd = "cloud";
  if (WantsHelp(args)) {
    std::fputs(kCloudUsage, stdout);
    return kExitOk;
  }
  auto flags =
      Flags::Parse(args, {"sequence", "cloud", "tau", "frame-step", "threads", "align-trajectory"}, {"object-only"});
  if (!flags.ok()) return Fail(cmd, kExitUsage, flags.status());
  auto sequence_dir = flags->Required("sequence");
  if (!sequence_dir.ok()) return Fail(cmd, kExitUsage, sequence_dir.status());
  auto cloud_path = flags->Required("cloud");
  if (!cloud_path.ok()) return Fail(cmd, kExitUsage, cloud_path.status());
  SurfaceSamplingOptions sampling;
  sampling.object_only = flags->Has("object-only");
  auto frame_step = flags->Int("frame-step", sampling.frame_step);
  if (!frame_step.ok()) return Fail(cmd, kExitUsage, frame_step.status());
  sampling.frame_step = *frame_step;
  auto threads = flags->Int("threads", 0);
  if (!threads.ok()) return Fail(cmd, kExitUsage, threads.status());
  if (*threads < 0) return Fail(cmd, kExitUsage, InvalidArgumentError("--threads must be >= 0"));
  CloudEvalOptions options;
  std::string tau_source;
  if (flags->Has("tau")) {
    auto tau = flags->Double("tau", options.tau_m);
    if (!tau.ok()) return Fail(cmd, kExitUsage, tau.status());
    options.tau_m = *tau;
    tau_source = "given";
  }
  if (Status s = options.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);
  if (Status s = sampling.Check(); !s.ok()) return Fail(cmd, kExitUsage, s);

  auto sequence = LoadSequence(*sequence_dir);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto cloud = ReadPointCloudPly(*cloud_path);
  if (!cloud.ok()) return Fail(cmd, kExitFailure, cloud.status());
  double alignment_scale = 1.0;
  if (flags->Has("align-trajectory")) {
    auto est_path = flags->Required("align-trajectory");
    if (!est_path.ok()) return Fail(cmd, kExitUsage, est_path.status());
    auto est = ReadTrajectoryAutoDetect(*est_path);
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
  if (*threads != 1) pool = std::make_unique<ThreadPool>(*threads);
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

  JsonObject json;
  json.Number("accuracy_m", metrics->accuracy_mean_m);
  json.Number("accuracy_median_m", metrics->accuracy_median_m);
  json.Number("precision", metrics->precision);
  json.Number("completeness", metrics->completeness);
  json.Number("fscore", metrics->fscore);
  json.Integer("points", static_cast<long long>(metrics->points));
  json.Integer("cloud_points", static_cast<long long>(cloud->size()));
  json.Integer("non_finite_points", static_cast<long long>(metrics->non_finite_points));
  json.Number("tau_m", metrics->tau_m);
  json.String("tau_source", tau_source);
  json.Integer("gt_samples", static_cast<long long>(metrics->gt_samples));
  json.Integer("gt_frames", static_cast<long long>(samples->frames_used));
  json.Number("gt_voxel_m", sampling.voxel_size_m);
  json.Integer("frame_step", sampling.frame_step);
  json.Bool("object_only", sampling.object_only);
  if (flags->Has("align-trajectory")) json.Number("aligned_with_scale", alignment_scale);
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

constexpr char kNormalsUsage[] =
    "Usage: prism-eval normals --sequence DIR --normals DIR [--object-only]\n"
    "\n"
    "Angular error of estimated normal maps against the sequence's ground-truth normals. The --normals\n"
    "directory holds 16-bit PNG normal maps in the sequence format (camera frame, (n+1)/2*65535) named\n"
    "like the files in the sequence's normals/ folder; every matching file is evaluated and the\n"
    "statistics are over all pixels of all files (pixels where both normals are valid).\n"
    "\n"
    "Options:\n"
    "  --sequence DIR      sequence with normals.txt and normals/ (required)\n"
    "  --normals DIR       estimated normal maps (required)\n"
    "  --object-only       only object pixels (mask == 255)\n"
    "\n"
    "Prints JSON: mean_deg, median_deg, rmse_deg, pct_under_5, pct_under_10, pct_under_20 (percent),\n"
    "pixels, frames, unmatched_files, object_only.\n";

int RunNormals(const std::vector<std::string>& args) {
  const std::string cmd = "normals";
  if (WantsHelp(args)) {
    std::fputs(kNormalsUsage, stdout);
    return kExitOk;
  }
  auto flags = Flags::Parse(args, {"sequence", "normals"}, {"object-only"});
  if (!flags.ok()) return Fail(cmd, kExitUsage, flags.status());
  auto sequence_dir = flags->Required("sequence");
  if (!sequence_dir.ok()) return Fail(cmd, kExitUsage, sequence_dir.status());
  auto normals_dir = flags->Required("normals");
  if (!normals_dir.ok()) return Fail(cmd, kExitUsage, normals_dir.status());
  const bool object_only = flags->Has("object-only");

  auto sequence = LoadSequence(*sequence_dir);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto matched = MatchFrames(*normals_dir, *sequence, &SequenceFrame::normal_file, "normal maps");
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
  JsonObject json;
  json.Number("mean_deg", stats.count ? stats.mean_deg : NAN);
  json.Number("median_deg", stats.count ? stats.median_deg : NAN);
  json.Number("rmse_deg", stats.count ? stats.rmse_deg : NAN);
  json.Number("pct_under_5", stats.count ? stats.pct_under_5 : NAN);
  json.Number("pct_under_10", stats.count ? stats.pct_under_10 : NAN);
  json.Number("pct_under_20", stats.count ? stats.pct_under_20 : NAN);
  json.Integer("pixels", static_cast<long long>(stats.count));
  json.Integer("frames", static_cast<long long>(matched->matches.size()));
  json.Integer("unmatched_files", static_cast<long long>(matched->unmatched));
  json.Bool("object_only", object_only);
  Print(json);
  return kExitOk;
}

constexpr char kDepthUsage[] =
    "Usage: prism-eval depth --sequence DIR --depth DIR [--object-only] [--scale-align MODE]\n"
    "\n"
    "Error of estimated depth maps against the sequence's ground-truth depth after one scale alignment\n"
    "over all pixels. The --depth directory holds 16-bit PNG depth maps (5000 per metre, 0 = none) named\n"
    "like the files in the sequence's depth/ folder; every matching file is evaluated.\n"
    "\n"
    "Options:\n"
    "  --sequence DIR      sequence with depth.txt and depth/ (required)\n"
    "  --depth DIR         estimated depth maps (required)\n"
    "  --object-only       only object pixels (mask == 255)\n"
    "  --scale-align MODE  median (median of gt/est ratios, default) | least_squares | none\n"
    "\n"
    "Prints JSON: rmse_m, mean_abs_m, median_rel_error, coverage (pixels with both depths / pixels with\n"
    "ground truth), scale, scale_align, pixels, gt_pixels, frames, unmatched_files, object_only.\n";

int RunDepth(const std::vector<std::string>& args) {
  const std::string cmd = "depth";
  if (WantsHelp(args)) {
    std::fputs(kDepthUsage, stdout);
    return kExitOk;
  }
  auto flags = Flags::Parse(args, {"sequence", "depth", "scale-align"}, {"object-only"});
  if (!flags.ok()) return Fail(cmd, kExitUsage, flags.status());
  auto sequence_dir = flags->Required("sequence");
  if (!sequence_dir.ok()) return Fail(cmd, kExitUsage, sequence_dir.status());
  auto depth_dir = flags->Required("depth");
  if (!depth_dir.ok()) return Fail(cmd, kExitUsage, depth_dir.status());
  const bool object_only = flags->Has("object-only");
  DepthEvalOptions options;
  auto align = ParseDepthScaleAlignment(flags->Get("scale-align", "median"));
  if (!align.ok()) return Fail(cmd, kExitUsage, align.status());
  options.scale_alignment = *align;

  auto sequence = LoadSequence(*sequence_dir);
  if (!sequence.ok()) return Fail(cmd, kExitFailure, sequence.status());
  auto matched = MatchFrames(*depth_dir, *sequence, &SequenceFrame::depth_file, "depth images");
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
  JsonObject json;
  json.Number("rmse_m", stats->rmse_m);
  json.Number("mean_abs_m", stats->mean_abs_m);
  json.Number("median_rel_error", stats->median_rel_error);
  json.Number("coverage", stats->coverage);
  json.Number("scale", stats->scale);
  json.String("scale_align", DepthScaleAlignmentName(options.scale_alignment));
  json.Integer("pixels", static_cast<long long>(stats->pixels));
  json.Integer("gt_pixels", static_cast<long long>(stats->gt_pixels));
  json.Integer("frames", static_cast<long long>(matched->matches.size()));
  json.Integer("unmatched_files", static_cast<long long>(matched->unmatched));
  json.Bool("object_only", object_only);
  Print(json);
  return kExitOk;
}

constexpr char kUsage[] =
    "Usage: prism-eval <command> [options]\n"
    "\n"
    "Commands (each prints one JSON object on stdout; 'prism-eval <command> --help' for options):\n"
    "  traj      ATE / RPE of an estimated trajectory (TUM or KITTI files)\n"
    "  cloud     accuracy / completeness / F-score of a reconstructed point cloud\n"
    "  normals   angular error of estimated normal maps\n"
    "  depth     scale-aligned error of estimated depth maps\n";

int Main(int argc, char** argv) {
  if (argc < 2) {
    std::fputs(kUsage, stderr);
    return kExitUsage;
  }
  const std::string command = argv[1];
  const std::vector<std::string> args(argv + 2, argv + argc);
  if (command == "--help" || command == "-h" || command == "help") {
    std::fputs(kUsage, stdout);
    return kExitOk;
  }
  if (command == "traj") return RunTraj(args);
  if (command == "cloud") return RunCloud(args);
  if (command == "normals") return RunNormals(args);
  if (command == "depth") return RunDepth(args);
  std::fprintf(stderr, "prism-eval: error: unknown command '%s'\n\n%s", command.c_str(), kUsage);
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
