// prism-slam: semi-dense direct monocular SLAM on a sequence folder (core/slam).
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <string>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/eval/depth_metrics.h"
#include "core/eval/trajectory_metrics.h"
#include "core/io/calibration_io.h"
#include "core/io/camera_info_io.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/io/trajectory_io.h"
#include "core/pipeline/dense_stage.h"
#include "core/slam/slam_config.h"
#include "core/slam/slam_system.h"
#include "core/slam/undistort.h"
#include "core/util/log_level.h"
#include "core/util/logging.h"
#include "core/util/thread_pool.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

constexpr char kNotes[] = R"(Writes to DIR:
  trajectory.txt   every frame's world_from_camera (TUM format, SLAM scale; frames before the
                   initialisation and lost frames are left out)
  states.txt       per frame: timestamp, state (initializing|tracking|lost), keyframe id, message
  tracking.txt     per frame aligned against a keyframe: timestamp, keyframe id, residual RMS, visible
                   and inlier fractions, iterations, retried (0/1), and the step from the previous frame,
                   its rotation (degrees) and the result's distance from the constant-velocity guess,
                   distances as fractions of the keyframe's mean depth (core/slam/slam_system.h)
  keyframes/       per keyframe <id>_idepth.tiff and <id>_variance.tiff (32-bit float, 0 = none)
                   and keyframes.txt (id frame_id timestamp scale tx ty tz qx qy qz qw; frame_id is
                   the frame's index in the sequence)
  semidense.ply    the semi-dense points of all keyframes, world frame, with colours
  trajectory_metres.txt  trajectory.txt in metres, when the metric scale is known (from the co-moving
                   lights, see --no-metric-scale; with --dense the lights' when it agrees with the
                   dense stage's within 25%, else the dense stage's: docs/method.md)
  camera.yaml      the calibration the SLAM ran with: the sequence's, or when it has lens distortion
                   the undistorted pinhole camera every frame was remapped into (keyframe depth maps
                   and poses refer to it; see core/slam/undistort.h)
  slam_config.txt  every SLAM option as used (core/slam/slam_config.h; re-readable by --slam-config)
  summary.json     frames, keyframes, states, timing; with ground truth in the sequence also the ATE
                   (Sim(3)-aligned, also as % of the path), the orientation error after that alignment
                   and the net rotation (first to last frame, estimate and truth), and the keyframe
                   depth error (printed too)

--slam-config, --set and the --no-* switches of SLAM options apply in command-line order.)";

// SlamSystem::start_check() as a JSON object (null for a spread that is not a number).
Json StartCheckJson(const StartCheckReport& r) {
  return Json{{"checked", r.checked},
              {"first_spread", r.first_spread},
              {"passed", r.passed},
              {"retried", r.retried},
              {"second_checked", r.second_checked},
              {"second_spread", r.second_spread},
              {"second_kept", r.second_kept},
              {"ms", 1000 * r.seconds},
              {"thread_ms", 1000 * r.thread_seconds}};
}

// SlamSystem::feature_adjustment() as a JSON object.
Json FeatureAdjustmentJson(const FeatureAdjustmentReport& r) {
  const FeatureAdjustmentSummary& s = r.summary;
  return Json{{"ran", r.ran},
              {"applied", r.applied},
              {"error", r.error},
              {"runs", r.runs},
              {"features", s.features},
              {"pairs_tried", r.pairs_tried},
              {"pairs_matched", s.pairs_matched},
              {"tracks", s.tracks},
              {"observations", s.observations},
              {"initial_median_px", s.initial_median_px},
              {"final_median_px", s.final_median_px},
              {"final_rms_px", s.final_rms_px},
              {"keyframes_rescaled", r.keyframes_rescaled},
              {"tracks_ms", 1000 * r.tracks_seconds},
              {"ms", 1000 * r.seconds}};
}

int Fail(const std::string& m) {
  std::cerr << "prism-slam: " << m << "\n";
  return 1;
}

// A KITTI odometry folder as a Sequence (images are read as RGB by Sequence::ReadRgb).
StatusOr<Sequence> LoadKitti(const std::string& dir) {
  Sequence seq;
  seq.root = dir;
  std::ifstream calib(dir + "/calib.txt");
  if (!calib) return NotFoundError("cannot open '" + dir + "/calib.txt'");
  std::string line;
  std::getline(calib, line);
  if (line.rfind("P0:", 0) == 0) line = line.substr(3);
  std::istringstream ls(line);
  double p[12];
  for (double& v : p)
    if (!(ls >> v)) return InvalidArgumentError("'" + dir + "/calib.txt': the first line must hold 12 numbers (P0)");
  std::ifstream times(dir + "/times.txt");
  if (!times) return NotFoundError("cannot open '" + dir + "/times.txt'");
  double t = 0;
  for (int i = 0; times >> t; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "image_0/%06d.png", i);
    SequenceFrame f;
    f.timestamp_s = t;
    f.rgb_file = name;
    seq.frames.push_back(f);
  }
  if (seq.frames.empty()) return InvalidArgumentError("'" + dir + "/times.txt' has no timestamps");
  StatusOr<cv::Mat> first = seq.ReadRgb(0);
  if (!first.ok()) return first.status();
  seq.calibration.camera.width = first->cols;
  seq.calibration.camera.height = first->rows;
  seq.calibration.camera.fx = p[0];
  seq.calibration.camera.cx = p[2];
  seq.calibration.camera.fy = p[5];
  seq.calibration.camera.cy = p[6];
  // No light moves with a KITTI camera (daylight): intensity 0 marks the rig's lights absent, so the
  // start check, the metric scale from the lights and the camera-attached tests stay off.
  for (Light& l : seq.calibration.lights) l.intensity = 0;
  PRISM_RETURN_IF_ERROR(seq.calibration.Check());
  seq.has_calibration = true;
  if (std::filesystem::exists(dir + "/poses.txt")) {
    StatusOr<Trajectory> gt = ReadKittiTrajectory(dir + "/poses.txt", dir + "/times.txt");
    if (!gt.ok()) return gt.status();
    seq.groundtruth = std::move(gt).value();
  }
  return seq;
}

