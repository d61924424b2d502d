// Frame-to-keyframe tracking at 512x512: build/bin/tracker_benchmark
#include <benchmark/benchmark.h>

#include "core/slam/slam_system.h"
#include "core/slam/tracker.h"
#include "core/slam/undistort.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"

namespace prism {
namespace {

// slam_options: the tracker settings SlamSystem uses (SlamOptions::tracker: darker, weaker pixels)
// instead of the tracker's own defaults.
void BM_Track(benchmark::State& state, const std::string& preset, int gap,
              ShadingModel shading_model = ShadingModel::kLocalMeanNormalisation, bool slam_options = false) {
  synth::PresetOptions o;
  o.frames = 60;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    state.SkipWithError(setup.status().ToString().c_str());
    return;
  }
  const Trajectory t = synth::MakeTrajectory(setup->trajectory);
  const synth::RenderedFrame key =
      synth::RenderFrame(setup->scene, setup->rig, t[0].world_from_camera, setup->render, 1);
  const synth::RenderedFrame frame =
      synth::RenderFrame(setup->scene, setup->rig, t[gap].world_from_camera, setup->render, 2);
  InverseDepthMap depth;
  depth.inverse_depth = cv::Mat::zeros(key.depth.size(), CV_32F);
  for (int y = 0; y < key.depth.rows; ++y)
    for (int x = 0; x < key.depth.cols; ++x)
      if (key.depth.at<float>(y, x) > 0) depth.inverse_depth.at<float>(y, x) = 1.0f / key.depth.at<float>(y, x);
  TrackerOptions options = slam_options ? SlamOptions().tracker : TrackerOptions();
  options.shading_model = shading_model;
  StatusOr<Tracker> tracker = Tracker::Create(setup->rig, options);
  if (!tracker.ok() || !tracker->SetKeyframe(key.rgb, depth).ok()) {
    state.SkipWithError("tracker setup failed");
    return;
  }
  for (auto _ : state) {
    StatusOr<TrackingResult> r = tracker->Track(frame.rgb, Rigid3d());
    if (!r.ok() || !r->ok) state.SkipWithError("tracking failed");
    benchmark::DoNotOptimize(r);
  }
}
BENCHMARK_CAPTURE(BM_Track, multicolor_sphere_gap1, std::string("sphere-multicolor-sideways"), 1)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, multicolor_sphere_gap5, std::string("sphere-multicolor-sideways"), 5)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, bunny_gap1, std::string("bunny-multicolor-forward"), 1)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, bunny_gap1_slam_options, std::string("bunny-multicolor-forward"), 1,
                  ShadingModel::kLocalMeanNormalisation, true)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, multicolor_sphere_gap1_slam_options, std::string("sphere-multicolor-sideways"), 1,
                  ShadingModel::kLocalMeanNormalisation, true)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, multicolor_sphere_gap5_predicted_shading, std::string("sphere-multicolor-sideways"), 5,
                  ShadingModel::kPredictedShading)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_Track, bunny_gap1_predicted_shading, std::string("bunny-multicolor-forward"), 1,
                  ShadingModel::kPredictedShading)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);

// Every standard preset with the SLAM's tracker settings, consecutive frames (the per-preset figures
// of the tracking bar: 10 ms = 100 frames/s on one core).
#define PRISM_TRACK_PRESET_BENCHMARK(NAME, PRESET)                                                                \
  BENCHMARK_CAPTURE(BM_Track, preset_##NAME, std::string(PRESET), 1, ShadingModel::kLocalMeanNormalisation, true) \
      ->Unit(benchmark::kMillisecond)                                                                             \
      ->Repetitions(5)                                                                                            \
      ->ReportAggregatesOnly(true)
PRISM_TRACK_PRESET_BENCHMARK(bunny_multicolor_forward, "bunny-multicolor-forward");
PRISM_TRACK_PRESET_BENCHMARK(sphere_multicolor_sideways, "sphere-multicolor-sideways");
PRISM_TRACK_PRESET_BENCHMARK(dragon_multicolor_sideways, "dragon-multicolor-sideways");
PRISM_TRACK_PRESET_BENCHMARK(sphere_uniform_sideways, "sphere-uniform-sideways");
PRISM_TRACK_PRESET_BENCHMARK(relief_uniform_sideways, "relief-uniform-sideways");
PRISM_TRACK_PRESET_BENCHMARK(boxes_multicolor_forward, "boxes-multicolor-forward");
PRISM_TRACK_PRESET_BENCHMARK(bunny_uniform_sideways, "bunny-uniform-sideways");
PRISM_TRACK_PRESET_BENCHMARK(armadillo_textured_forward, "armadillo-textured-forward");
PRISM_TRACK_PRESET_BENCHMARK(torus_textured_forward, "torus-textured-forward");

// The per-frame cost a lens with distortion adds in front of the tracker (prism-slam and the session
// pipeline remap every frame, core/slam/undistort.h): one 512x512 RGB frame, k1 = -0.25.
void BM_UndistortFrame(benchmark::State& state) {
  PinholeCamera camera = PinholeCamera::FromFov(512, 512, 50.0);
  camera.distortion = {-0.25, 0.08, 0, 0, 0};
  StatusOr<ImageUndistorter> u = ImageUndistorter::Create(camera);
  if (!u.ok()) {
    state.SkipWithError(u.status().ToString().c_str());
    return;
  }
  cv::Mat rgb(512, 512, CV_8UC3);
  cv::randu(rgb, cv::Scalar::all(0), cv::Scalar::all(255));
  for (auto _ : state) {
    StatusOr<cv::Mat> out = u->Undistort(rgb);
    benchmark::DoNotOptimize(out);
  }
}
BENCHMARK(BM_UndistortFrame)->Unit(benchmark::kMillisecond)->Repetitions(5)->ReportAggregatesOnly(true);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
