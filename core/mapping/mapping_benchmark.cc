// Registration + map merge per keyframe at 512x512 (the dense stage's bar: <= 50 ms median).
// Each case renders dense keyframe clouds of a preset (~2.5e5 points each: the ground fills the frame),
// builds the map (2 mm voxels) from the keyframe before, and times, per keyframe: the ICP target of the map snapshot
// (PCL cloud + kd-tree), ICP from a drifted guess (default IcpOptions) and the merge of the registered keyframe into
// the map. Counters give the pose error against the ground truth, so speed never hides a wrong answer. Run:
// build/bin/mapping_benchmark --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <benchmark/benchmark.h>

#include "core/mapping/global_map.h"
#include "core/mapping/icp.h"
#include "core/mapping/synthetic_keyframe.h"
#include "core/synth/presets.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

constexpr double kDegToRad = M_PI / 180.0;
// Frames between keyframes: 0.5 s at 30 fps, ~6 degrees of the preset's 120-degree, 300-frame orbit
// (~5 cm of camera motion).
constexpr int kKeyframeStep = 15;
constexpr int kKeyframePairs = 4;

// One registration problem: the map of the previous keyframe and the next keyframe's cloud.
struct KeyframePair {
  GlobalMap map;
  PointCloud cloud;           // camera frame
  Rigid3d world_from_camera;  // ground truth
  Rigid3d guess;              // drifted
};

struct Scenario {
  std::string error;
  std::vector<KeyframePair> pairs;
  double mean_points = 0;
};

// Rendered once per preset and shared by the cases.
const Scenario& GetScenario(const std::string& preset) {
  static std::map<std::string, std::unique_ptr<Scenario>> cache;
  auto& slot = cache[preset];
  if (slot) return *slot;
  slot = std::make_unique<Scenario>();
  synth::PresetOptions o;
  o.width = 512;
  o.height = 512;
  o.frames = 300;  // the presets' default sequence length: it sets the orbit's pace
  auto setup = synth::MakePreset(preset, o);
  if (!setup.ok()) {
    slot->error = setup.status().ToString();
    return *slot;
  }
  const Trajectory trajectory = synth::MakeTrajectory(setup->trajectory);
  ThreadPool pool(0);
  auto render = [&](int frame) {
    const synth::RenderedFrame f = synth::RenderFrame(setup->scene, setup->rig, trajectory[frame].world_from_camera,
                                                      setup->render, frame + 1, &pool);
    return BackProjectFrame(setup->rig.camera, f);
  };
  PointCloud previous = render(0);
  for (int k = 1; k <= kKeyframePairs; ++k) {
    KeyframePair pair;
    const int frame = k * kKeyframeStep;
    PRISM_CHECK(pair.map.Insert(previous, trajectory[frame - kKeyframeStep].world_from_camera, k - 1).ok());
    pair.map.TakeChanges();
    pair.cloud = render(frame);
    pair.world_from_camera = trajectory[frame].world_from_camera;
    // Tracking drift the registration has to remove: 0.7 degrees and ~1 cm, varying per pair.
    const Rigid3d drift(Eigen::Quaterniond(Eigen::AngleAxisd(0.7 * kDegToRad, Eigen::Vector3d(1, k, 2).normalized())),
                        Eigen::Vector3d(0.003, -0.002 * k, 0.002));
    pair.guess = drift * pair.world_from_camera;
    slot->mean_points += static_cast<double>(pair.cloud.size()) / kKeyframePairs;
    previous = pair.cloud;
    slot->pairs.push_back(std::move(pair));
  }
  return *slot;
}

struct Errors {
  double max_rotation_rad = 0;
  double max_translation_m = 0;
  void Add(const Rigid3d& estimate, const Rigid3d& truth) {
    max_rotation_rad = std::max(max_rotation_rad, RotationAngle(estimate.rotation * truth.rotation.inverse()));
    max_translation_m = std::max(max_translation_m, (estimate.translation - truth.translation).norm());
  }
  void Report(benchmark::State& state) const {
    state.counters["max_rot_err_mrad"] = 1e3 * max_rotation_rad;
    state.counters["max_trans_err_mm"] = 1e3 * max_translation_m;
  }
};