// The run's settings, from the command line.
struct Settings {
  std::string sequence_dir, kitti_dir, out_dir, camera_file, on_bad_frame = "skip", log_level = "info";
  long max_frames = -1;
  int threads = 0;
  bool no_eval = false, dense = false, no_remap = false, no_metric_scale = false, dense_online = false;
  SlamOptions options;
  DenseStageOptions dense_options;
  bool eval = true, remap = true, metric_scale = true, stop_on_bad_frame = false;  // from the above
};

// The input: the sequence, and the undistorted rig the SLAM and the dense stage run on.
struct Input {
  std::optional<Sequence> seq;
  std::optional<ImageUndistorter> undistorter;
  RigCalibration rig;
};

// The dense stage (--dense, --dense-online) and what it reports.
struct DenseRun {
  std::unique_ptr<DenseStage> stage;
  bool eval = false;  // keep each keyframe's fused depth for the evaluation
  double seconds = 0;
  double photometric_ms = 0, fusion_ms = 0, map_ms = 0;  // DenseKeyframeResult's parts, summed
  std::vector<int> keyframes_per_level;                  // DenseKeyframeResult::image_level
  int failed = 0;
  std::map<int, cv::Mat> fused_depth;  // keyframe id -> fused depth (SLAM units), for the evaluation
  std::string first_error;
  double remap_seconds = 0;
  bool remapped = false;

  // Runs the stage on one keyframe (nothing without a stage).
  void Run(const SlamKeyframe& k);
};

void DenseRun::Run(const SlamKeyframe& k) {
  if (!stage) return;
  DenseKeyframe dk;
  dk.id = static_cast<uint64_t>(k.id);
  dk.rgb = k.rgb;
  dk.world_from_keyframe = k.world_from_keyframe;
  dk.depth = k.depth;
  const auto t0 = std::chrono::steady_clock::now();
  StatusOr<DenseKeyframeResult> r = stage->Process(dk);
  seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (r.ok()) {
    photometric_ms += r->photometric_ms;
    fusion_ms += r->fusion_ms;
    map_ms += r->map_ms;
    if (keyframes_per_level.size() <= static_cast<size_t>(r->image_level))
      keyframes_per_level.resize(static_cast<size_t>(r->image_level) + 1);
    ++keyframes_per_level[static_cast<size_t>(r->image_level)];
  }
  if (r.ok() && eval) fused_depth[k.id] = r->depth;
  if (!r.ok()) {
    if (failed++ == 0) first_error = r.status().ToString();
    std::cerr << "prism-slam: dense stage, keyframe " << k.id << ": " << r.status() << "\n";
  }
}

// What the SLAM run produced.
struct SlamRun {
  size_t n = 0;  // frames to process
  std::vector<SlamKeyframe> keyframes;
  std::vector<size_t> seq_index;     // the SLAM's frame id -> the frame's index in the sequence
  std::vector<std::string> skipped;  // "frame i (t = ...): error"
  std::string stop_error;
  double slam_seconds = 0, finish_seconds = 0, refine_seconds = 0;
  std::optional<MetricScaleEstimate> shading_scale;
  std::string shading_scale_error;
  double shading_scale_seconds = 0;
  // Metres per world unit of the outputs (0 = unknown), and the dense stage's own.
  double metres_per_unit = 0, dense_metres_per_unit = 0;
  bool metres_per_unit_from_shading = false;  // ChooseMetresPerUnit took the SLAM's
};

// What the outputs hold that the summary and the evaluation read.
struct Outputs {
  std::vector<SlamFrameResult> results;
  Trajectory estimate;
  int counts[3] = {0, 0, 0};
  std::vector<Sim3d> keyframe_poses;
  size_t semidense_points = 0;
};

