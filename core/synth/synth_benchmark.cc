// Render speed of prism-synth at 512x512: one frame on one thread per preset, and whole sequences
// rendered and written with all cores. Run: build/bin/synth_benchmark [--benchmark_format=json]
#include <filesystem>

#include <benchmark/benchmark.h>

#include "core/synth/presets.h"
#include "core/synth/synthesize.h"
#include "core/util/thread_pool.h"

namespace prism::synth {
namespace {

void BM_RenderFrame(benchmark::State& state, const std::string& preset) {
  PresetOptions o;
  o.frames = 30;
  auto setup = MakePreset(preset, o);
  if (!setup.ok()) {
    state.SkipWithError(setup.status().ToString().c_str());
    return;
  }
  const Trajectory t = MakeTrajectory(setup->trajectory);
  size_t i = 0;
  for (auto _ : state) {
    RenderedFrame f = RenderFrame(setup->scene, setup->rig, t[i % t.size()].world_from_camera, setup->render, i);
    ++i;
    benchmark::DoNotOptimize(f.rgb.data);
  }
  state.counters["frames_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}
BENCHMARK_CAPTURE(BM_RenderFrame, sphere, std::string("sphere-uniform-sideways"))->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_RenderFrame, bunny, std::string("bunny-multicolor-forward"))->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_RenderFrame, dragon, std::string("dragon-multicolor-sideways"))->Unit(benchmark::kMillisecond);

// Whole sequence (render + PNG writing of rgb, depth, normals, mask), all cores.
void BM_SynthesizeSequence(benchmark::State& state) {
  PresetOptions o;
  o.frames = static_cast<int>(state.range(0));
  auto setup = MakePreset("bunny-multicolor-forward", o);
  if (!setup.ok()) {
    state.SkipWithError(setup.status().ToString().c_str());
    return;
  }
  ThreadPool pool(0);
  const std::string dir = (std::filesystem::temp_directory_path() / "prism_synth_benchmark").string();
  for (auto _ : state) {
    auto s = SynthesizeSequence(*setup, 1, dir, &pool);
    if (!s.ok()) state.SkipWithError(s.status().ToString().c_str());
  }
  std::filesystem::remove_all(dir);
  state.counters["frames_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations() * state.range(0)), benchmark::Counter::kIsRate);
  state.counters["threads"] = pool.num_threads();
}
BENCHMARK(BM_SynthesizeSequence)->Arg(60)->Unit(benchmark::kSecond)->UseRealTime()->Iterations(1);

}  // namespace
}  // namespace prism::synth

BENCHMARK_MAIN();
