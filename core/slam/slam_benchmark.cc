// The SLAM at 512x512 on this machine: build/bin/slam_benchmark
//   BM_DepthUpdate: one stereo update of a keyframe's depth filter from a tracked frame (the mapping
//                   work per frame), on 1 thread.
//   BM_SlamSequence: the whole SlamSystem (initialisation, tracking, depth filter, keyframes, keyframe
//                    adjustment) over 150 frames of a preset; the per-frame time is the "ms_per_frame"
//                    counter (with and without the keyframe adjustment on the bunny).
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <benchmark/benchmark.h>

#include "core/slam/depth_filter.h"
#include "core/slam/slam_system.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

struct Frames {
  synth::SynthSetup setup;
  Trajectory trajectory;
  std::vector<synth::RenderedFrame> frames;
};

// Rendered once per preset (the render is not timed).
const Frames* GetFrames(const std::string& preset) {
  static std::map<std::string, std::unique_ptr<Frames>> cache;
  auto it = cache.find(preset);
  if (it != cache.end()) return it->second.get();
  synth::PresetOptions o;
  o.frames = 150;
  StatusOr<synth::SynthSetup> setup = synth::MakePreset(preset, o);
  if (!setup.ok()) return nullptr;
  auto f = std::make_unique<Frames>();
  f->setup = std::move(setup).value();
  f->trajectory = synth::MakeTrajectory(f->setup.trajectory);
  f->frames.resize(o.frames);
  ThreadPool pool;
  pool.ParallelFor(0, o.frames, [&](std::ptrdiff_t i) {
    f->frames[i] = synth::RenderFrame(f->setup.scene, f->setup.rig, f->trajectory[i].world_from_camera,
                                      f->setup.render, 1000003ull + static_cast<uint64_t>(i));
  });
  return (cache[preset] = std::move(f)).get();
}

void BM_DepthUpdate(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  DepthFilterOptions options;
  StatusOr<KeyframeDepth> kd = KeyframeDepth::Create(f->frames[0].rgb, f->setup.rig.camera, options);
  if (!kd.ok()) {
    state.SkipWithError(kd.status().ToString().c_str());
    return;
  }
  cv::Mat seed = cv::Mat::zeros(f->frames[0].depth.size(), CV_32F);
  for (int y = 0; y < seed.rows; ++y)
    for (int x = 0; x < seed.cols; ++x)
      if (f->frames[0].depth.at<float>(y, x) > 0) seed.at<float>(y, x) = 1.0f / f->frames[0].depth.at<float>(y, x);
  kd->Seed(seed, 0.05, 2);
  const Rigid3d frame_from_keyframe = f->trajectory[5].world_from_camera.Inverse() * f->trajectory[0].world_from_camera;
  cv::Mat j, mean;
  for (auto _ : state) {
    KeyframeDepth copy = *kd;
    KeyframeDepth::NormalisedGrey(f->frames[5].rgb, options, &j, &mean);
    const DepthUpdateStats s = copy.Update(j, frame_from_keyframe, nullptr);
    benchmark::DoNotOptimize(s);
  }
}
BENCHMARK_CAPTURE(BM_DepthUpdate, bunny, std::string("bunny-multicolor-forward"))
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);

void BM_SlamSequence(benchmark::State& state, const std::string& preset, bool keyframe_adjustment) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  ThreadPool pool(static_cast<int>(state.range(0)));
  int lost = 0, keyframes = 0;
  for (auto _ : state) {
    SlamOptions options;
    options.keyframe_adjustment = keyframe_adjustment;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(f->setup.rig, options, &pool);
    if (!slam.ok()) {
      state.SkipWithError(slam.status().ToString().c_str());
      return;
    }
    for (size_t i = 0; i < f->frames.size(); ++i) {
      StatusOr<SlamFrameResult> r = (*slam)->ProcessFrame(f->trajectory[i].timestamp_s, f->frames[i].rgb);
      if (!r.ok()) {
        state.SkipWithError(r.status().ToString().c_str());
        return;
      }
      lost += r->state == SlamState::kLost;
      benchmark::DoNotOptimize((*slam)->TakeFinishedKeyframes());
    }
    keyframes = (*slam)->num_keyframes();
  }
  state.counters["ms_per_frame"] = benchmark::Counter(
      static_cast<double>(f->frames.size()) * state.iterations(),
      benchmark::Counter::kIsRate | benchmark::Counter::kInvert, benchmark::Counter::kIs1000);
  state.counters["lost_frames"] = lost;
  state.counters["keyframes"] = keyframes;
}
BENCHMARK_CAPTURE(BM_SlamSequence, bunny, std::string("bunny-multicolor-forward"), true)
    ->Arg(1)
    ->Arg(2)
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1)
    ->UseRealTime()
    ->Repetitions(3)
    ->ReportAggregatesOnly(true);
// Without the keyframe adjustment: the difference is its cost.
BENCHMARK_CAPTURE(BM_SlamSequence, bunny_no_keyframe_adjustment, std::string("bunny-multicolor-forward"), false)
    ->Arg(1)
    ->Arg(2)
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1)
    ->UseRealTime()
    ->Repetitions(3)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_SlamSequence, dragon, std::string("dragon-multicolor-sideways"), true)
    ->Arg(2)
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1)
    ->UseRealTime()
    ->Repetitions(3)
    ->ReportAggregatesOnly(true);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