// Parses the command line into `settings`: cli::kContinue, or the exit status (after --help, a usage
// error or --print-config).
int ParseCommandLine(int argc, char** argv, Settings* settings) {
  Settings& s = *settings;
  CLI::App app{"", "prism-slam"};
  cli::Setup(&app, "semi-dense direct monocular SLAM on a sequence folder or a KITTI odometry folder",
             {"prism-slam --sequence DIR --out DIR [options]", "prism-slam --kitti DIR --out DIR [options]"}, kNotes);
  app.add_option("--sequence", s.sequence_dir, "sequence folder: rgb.txt, rgb/, camera.yaml (see README)")
      ->type_name("DIR");
  app.add_option("--kitti", s.kitti_dir,
                 "a KITTI odometry folder instead: image_0/*.png (grey), calib.txt (P0,\n"
                 "with or without 'P0:'), times.txt and, when present, poses.txt (truth)")
      ->type_name("DIR");
  app.add_option("--out", s.out_dir, "output folder (created)")->type_name("DIR");
  app.add_option("--camera", s.camera_file,
                 "intrinsics and lens distortion from FILE instead of camera.yaml's: OpenCV\n"
                 "or ROS camera_info YAML, DSO / LSD-SLAM camera.txt, Prism camera.yaml")
      ->type_name("FILE");
  app.add_flag("--dense", s.dense,
               "also run the dense stage (photometric stereo, fusion, ICP map) on every\n"
               "keyframe at the end, at its final pose, and write map.ply (metres)");
  app.add_flag("--dense-online", s.dense_online,
               "run it instead on each keyframe as it is finished (as prism-server\n"
               "does), then rebuild map.ply at the final keyframe poses");
  // SLAM options: --slam-config, --set and the switches apply in command-line order (below).
  CLI::Option* slam_config =
      app.add_option("--slam-config", "SLAM options, 'key = value' lines (core/slam/slam_config.h)")->type_name("FILE");
  CLI::Option* set =
      app.add_option("--set", "one SLAM option, e.g. --set tracker.min_gradient=5")->type_name("KEY=VALUE");
  const struct {
    const char* flag;
    const char* key;
    const char* help;
  } kSlamSwitches[] = {
      {"--no-loop-closure", "loop_closure", "no loop-closure edges (= --set loop_closure=false)"},
      {"--no-keyframe-adjustment", "keyframe_adjustment",
       "no windowed direct adjustment of the keyframes\n(= --set keyframe_adjustment=false)"},
      {"--no-repropagation", "repropagate_after_adjustment",
       "a new keyframe keeps the depth propagated along the tracked pose\n"
       "(= --set repropagate_after_adjustment=false)"},
      {"--no-final-adjustment", "final_adjustment",
       "no adjustment of all keyframes at the end (= --set final_adjustment=false)"},
  };
  std::map<const CLI::Option*, const char*> slam_switch;
  for (const auto& sw : kSlamSwitches) slam_switch[app.add_flag(sw.flag, sw.help)] = sw.key;
  app.add_flag("--no-metric-scale", s.no_metric_scale,
               "skip the metres per world unit from the co-moving lights (2-7 s at the\n"
               "end; trajectory_metres.txt and map.ply use it, else the dense stage's)");
  app.add_flag("--no-remap", s.no_remap,
               "with --dense-online: write map.ply as the keyframe clouds were merged,\n"
               "not rebuilt at the final keyframe poses");
  app.add_flag("--remap-icp", s.dense_options.remap_icp,
               "with --dense-online: register each keyframe cloud again with ICP as\nmap.ply is rebuilt");
  app.add_option("--position-weight", s.dense_options.fusion.position_weight,
                 "the dense stage's fusion position weight, >= 0")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--min-brightness", s.dense_options.min_brightness,
                 "the dense stage leaves pixels darker than this (0-255) out of the map")
      ->check(CLI::Range(0.0, 255.0));
  app.add_option("--max-frames", s.max_frames, "process at most N frames (default: all)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::PositiveNumber);
  app.add_option("--on-bad-frame", s.on_bad_frame,
                 "skip|stop: a frame that cannot be read or decoded, or has the wrong\n"
                 "size, is skipped with a warning (listed in summary.json) or ends the\n"
                 "run (exit 1 after writing the outputs of the frames before it)")
      ->check(CLI::IsMember({"skip", "stop"}));
  app.add_option("--threads", s.threads, "threads for the depth filter and the adjustments, 1-256 (default: all)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::Range(1, 256));
  app.add_option("--log-level", s.log_level,
                 "debug|info|warning|error; debug prints each keyframe adjustment's\npoints, residuals and RMS")
      ->check(CLI::IsMember({"debug", "info", "warning", "error"}));
  app.add_flag("--no-eval", s.no_eval, "skip the evaluation against ground truth");
  bool print_config = false;
  app.add_flag("--print-config", print_config,
               "print every SLAM option (after --slam-config, --set and the switches) as\n"
               "'key = value' lines and exit");
  if (const int exit = cli::Parse(&app, argc, argv, /*usage_exit=*/1); exit != cli::kContinue) return exit;
  for (const auto& [option, value] : cli::InCommandLineOrder(app)) {
    Status st;
    if (option == slam_config) {
      st = ApplySlamConfigFile(value, &s.options);
    } else if (option == set) {
      const size_t eq = value.find('=');
      if (eq == std::string::npos) return Fail("--set expects KEY=VALUE, got '" + value + "'");
      st = SetSlamOption(value.substr(0, eq), value.substr(eq + 1), &s.options);
    } else if (const auto sw = slam_switch.find(option); sw != slam_switch.end()) {
      st = SetSlamOption(sw->second, "false", &s.options);
    }
    if (!st.ok()) return Fail(st.ToString());
  }
  if (print_config) {
    std::cout << FormatSlamConfig(s.options);
    return 0;
  }
  s.eval = !s.no_eval;
  s.remap = !s.no_remap;
  s.metric_scale = !s.no_metric_scale;
  s.stop_on_bad_frame = s.on_bad_frame == "stop";
  return cli::kContinue;
}

// Checks the settings, reads the sequence, creates the output folder with slam_config.txt and
// camera.yaml, and sets up the undistortion: cli::kContinue or the exit status.
int ReadInput(const Settings& s, Input* input) {
  if (s.sequence_dir.empty() == s.kitti_dir.empty() || s.out_dir.empty())
    return Fail("--out and one of --sequence or --kitti are required (see --help)");
  if (Status st = s.options.Check(); !st.ok()) return Fail("SLAM options: " + st.ToString());
  StatusOr<Sequence> loaded = s.kitti_dir.empty() ? LoadSequence(s.sequence_dir) : LoadKitti(s.kitti_dir);
  if (!loaded.ok()) return Fail(loaded.status().ToString());
  std::optional<Sequence>& seq = input->seq;
  seq = std::move(loaded).value();
  if (!s.camera_file.empty()) {
    // The intrinsics from the user's own calibration file; the lights and crosstalk stay the
    // sequence's (the SLAM does not use them; the dense stage does).
    if (s.dense && !seq->has_calibration)
      return Fail("--camera gives the intrinsics only; --dense also needs the rig's lights (camera.yaml)");
    StatusOr<PinholeCamera> camera = ReadCameraIntrinsics(s.camera_file);
    if (!camera.ok()) return Fail(camera.status().ToString());
    seq->calibration.camera = *camera;
    seq->has_calibration = true;
  }
  if (!seq->has_calibration)
    return Fail("sequence has no camera.yaml (the camera calibration is needed; or give --camera FILE)");
  std::error_code ec;
  std::filesystem::create_directories(s.out_dir + "/keyframes", ec);
  if (ec) return Fail("cannot create '" + s.out_dir + "/keyframes': " + ec.message());

  {
    std::ofstream config(s.out_dir + "/slam_config.txt");
    config << FormatSlamConfig(s.options);
    if (!config) return Fail("cannot write '" + s.out_dir + "/slam_config.txt'");
  }

  // Lens distortion: every frame (and, for the evaluation, the true depth) is remapped into an
  // undistorted pinhole camera of the same size, which the SLAM and the dense stage run on.
  StatusOr<ImageUndistorter> undistorter = ImageUndistorter::Create(seq->calibration.camera);
  if (!undistorter.ok()) return Fail(undistorter.status().ToString());
  RigCalibration& rig = input->rig;
  rig = seq->calibration;
  rig.camera = undistorter->camera();
  if (Status st = WriteCalibrationYaml(s.out_dir + "/camera.yaml", rig); !st.ok()) return Fail(st.ToString());
  input->undistorter = std::move(undistorter).value();
  return cli::kContinue;
}

// Runs the SLAM over the frames (with --dense-online the dense stage on each finished keyframe) and
// finishes it: cli::kContinue or the exit status.
int RunSlam(const Settings& s, const Input& input, SlamSystem* slam, DenseRun* dense, SlamRun* run) {
  const std::optional<Sequence>& seq = input.seq;
  const bool stop_on_bad_frame = s.stop_on_bad_frame;
  // A frame that cannot be read, decoded or undistorted, or that has the wrong size, is skipped
  // (--on-bad-frame skip) or ends the frame loop (stop); either way every output of the frames before
  // it is written. The SLAM numbers the frames it was given; seq_index maps its frame ids back.
  for (size_t i = 0; i < run->n; ++i) {
    const auto bad_frame = [&](const Status& st) {
      std::ostringstream m;
      m << "frame " << i << " (t = " << std::fixed << std::setprecision(6) << seq->frames[i].timestamp_s
        << "): " << st.ToString();
      std::cerr << "prism-slam: " << m.str() << (stop_on_bad_frame ? "; stopping (--on-bad-frame stop)" : "; skipped")
                << "\n";
      if (stop_on_bad_frame) run->stop_error = m.str();
      else run->skipped.push_back(m.str());
    };
    // ReadRgb gives 8-bit RGB or an error; Undistort refuses an image whose size is not the camera's.
    StatusOr<cv::Mat> rgb = seq->ReadRgb(i);
    const auto t0 = std::chrono::steady_clock::now();
    if (rgb.ok()) rgb = input.undistorter->Undistort(*rgb);
    if (!rgb.ok()) {
      bad_frame(rgb.status());
      if (stop_on_bad_frame) break;
      continue;
    }
    StatusOr<SlamFrameResult> r = slam->ProcessFrame(seq->frames[i].timestamp_s, *rgb);
    run->slam_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!r.ok()) return Fail("frame " + std::to_string(i) + ": " + r.status().ToString());
    run->seq_index.push_back(i);
    if (r->state == SlamState::kLost) std::cerr << "prism-slam: frame " << i << ": " << r->message << "\n";
    for (SlamKeyframe& k : slam->TakeFinishedKeyframes()) {
      if (s.dense_online) dense->Run(k);
      run->keyframes.push_back(std::move(k));
    }
  }
  const auto finish_start = std::chrono::steady_clock::now();
  std::vector<SlamKeyframe> last_keyframes = slam->FinishTracking();  // the rest: RefineAndScale
  run->finish_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - finish_start).count();
  for (SlamKeyframe& k : last_keyframes) {
    if (s.dense_online) dense->Run(k);
    run->keyframes.push_back(std::move(k));
  }
  if (dense->stage && s.dense_online) {
    StatusOr<MapChunk> rest = dense->stage->Flush();
    if (!rest.ok()) return Fail("dense stage: " + rest.status().ToString());
  }
  return cli::kContinue;
}

