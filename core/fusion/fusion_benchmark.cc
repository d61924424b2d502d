// Fusion of one 512x512 keyframe (bunny-multicolor-forward, frame 40 of 60: SLAM depth simulated at
// scale 0.37, ground-truth normals with 4 deg noise + 4 deg smooth bias), default options, with 1 and
// 2 threads. Run:
//   build/bin/fusion_benchmark --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
// BM_Fuse reuses one DepthNormalFusion (the per-keyframe cost in a running session); BM_FuseOneShot
// calls FuseDepthAndNormals (allocates its buffers every call); BM_Fuse*Jacobi uses the diagonal
// preconditioner for comparison.
#include <cstdlib>
#include <memory>

#include <benchmark/benchmark.h>

#include "core/fusion/fusion.h"
#include "core/fusion/fusion_testing.h"
#include "core/util/thread_pool.h"

namespace {

struct Keyframe {
  prism::FusionTestFrame frame;
  cv::Mat normals;
};

const Keyframe& GetKeyframe() {
  static const Keyframe* keyframe = [] {
    auto frame = prism::MakeFusionTestFrame("bunny-multicolor-forward", prism::FusionTestFrameOptions());
    if (!frame.ok()) frame = prism::MakeFusionTestFrame("torus-textured-forward", prism::FusionTestFrameOptions());
    if (!frame.ok()) std::abort();
    auto* k = new Keyframe{*frame, cv::Mat()};
    k->normals = prism::PerturbNormals(k->frame.frame.normals, prism::NormalNoiseOptions());
    return k;
  }();
  return *keyframe;
}

prism::ThreadPool& Pool() {
  static prism::ThreadPool pool(2);
  return pool;
}

void Report(benchmark::State& state, const prism::FusionResult& r) {
  state.counters["iterations"] = r.iterations;
  state.counters["unknowns"] = r.unknowns;
}

void BM_Fuse(benchmark::State& state, prism::FusionPreconditioner preconditioner) {
  const Keyframe& k = GetKeyframe();
  prism::FusionOptions options;
  options.num_threads = static_cast<int>(state.range(0));
  options.preconditioner = preconditioner;
  if (preconditioner == prism::FusionPreconditioner::kJacobi) options.max_solver_iterations = 2000;
  prism::DepthNormalFusion fusion(options, &Pool());
  const prism::FusionInput input = prism::MakeFusionInput(k.frame, k.normals);
  prism::FusionResult last;
  for (auto _ : state) {
    auto r = fusion.Fuse(input);
    if (!r.ok()) {
      state.SkipWithError(r.status().ToString().c_str());
      return;
    }
    last = std::move(r).value();
    benchmark::DoNotOptimize(last.depth.data);
  }
  Report(state, last);
}

void BM_FuseMultigrid(benchmark::State& state) { BM_Fuse(state, prism::FusionPreconditioner::kMultigrid); }
void BM_FuseJacobi(benchmark::State& state) { BM_Fuse(state, prism::FusionPreconditioner::kJacobi); }

void BM_FuseOneShot(benchmark::State& state) {
  const Keyframe& k = GetKeyframe();
  prism::FusionOptions options;
  options.num_threads = static_cast<int>(state.range(0));
  const prism::FusionInput input = prism::MakeFusionInput(k.frame, k.normals);
  prism::FusionResult last;
  for (auto _ : state) {
    auto r = prism::FuseDepthAndNormals(input, options, &Pool());
    if (!r.ok()) {
      state.SkipWithError(r.status().ToString().c_str());
      return;
    }
    last = std::move(r).value();
    benchmark::DoNotOptimize(last.depth.data);
  }
  Report(state, last);
}

}  // namespace

BENCHMARK(BM_FuseMultigrid)->ArgName("threads")->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_FuseOneShot)->ArgName("threads")->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_FuseJacobi)->ArgName("threads")->Arg(2)->Unit(benchmark::kMillisecond)->UseRealTime()->Iterations(3);

BENCHMARK_MAIN();
