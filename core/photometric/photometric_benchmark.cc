// Photometric stereo per keyframe at 512x512: build/bin/photometric_benchmark
#include <memory>

#include <benchmark/benchmark.h>

#include "core/photometric/photometric_stereo.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/semidense.h"
#include "core/synth/trajectory.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

struct Keyframe {
  RigCalibration rig;
  cv::Mat rgb;
  InverseDepthMap prior;
};

Keyframe MakeKeyframe(const std::string& preset) {
  synth::PresetOptions o;
  o.frames = 60;
  const synth::SynthSetup setup = synth::MakePreset(preset, o).value();
  const Trajectory t = synth::MakeTrajectory(setup.trajectory);
  const synth::RenderedFrame f = synth::RenderFrame(setup.scene, setup.rig, t[40].world_from_camera, setup.render, 1);
  synth::SemiDenseOptions s;
  s.scale = 0.37;
  return {setup.rig, f.rgb, synth::SimulateSemiDenseDepth(f.depth, f.rgb, s)};
}

// threads = 0: no pool (one thread); else a pool of that many threads (EstimateNormals spreads its
// stages and loops over it).
void BM_EstimateNormals(benchmark::State& state, const std::string& preset, bool estimate_scale, int threads) {
  const Keyframe k = MakeKeyframe(preset);
  PhotometricOptions options;
  options.estimate_depth_scale = estimate_scale;
  options.depth_scale = 0.37;
  std::unique_ptr<ThreadPool> pool = threads > 0 ? std::make_unique<ThreadPool>(threads) : nullptr;
  for (auto _ : state) {
    auto r = EstimateNormals(k.rgb, k.prior, k.rig, options, pool.get());
    if (!r.ok()) state.SkipWithError(r.status().ToString().c_str());
    benchmark::DoNotOptimize(r);
  }
}
// Per keyframe in a session (the session's depth scale known): one thread, and two.
BENCHMARK_CAPTURE(BM_EstimateNormals, multicolor_sphere_session_scale, std::string("sphere-multicolor-sideways"), false,
                  0)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_EstimateNormals, multicolor_sphere_session_scale_2threads,
                  std::string("sphere-multicolor-sideways"), false, 2)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_EstimateNormals, bunny_session_scale_2threads, std::string("bunny-multicolor-forward"), false, 2)
    ->Unit(benchmark::kMillisecond);
// A keyframe that also estimates the depth scale (a session's first keyframes).
BENCHMARK_CAPTURE(BM_EstimateNormals, multicolor_sphere_estimating_scale, std::string("sphere-multicolor-sideways"),
                  true, 2)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