// After the frames: the SLAM's end of the stream (SlamSystem::FinishStream, as the server runs it, with
// the keyframes' depth refinement on the keyframes kept here): the final adjustment, the refinement and
// the metric scale.
void RefineAndScale(const Settings& s, SlamSystem* slam, SlamRun* run) {
  const SlamStreamEnd end = slam->FinishStream(s.metric_scale, &run->keyframes);
  run->finish_seconds += end.adjustment_seconds;
  run->refine_seconds = end.refinement_seconds;
  if (!s.metric_scale) return;
  run->shading_scale = end.metric;
  run->shading_scale_error = end.metric_error;
  run->shading_scale_seconds = end.metric_seconds;
  const std::optional<MetricScaleEstimate>& shading_scale = run->shading_scale;
  if (shading_scale && !shading_scale->consistent)
    std::cerr << "prism-slam: warning: the reconstruction disagrees with the co-moving lights' shading (keyframe "
                 "pairs' shading scales spread by "
              << shading_scale->pair_spread << " of their median, limit " << s.options.metric_scale_max_pair_spread
              << "): the trajectory and depth are probably distorted\n";
}

// The dense stage's end (--dense: every final keyframe through it; --dense-online: the map rebuilt at
// the final poses), the output scale, and map.ply: cli::kContinue or the exit status.
int FinishDense(const Settings& s, SlamSystem* slam, DenseRun* dense, SlamRun* run) {
  const std::unique_ptr<DenseStage>& dense_stage = dense->stage;
  // The dense stage on the final keyframes: their refined depth at their final poses.
  if (dense_stage && !s.dense_online) {
    const std::vector<Sim3d> final_poses = slam->KeyframePoses();
    for (const SlamKeyframe& k : run->keyframes) {
      SlamKeyframe placed = k;
      placed.world_from_keyframe = final_poses[static_cast<size_t>(k.id)];
      dense->Run(placed);
    }
    StatusOr<MapChunk> rest = dense_stage->Flush();
    if (!rest.ok()) return Fail("dense stage: " + rest.status().ToString());
  }
  // Metres per world unit of the outputs (ChooseMetresPerUnit).
  const double dense_metres_per_unit = dense_stage ? dense_stage->session_metres_per_unit() : 0.0;
  const MetresPerUnit chosen =
      ChooseMetresPerUnit(dense_metres_per_unit, run->shading_scale ? run->shading_scale->metres_per_world_unit : 0.0,
                          run->shading_scale && run->shading_scale->consistent);
  run->dense_metres_per_unit = dense_metres_per_unit;
  run->metres_per_unit = chosen.value;
  run->metres_per_unit_from_shading = chosen.from_shading;
  if (!dense_stage) return cli::kContinue;
  // The map rebuilt at that scale, so that its voxels are MapOptions::voxel_m in metres, and with
  // --dense-online each keyframe cloud placed again at its final pose (--no-remap: the map as merged,
  // its points scaled).
  const bool rebuild = dense_stage->map_metres_per_unit() > 0 && chosen.value > 0 && (!s.dense_online || s.remap);
  if (rebuild) {
    const auto remap_start = std::chrono::steady_clock::now();
    StatusOr<MapChunk> changed = dense_stage->Remap(slam->KeyframePoses(), 1e-6, chosen.value);
    dense->remap_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - remap_start).count();
    if (!changed.ok())
      return Fail("dense stage: the map not rebuilt at the final poses: " + changed.status().ToString());
    dense->remapped = changed->replaces_map;
  }
  PointCloud map = dense_stage->map().ToPointCloud();
  if (!rebuild && dense_stage->map_metres_per_unit() > 0 && chosen.value > 0) {
    const float f = static_cast<float>(chosen.value / dense_stage->map_metres_per_unit());
    for (Eigen::Vector3f& p : map.positions) p *= f;
  }
  if (Status st = WritePointCloudPly(s.out_dir + "/map.ply", map); !st.ok()) return Fail(st.ToString());
  return cli::kContinue;
}