// The whole per-keyframe step: target of the map snapshot + ICP + merge.
void BM_KeyframeIcpAndMerge(benchmark::State& state, const std::string& preset, IcpMethod method) {
  const Scenario& scenario = GetScenario(preset);
  if (!scenario.error.empty()) {
    state.SkipWithError(scenario.error.c_str());
    return;
  }
  IcpOptions options;
  options.method = method;
  Errors errors;
  GlobalMap map;
  size_t i = 0;
  for (auto _ : state) {
    const KeyframePair& pair = scenario.pairs[i++ % scenario.pairs.size()];
    state.PauseTiming();
    map = pair.map;  // each keyframe meets the map of its predecessor (copied and freed untimed)
    state.ResumeTiming();
    auto target = IcpTarget::Create(map.ToPointCloud(), options);
    Rigid3d world_from_camera;
    auto summary = AlignIcp(pair.cloud, *target, pair.guess, options, &world_from_camera);
    auto merged = map.Insert(pair.cloud, world_from_camera, i);
    if (!target.ok() || !summary.ok() || !merged.ok()) {
      state.SkipWithError("ICP or merge failed");
      return;
    }
    MapChunk chunk = map.TakeChanges();
    benchmark::DoNotOptimize(chunk.keys.data());
    state.PauseTiming();
    errors.Add(world_from_camera, pair.world_from_camera);
    state.ResumeTiming();
  }
  errors.Report(state);
  state.counters["points"] = scenario.mean_points;
}

// The parts on their own.
void BM_IcpTargetBuild(benchmark::State& state, const std::string& preset) {
  const Scenario& scenario = GetScenario(preset);
  if (!scenario.error.empty()) {
    state.SkipWithError(scenario.error.c_str());
    return;
  }
  const PointCloud map_cloud = scenario.pairs[0].map.ToPointCloud();
  for (auto _ : state) {
    auto target = IcpTarget::Create(map_cloud, IcpOptions());
    benchmark::DoNotOptimize(target.ok());
  }
  state.counters["map_voxels"] = static_cast<double>(map_cloud.size());
}

void BM_AlignIcp(benchmark::State& state, const std::string& preset) {
  const Scenario& scenario = GetScenario(preset);
  if (!scenario.error.empty()) {
    state.SkipWithError(scenario.error.c_str());
    return;
  }
  const IcpOptions options;
  std::vector<IcpTarget> targets;
  for (const KeyframePair& pair : scenario.pairs)
    targets.push_back(IcpTarget::Create(pair.map.ToPointCloud(), options).value());
  Errors errors;
  double iterations = 0;
  size_t i = 0;
  for (auto _ : state) {
    const size_t k = i++ % scenario.pairs.size();
    Rigid3d estimate;
    auto summary = AlignIcp(scenario.pairs[k].cloud, targets[k], scenario.pairs[k].guess, options, &estimate);
    iterations += summary->iterations;
    errors.Add(estimate, scenario.pairs[k].world_from_camera);
  }
  errors.Report(state);
  state.counters["iterations"] = iterations / static_cast<double>(state.iterations());
}

void BM_MapInsert(benchmark::State& state, const std::string& preset) {
  const Scenario& scenario = GetScenario(preset);
  if (!scenario.error.empty()) {
    state.SkipWithError(scenario.error.c_str());
    return;
  }
  GlobalMap map;
  size_t i = 0;
  for (auto _ : state) {
    const KeyframePair& pair = scenario.pairs[i++ % scenario.pairs.size()];
    state.PauseTiming();
    map = pair.map;
    state.ResumeTiming();
    auto merged = map.Insert(pair.cloud, pair.world_from_camera, i);
    MapChunk chunk = map.TakeChanges();
    benchmark::DoNotOptimize(chunk.keys.data());
    benchmark::DoNotOptimize(merged.ok());
  }
  state.counters["points"] = scenario.mean_points;
}

const std::string kRelief = "relief-uniform-sideways";  // procedural: always available
const std::string kBunny = "bunny-uniform-sideways";

BENCHMARK_CAPTURE(BM_KeyframeIcpAndMerge, relief_point_to_plane, kRelief, IcpMethod::kPointToPlane)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_KeyframeIcpAndMerge, bunny_point_to_plane, kBunny, IcpMethod::kPointToPlane)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_KeyframeIcpAndMerge, bunny_point_to_point, kBunny, IcpMethod::kPointToPoint)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_KeyframeIcpAndMerge, bunny_generalized, kBunny, IcpMethod::kGeneralized)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_IcpTargetBuild, bunny, kBunny)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_AlignIcp, bunny, kBunny)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_MapInsert, bunny, kBunny)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
