// Photometric stereo per keyframe at 512x512: build/bin/photometric_benchmark
#include <benchmark/benchmark.h>

#include "core/photometric/photometric_stereo.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"
#include "core/synth/semidense.h"
#include "core/synth/trajectory.h"

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

void BM_EstimateNormals(benchmark::State& state, const std::string& preset, bool estimate_scale) {
  const Keyframe k = MakeKeyframe(preset);
  PhotometricOptions options;
  options.estimate_depth_scale = estimate_scale;
  options.depth_scale = 0.37;
  for (auto _ : state) {
    auto r = EstimateNormals(k.rgb, k.prior, k.rig, options);
    if (!r.ok()) state.SkipWithError(r.status().ToString().c_str());
    benchmark::DoNotOptimize(r);
  }
}
BENCHMARK_CAPTURE(BM_EstimateNormals, multicolor_sphere, std::string("sphere-multicolor-sideways"), true)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_EstimateNormals, multicolor_sphere_known_scale, std::string("sphere-multicolor-sideways"), false)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_EstimateNormals, bunny, std::string("bunny-multicolor-forward"), true)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