// Writes states.txt, tracking.txt, the trajectories, the keyframes and semidense.ply: cli::kContinue or
// the exit status.
int WriteOutputs(const Settings& s, SlamSystem* slam, const SlamRun& run, Outputs* outputs) {
  const std::string& out_dir = s.out_dir;
  const double metres_per_unit = run.metres_per_unit;
  outputs->results = slam->Trajectory();
  const std::vector<SlamFrameResult>& results = outputs->results;
  Trajectory& estimate = outputs->estimate;
  int* counts = outputs->counts;
  std::ofstream states(out_dir + "/states.txt");
  states << "# timestamp state keyframe_id message\n" << std::setprecision(17);
  std::ofstream tracking(out_dir + "/tracking.txt");
  tracking << "# timestamp keyframe_id residual_rms visible_fraction inlier_fraction iterations retried step "
              "rotation_deg guess_correction\n";
  for (const SlamFrameResult& r : results) {
    ++counts[static_cast<int>(r.state)];
    states << r.timestamp << " " << SlamStateName(r.state) << " " << r.keyframe_id << " " << r.message << "\n";
    const SlamTrackingQuality& q = r.tracking;
    if (q.tracked)
      tracking << std::fixed << std::setprecision(6) << r.timestamp << std::defaultfloat << " " << r.keyframe_id << " "
               << q.residual_rms << " " << q.visible_fraction << " " << q.inlier_fraction << " " << q.iterations << " "
               << (q.retried ? 1 : 0) << " " << q.step << " " << q.rotation_deg << " " << q.guess_correction << "\n";
    if (r.state == SlamState::kTracking) estimate.push_back({r.timestamp, r.world_from_camera});
  }
  if (Status st = WriteTumTrajectory(out_dir + "/trajectory.txt", estimate); !st.ok()) return Fail(st.ToString());
  if (metres_per_unit > 0) {
    Trajectory metric = estimate;
    for (TimedPose& p : metric) p.world_from_camera.translation *= metres_per_unit;
    if (Status st = WriteTumTrajectory(out_dir + "/trajectory_metres.txt", metric); !st.ok())
      return Fail(st.ToString());
  }
  std::ofstream kf_index(out_dir + "/keyframes/keyframes.txt");
  kf_index << "# id frame_id timestamp scale tx ty tz qx qy qz qw (world_from_keyframe, Sim(3))\n"
           << std::setprecision(17);
  outputs->keyframe_poses = slam->KeyframePoses();  // after the last loop closure
  const std::vector<Sim3d>& keyframe_poses = outputs->keyframe_poses;
  for (const SlamKeyframe& k : run.keyframes) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06d", k.id);
    const std::string base = out_dir + "/keyframes/" + name;
    if (!cv::imwrite(base + "_idepth.tiff", k.depth.inverse_depth) ||
        !cv::imwrite(base + "_variance.tiff", k.depth.variance))
      return Fail("cannot write '" + base + "_*.tiff'");
    const Sim3d& p = keyframe_poses[static_cast<size_t>(k.id)];
    // frame_id: the frame's index in the sequence (the SLAM's own count leaves out skipped frames).
    const long frame = k.frame_id >= 0 && static_cast<size_t>(k.frame_id) < run.seq_index.size()
                           ? static_cast<long>(run.seq_index[k.frame_id])
                           : -1;
    kf_index << k.id << " " << frame << " " << k.timestamp << " " << p.scale << " " << p.translation.x() << " "
             << p.translation.y() << " " << p.translation.z() << " " << p.rotation.x() << " " << p.rotation.y() << " "
             << p.rotation.z() << " " << p.rotation.w() << "\n";
  }
  const PointCloud cloud = slam->SemiDenseCloud();
  if (Status st = WritePointCloudPly(out_dir + "/semidense.ply", cloud); !st.ok()) return Fail(st.ToString());
  outputs->semidense_points = cloud.size();
  return cli::kContinue;
}

// summary.json's fields before the evaluation: frames, keyframes, states, timing, scale and dense stage.
Json Summary(const Settings& s, const Input& input, SlamSystem* slam, const SlamRun& run, const DenseRun& dense,
             const Outputs& outputs) {
  const std::optional<MetricScaleEstimate>& shading_scale = run.shading_scale;
  const std::vector<SlamKeyframe>& keyframes = run.keyframes;
  const std::unique_ptr<DenseStage>& dense_stage = dense.stage;
  const double metres_per_unit = run.metres_per_unit;
  const SlamTimings timings = slam->timings();
  const double nf = static_cast<double>(std::max<size_t>(1, run.n));
  Json json;
  json["frames"] = outputs.results.size();
  json["keyframes"] = keyframes.size();
  json["initializing_frames"] = outputs.counts[0];
  json["tracking_frames"] = outputs.counts[1];
  json["lost_frames"] = outputs.counts[2];
  json["skipped_frames"] = run.skipped.size();
  json["loop_closures"] = slam->num_loop_closures();
  json["keyframe_adjustments"] = slam->num_keyframe_adjustments();
  json["start_check"] = StartCheckJson(slam->start_check());
  json["feature_adjustment"] = FeatureAdjustmentJson(slam->feature_adjustment());
  json["semidense_points"] = outputs.semidense_points;
  json["undistorted"] = !input.undistorter->identity();
  json["slam_ms_per_frame"] = 1000.0 * run.slam_seconds / nf;
  json["slam_ms_per_frame_parts"] =
      Json{{"initialisation", 1000.0 * timings.initialisation / nf},
           {"tracking", 1000.0 * timings.tracking / nf},
           {"depth_update", 1000.0 * timings.depth_update / nf},
           {"keyframes", 1000.0 * timings.keyframes / nf},
           {"keyframe_adjustment", 1000.0 * timings.keyframe_adjustment / nf},
           {"keyframe_adjustment_thread", 1000.0 * timings.keyframe_adjustment_thread / nf},
           {"keyframe_adjustment_wait", 1000.0 * timings.keyframe_adjustment_wait / nf},
           {"loop_search", 1000.0 * timings.loop_search / nf},
           {"relocalisation", 1000.0 * timings.relocalisation / nf}};
  const double tracked = std::max(1, timings.tracked_frames);
  json["mapping_ms_per_tracked_frame"] = 1000.0 * (timings.depth_update + timings.keyframes) / tracked;
  json["tracking_ms_per_tracked_frame"] = 1000.0 * timings.tracking / tracked;
  json["depth_updates"] = timings.depth_updates;
  json["depth_updates_over_budget"] = timings.depth_updates_over_budget;
  json["keyframes_made_before_adjustment"] = timings.keyframes_made_before_adjustment;
  json["adjustments_started_late"] = timings.adjustments_started_late;
  json["depth_pixels_searched"] = timings.depth_pixels_searched;
  json["depth_pixels_skipped"] = timings.depth_pixels_skipped;
  json["slam_finish_ms"] = 1000.0 * run.finish_seconds;
  json["depth_refinement_ms"] = 1000.0 * run.refine_seconds;
  if (metres_per_unit > 0) {
    json["metres_per_unit"] = metres_per_unit;
    json["metres_per_unit_source"] = run.metres_per_unit_from_shading ? "shading" : "dense_stage";
  }
  if (shading_scale) {
    json["shading_metres_per_unit"] = shading_scale->metres_per_world_unit;
    json["shading_metres_per_unit_start"] = shading_scale->start_metres_per_world_unit;
    json["shading_scale_passes"] = shading_scale->passes;
    json["shading_scale_ms"] = 1000.0 * run.shading_scale_seconds;
    json["shading_scale_pairs"] = shading_scale->pairs;
    json["shading_scale_pair_spread"] = shading_scale->pair_spread;
    json["shading_scale_consistent"] = shading_scale->consistent;
  } else if (s.metric_scale) {
    json["shading_scale_error"] = run.shading_scale_error;
  }
  if (dense_stage) {
    const double n = static_cast<double>(std::max<size_t>(1, keyframes.size()));
    json["dense_ms_per_keyframe"] = 1000.0 * dense.seconds / n;
    json["dense_photometric_ms_per_keyframe"] = dense.photometric_ms / n;
    json["dense_fusion_ms_per_keyframe"] = dense.fusion_ms / n;
    json["dense_keyframes_per_image_level"] = dense.keyframes_per_level;
    json["dense_map_ms_per_keyframe"] = dense.map_ms / n;
    json["dense_failed_keyframes"] = dense.failed;
    json["dense_metres_per_unit"] = run.dense_metres_per_unit;
    json["map_points"] = dense_stage->map().output_size();
    json["map_remapped"] = dense.remapped;
    json["remap_ms"] = 1000.0 * dense.remap_seconds;
    if (dense.failed) json["dense_first_error"] = dense.first_error;
  }
  return json;
}

// The evaluation against the sequence's ground truth, into `json`: the ATE (Sim(3)-aligned), the
// orientation error and the keyframe depth error.
void EvaluateAgainstGroundTruth(const Input& input, const SlamRun& run, const DenseRun& dense, const Outputs& outputs,
                                Json* out) {
  Json& json = *out;
  const std::optional<Sequence>& seq = input.seq;
  const std::optional<ImageUndistorter>& undistorter = input.undistorter;
  const std::optional<MetricScaleEstimate>& shading_scale = run.shading_scale;
  const std::vector<size_t>& seq_index = run.seq_index;
  const std::vector<Sim3d>& keyframe_poses = outputs.keyframe_poses;
  const std::map<int, cv::Mat>& fused_depth = dense.fused_depth;
  TrajectoryEvalOptions eo;
  eo.alignment = AlignmentModel::kSim3;
  StatusOr<AteResult> ate = ComputeAte(seq->groundtruth, outputs.estimate, eo);
  if (ate.ok()) {
    json["ate_rmse_m"] = ate->error_m.rmse;
    json["path_length_m"] = ate->trajectory_length_m;
    json["ate_percent_of_path"] = 100.0 * ate->error_m.rmse / std::max(1e-12, ate->trajectory_length_m);
    json["sim3_scale"] = ate->gt_from_est.scale;
    json["orientation_rmse_deg"] = ate->orientation_error_deg.rmse;
    json["orientation_max_deg"] = ate->orientation_error_deg.max;
    json["net_rotation_gt_deg"] = ate->net_rotation_deg_gt;
    json["net_rotation_est_deg"] = ate->net_rotation_deg_est;
    if (shading_scale)
      json["shading_metres_per_unit_rel_error"] = shading_scale->metres_per_world_unit / ate->gt_from_est.scale - 1.0;
    if (run.dense_metres_per_unit > 0)
      json["dense_metres_per_unit_rel_error"] = run.dense_metres_per_unit / ate->gt_from_est.scale - 1.0;
    if (run.metres_per_unit > 0) json["metres_per_unit_rel_error"] = run.metres_per_unit / ate->gt_from_est.scale - 1.0;
    // Keyframe depth against ground truth, in metres through the trajectory's Sim(3) scale.
    DepthErrorAccumulator acc;
    long claimed = 0;
    Json per_keyframe = Json::array(), per_keyframe_fused = Json::array();
    for (const SlamKeyframe& k : run.keyframes) {
      if (k.frame_id < 0 || static_cast<size_t>(k.frame_id) >= seq_index.size()) continue;
      const size_t frame = seq_index[static_cast<size_t>(k.frame_id)];  // in the sequence
      if (seq->frames[frame].depth_file.empty()) continue;
      StatusOr<cv::Mat> gt = seq->ReadDepth(frame);
      if (gt.ok()) gt = undistorter->UndistortNearest(*gt);
      if (!gt.ok()) continue;
      cv::Mat est = cv::Mat::zeros(k.depth.inverse_depth.size(), CV_32F);
      for (int y = 0; y < est.rows; ++y)
        for (int x = 0; x < est.cols; ++x) {
          const float d = k.depth.inverse_depth.at<float>(y, x);
          if (d > 0)
            est.at<float>(y, x) =
                static_cast<float>(ate->gt_from_est.scale * keyframe_poses[static_cast<size_t>(k.id)].scale / d),
                             ++claimed;
        }
      (void)acc.Add(est, *gt);
      DepthEvalOptions per;
      StatusOr<DepthErrorStats> one = ComputeDepthError(est, *gt, cv::Mat(), per);
      auto fused = fused_depth.find(k.id);
      if (fused != fused_depth.end() && !fused->second.empty()) {
        cv::Mat gt_at_level = *gt;  // the fused depth is at its keyframe's image level
        if (gt_at_level.size() != fused->second.size())
          cv::resize(*gt, gt_at_level, fused->second.size(), 0, 0, cv::INTER_NEAREST);
        StatusOr<DepthErrorStats> f = ComputeDepthError(fused->second, gt_at_level, cv::Mat(), per);
        if (f.ok())
          per_keyframe_fused.push_back(
              Json{{"id", k.id}, {"coverage", f->coverage}, {"median_rel_error_own_scale", f->median_rel_error}});
      }
      if (one.ok())
        per_keyframe.push_back(Json{{"id", k.id},
                                    {"points", one->pixels},
                                    {"scale", one->scale},
                                    {"median_rel_error_own_scale", one->median_rel_error}});
    }
    DepthEvalOptions de;
    de.scale_alignment = DepthScaleAlignment::kNone;
    StatusOr<DepthErrorStats> ds = acc.Summarize(de);
    if (ds.ok()) {
      json["depth_pixels"] = ds->pixels;
      json["depth_median_rel_error"] = ds->median_rel_error;
      json["depth_coverage_of_image"] = ds->coverage;
      DepthEvalOptions dm;
      StatusOr<DepthErrorStats> dsm = acc.Summarize(dm);
      if (dsm.ok()) json["depth_median_rel_error_median_scaled"] = dsm->median_rel_error;
      json["keyframe_depth"] = per_keyframe;
      if (!fused_depth.empty()) json["keyframe_fused_depth"] = per_keyframe_fused;
    }
  } else {
    json["ate_error"] = std::string(ate.status().message());
  }
}

}  // namespace

int main(int argc, char** argv) {
  Settings settings;
  if (const int exit = ParseCommandLine(argc, argv, &settings); exit != cli::kContinue) return exit;
  SetMinLogLevel(settings.log_level);
  Input input;
  if (const int exit = ReadInput(settings, &input); exit != cli::kContinue) return exit;
  const std::optional<Sequence>& seq = input.seq;

  ThreadPool pool(settings.threads);
  StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(input.rig, settings.options, &pool);
  if (!slam.ok()) return Fail(slam.status().ToString());

  SlamRun run;
  run.n = settings.max_frames > 0 ? std::min<size_t>(seq->frames.size(), static_cast<size_t>(settings.max_frames))
                                  : seq->frames.size();
  DenseRun dense;
  dense.eval = settings.eval;
  if (settings.dense) {
    StatusOr<std::unique_ptr<DenseStage>> d = DenseStage::Create(input.rig, settings.dense_options, &pool);
    if (!d.ok()) return Fail(d.status().ToString());
    dense.stage = std::move(d).value();
  }
  if (const int exit = RunSlam(settings, input, slam->get(), &dense, &run); exit != cli::kContinue) return exit;
  RefineAndScale(settings, slam->get(), &run);
  if (const int exit = FinishDense(settings, slam->get(), &dense, &run); exit != cli::kContinue) return exit;
  Outputs outputs;
  if (const int exit = WriteOutputs(settings, slam->get(), run, &outputs); exit != cli::kContinue) return exit;

  Json json = Summary(settings, input, slam->get(), run, dense, outputs);
  if (settings.eval && !seq->groundtruth.empty() && outputs.estimate.size() >= 3)
    EvaluateAgainstGroundTruth(input, run, dense, outputs, &json);
  if (!run.skipped.empty()) json["skipped"] = run.skipped;
  if (!run.stop_error.empty()) json["stopped_at_bad_frame"] = run.stop_error;
  const std::string text = JsonText(json, 2);
  std::ofstream(settings.out_dir + "/summary.json") << text;
  std::cout << text;
  // --on-bad-frame stop: everything up to the bad frame is written; the exit status says the run ended there.
  if (!run.stop_error.empty()) return Fail("stopped at " + run.stop_error + " (outputs cover the frames before it)");
  if (run.seq_index.empty()) return Fail("none of the sequence's " + std::to_string(run.n) + " frames could be used");
  return 0;
}
