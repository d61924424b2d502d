// The SLAM at 512x512 on this machine: build/bin/slam_benchmark
//   BM_DepthUpdate: one stereo update of a keyframe's depth filter from a tracked frame (the mapping
//                   work per frame), on 1 thread.
//   BM_SampleAlongLine: the epipolar search's bilinear samples along a line (line_sampler.h), 70 per
//                       line, random lines over a 512x512 image: the version this CPU runs (AVX2 when
//                       present) against the portable one; the time per sample is the "ns_per_sample"
//                       counter.
//   BM_KeyframeWindowAdjustment: one window adjustment (keyframe_ba.h) with SlamSystem's window settings:
//                    8 keyframes 6 frames apart at their true poses, then perturbed (2% of the spacing
//                    sideways, 0.1 degrees, inverse depths 3% off), one point per 12x12 cell; the time
//                    per residual linearised or evaluated is the "ns_per_residual" counter. The last
//                    argument 24: 24 keyframes 4 frames apart (the size of a final adjustment).
//   BM_FeatureTracks / BM_FeatureAdjustment: the feature adjustment's two parts (feature_adjustment.h; the
//                    one-off work after the last frame): SIFT on J and matching over 22 keyframes 7 frames
//                    apart along the whole arc (every pair within 90 degrees), on 1 or 2 threads; and the
//                    adjustment of those tracks from a turn 0.98 of the truth (one thread).
//   BM_SlamSequence: the whole SlamSystem (initialisation, tracking, depth filter, keyframes, keyframe
//                    adjustment) over 150 frames of a preset; the per-frame time is the "ms_per_frame"
//                    counter (with and without the keyframe adjustment on the bunny; budget_*: with
//                    a mapping budget of 33.3 ms per frame).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <benchmark/benchmark.h>

#include "core/slam/depth_filter.h"
#include "core/slam/feature_adjustment.h"
#include "core/slam/keyframe_ba.h"
#include "core/slam/line_sampler.h"
#include "core/slam/shading_scale.h"
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
    f->frames[i] = synth::RenderFrame(f->setup.scene, f->setup.rig, f->trajectory[i].world_from_camera, f->setup.render,
                                      1000003ull + static_cast<uint64_t>(i));
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
  // Args: threads (1: no pool).
  const int threads = static_cast<int>(state.range(0));
  std::unique_ptr<ThreadPool> pool = threads > 1 ? std::make_unique<ThreadPool>(threads) : nullptr;
  for (auto _ : state) {
    KeyframeDepth copy = *kd;
    KeyframeDepth::NormalisedGrey(f->frames[5].rgb, options, &j, &mean);
    const DepthUpdateStats s = copy.Update(j, frame_from_keyframe, pool.get());
    benchmark::DoNotOptimize(s);
  }
}
BENCHMARK_CAPTURE(BM_DepthUpdate, bunny, std::string("bunny-multicolor-forward"))
    ->Arg(1)
    ->Arg(2)
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);

// One keyframe pair's shading scale (EstimateShadingScale, as the start check takes it for each of its
// five pairs and SlamSystem::EstimateMetricScale for each pair at the end): frame 30 of the preset at its
// true inverse depth (depth units of 0.6 m) against frame 38 at the true pose. The figures it reports
// (metres per unit, iterations) say that the work is the same between builds.
void BM_ShadingScale(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  constexpr double kMetresPerUnit = 0.6;
  constexpr int kKeyframe = 30, kFrame = 38;
  const synth::RenderedFrame& key = f->frames[kKeyframe];
  cv::Mat inverse_depth = cv::Mat::zeros(key.depth.size(), CV_32F);
  for (int y = 0; y < key.depth.rows; ++y)
    for (int x = 0; x < key.depth.cols; ++x)
      if (key.depth.at<float>(y, x) > 0)
        inverse_depth.at<float>(y, x) = static_cast<float>(kMetresPerUnit / key.depth.at<float>(y, x));
  Rigid3d frame_from_keyframe =
      f->trajectory[kFrame].world_from_camera.Inverse() * f->trajectory[kKeyframe].world_from_camera;
  frame_from_keyframe.translation /= kMetresPerUnit;
  const std::vector<ShadingScaleFrame> frames = {{f->frames[kFrame].rgb, frame_from_keyframe}};
  ShadingScaleResult result;
  for (auto _ : state) {
    StatusOr<ShadingScaleResult> r =
        EstimateShadingScale(f->setup.rig, key.rgb, inverse_depth, frames, ShadingScaleOptions());
    if (!r.ok()) {
      state.SkipWithError(r.status().ToString().c_str());
      return;
    }
    result = *r;
  }
  state.counters["metres_per_unit"] = result.metres_per_unit;
  state.counters["iterations"] = result.iterations;
  state.counters["points"] = result.points;
}
BENCHMARK_CAPTURE(BM_ShadingScale, bunny, std::string("bunny-multicolor-forward"))
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_ShadingScale, sphere_uniform, std::string("sphere-uniform-sideways"))
    ->Unit(benchmark::kMillisecond)
    ->Repetitions(5)
    ->ReportAggregatesOnly(true);

void BM_SampleAlongLine(benchmark::State& state, bool portable) {
  constexpr int kSize = 512, kLines = 1024, kSamples = 70;
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> value(0.0f, 255.0f), pos(40.0f, 470.0f), angle(0.0f, 6.2831853f);
  std::vector<float> pixels(static_cast<size_t>(kSize) * kSize);
  for (float& v : pixels) v = value(rng);
  LineSamplerImage image;
  image.data = pixels.data();
  image.stride = kSize;
  image.u_end = kSize - 1;
  image.v_end = kSize - 1;
  std::vector<LineSamples> lines(kLines);
  for (LineSamples& l : lines) {
    const float a = angle(rng);
    l.start_x = pos(rng);
    l.start_y = pos(rng);
    l.e_x = std::cos(a);
    l.e_y = std::sin(a);
    l.step = 0.9f;
    l.k_offset = -3;
    l.num = kSamples;
  }
  std::vector<float> samples(kSamples);
  std::vector<int> outside(kSamples + 1);
  for (auto _ : state) {
    for (const LineSamples& l : lines) {
      if (portable) SampleAlongLinePortable(image, l, samples.data(), outside.data());
      else SampleAlongLine(image, l, samples.data(), outside.data());
      benchmark::DoNotOptimize(samples.data());
    }
  }
  state.counters["ns_per_sample"] = benchmark::Counter(static_cast<double>(state.iterations()) * kLines * kSamples,
                                                       benchmark::Counter::kIsRate | benchmark::Counter::kInvert);
  state.SetLabel(portable ? "portable" : (LineSamplerUsesAvx2() ? "AVX2" : "portable (no AVX2 here)"));
}
BENCHMARK_CAPTURE(BM_SampleAlongLine, dispatched, false)->Repetitions(5)->ReportAggregatesOnly(true);
BENCHMARK_CAPTURE(BM_SampleAlongLine, portable, true)->Repetitions(5)->ReportAggregatesOnly(true);

void BM_KeyframeWindowAdjustment(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  const SlamOptions slam_options;
  // Arg 3: keyframes (0: the window's 8, 6 frames apart; more: 4 frames apart, as the final adjustment).
  const int num_kf = state.range(3) > 0 ? static_cast<int>(state.range(3)) : slam_options.keyframe_window;
  const int spacing = state.range(3) > 0 ? 4 : 6, first = 40;
  DirectBaProblem start;
  start.camera = f->setup.rig.camera;
  std::mt19937 rng(11);
  std::normal_distribution<float> noise(0.0f, 0.03f);
  for (int k = 0; k < num_kf; ++k) {
    const synth::RenderedFrame& frame = f->frames[static_cast<size_t>(first + spacing * k)];
    const Rigid3d& pose = f->trajectory[static_cast<size_t>(first + spacing * k)].world_from_camera;
    Sim3d world_from_keyframe(1.0, pose.rotation, pose.translation);
    if (k >= 2) {
      const Rigid3d& previous = f->trajectory[static_cast<size_t>(first + spacing * (k - 1))].world_from_camera;
      const double step = (pose.translation - previous.translation).norm();
      world_from_keyframe.translation += pose.rotation * Eigen::Vector3d(0, 0.02 * step, 0);
      world_from_keyframe.rotation = world_from_keyframe.rotation *
                                     Eigen::Quaterniond(Eigen::AngleAxisd(0.1 * M_PI / 180, Eigen::Vector3d::UnitX()));
    }
    start.world_from_keyframe.push_back(world_from_keyframe);
    cv::Mat j, mean;
    KeyframeDepth::NormalisedGrey(frame.rgb, slam_options.depth, &j, &mean);
    start.grey_j.push_back(j);
    cv::Mat inverse_depth = cv::Mat::zeros(frame.depth.size(), CV_32F);
    for (int y = 0; y < frame.depth.rows; ++y)
      for (int x = 0; x < frame.depth.cols; ++x)
        if (frame.depth.at<float>(y, x) > 0) inverse_depth.at<float>(y, x) = 1.0f / frame.depth.at<float>(y, x);
    SelectCellPoints(
        j, inverse_depth, k, slam_options.keyframe_window_cell_px, 0.0f, [](int, int) { return true; }, &start.points);
  }
  for (DirectBaPoint& p : start.points) p.inverse_depth *= std::exp(noise(rng));
  // Args: threads (1: no pool, as SlamSystem on one thread); the LM damping rule
  // (DirectBaOptions::gain_ratio_damping, 0: the fixed factors, 1: the gain ratio, SlamSystem's); the
  // linearisation's reads (DirectBaOptions::linearise_from_evaluation, 0: its own, 1: the evaluation's,
  // SlamSystem's).
  const int threads = static_cast<int>(state.range(0));
  DirectBaOptions ba_options = slam_options.keyframe_window_ba;
  ba_options.gain_ratio_damping = state.range(1) != 0;
  ba_options.linearise_from_evaluation = state.range(2) != 0;
  std::unique_ptr<ThreadPool> pool = threads > 1 ? std::make_unique<ThreadPool>(threads) : nullptr;
  DirectBaSummary summary;
  double seconds = 0;
  for (auto _ : state) {
    state.PauseTiming();
    DirectBaProblem problem = start;
    state.ResumeTiming();
    const auto t0 = std::chrono::steady_clock::now();
    StatusOr<DirectBaSummary> s = AdjustKeyframeWindowDirect(ba_options, &problem, pool.get());
    seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!s.ok()) {
      state.SkipWithError(s.status().ToString().c_str());
      return;
    }
    summary = *s;
  }
  state.counters["points"] = static_cast<double>(start.points.size());
  state.counters["residuals"] = summary.residuals;
  state.counters["iterations"] = summary.iterations;
  state.counters["evaluations"] = summary.evaluations;
  state.counters["final_rms"] = summary.final_rms;
  state.counters["image_samples"] = static_cast<double>(summary.image_samples);
  // Each iteration linearises once and evaluates at least once: per residual of the final solve.
  state.counters["ns_per_residual"] =
      1e9 * seconds / (static_cast<double>(state.iterations()) * summary.residuals * 2 * summary.iterations);
}
// Threads, damping rule, reads (see above) and keyframes (0: the window's 8, or 24).
void WindowAdjustmentSettings(benchmark::internal::Benchmark* b) {
  b->Args({1, 0, 1, 0})
      ->Args({1, 1, 0, 0})
      ->Args({1, 1, 1, 0})
      ->Args({2, 1, 1, 0})
      ->Args({1, 1, 1, 24})
      ->Args({2, 1, 1, 24})
      ->Unit(benchmark::kMillisecond)
      ->UseRealTime()
      ->Repetitions(5)
      ->ReportAggregatesOnly(true);
}
BENCHMARK_CAPTURE(BM_KeyframeWindowAdjustment, torus, std::string("torus-textured-forward"))
    ->Apply(WindowAdjustmentSettings);
BENCHMARK_CAPTURE(BM_KeyframeWindowAdjustment, armadillo, std::string("armadillo-textured-forward"))
    ->Apply(WindowAdjustmentSettings);

void BM_SlamSequence(benchmark::State& state, const std::string& preset, bool keyframe_adjustment,
                     double mapping_budget_ms = 0, bool async_adjustment = false, bool paced = false,
                     double max_wait_ms = -1, bool start_check_async = true) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  ThreadPool pool(static_cast<int>(state.range(0)));
  int lost = 0, keyframes = 0, adjustments = 0;
  std::vector<double> frame_ms;  // of the last iteration
  SlamTimings timings;           // of the last iteration
  StartCheckReport check;        // of the last iteration
  for (auto _ : state) {
    frame_ms.clear();
    SlamOptions options;
    options.keyframe_adjustment = keyframe_adjustment;
    options.mapping_budget_ms = mapping_budget_ms;
    options.keyframe_adjustment_async = async_adjustment;
    options.keyframe_adjustment_max_wait_ms = max_wait_ms;
    options.start_check_async = start_check_async;
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(f->setup.rig, options, &pool);
    if (!slam.ok()) {
      state.SkipWithError(slam.status().ToString().c_str());
      return;
    }
    const auto start = std::chrono::steady_clock::now();
    for (size_t i = 0; i < f->frames.size(); ++i) {
      // Paced: frame i arrives at i / 30 s (as from a camera), not as soon as the last one is done.
      if (paced) std::this_thread::sleep_until(start + std::chrono::microseconds(33333 * static_cast<int64_t>(i)));
      const auto t0 = std::chrono::steady_clock::now();
      StatusOr<SlamFrameResult> r = (*slam)->ProcessFrame(f->trajectory[i].timestamp_s, f->frames[i].rgb);
      frame_ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
      if (!r.ok()) {
        state.SkipWithError(r.status().ToString().c_str());
        return;
      }
      lost += r->state == SlamState::kLost;
      benchmark::DoNotOptimize((*slam)->TakeFinishedKeyframes());
    }
    keyframes = (*slam)->num_keyframes();
    adjustments = (*slam)->num_keyframe_adjustments();
    timings = (*slam)->timings();
    check = (*slam)->start_check();
  }
  state.counters["ms_per_frame"] =
      benchmark::Counter(static_cast<double>(f->frames.size()) * state.iterations(),
                         benchmark::Counter::kIsRate | benchmark::Counter::kInvert, benchmark::Counter::kIs1000);
  // The spread over the frames: keyframes (propagation, adjustment) are the slow ones.
  if (!frame_ms.empty())
    state.counters["max_frame_at"] =
        static_cast<double>(std::max_element(frame_ms.begin(), frame_ms.end()) - frame_ms.begin());
  std::sort(frame_ms.begin(), frame_ms.end());
  if (!frame_ms.empty()) {
    state.counters["p50_frame_ms"] = frame_ms[frame_ms.size() / 2];
    state.counters["p95_frame_ms"] = frame_ms[frame_ms.size() * 95 / 100];
    state.counters["max_frame_ms"] = frame_ms.back();
  }
  // The two halves the speed bar puts on separate cores (SlamTimings), per tracked frame.
  const double tracked = std::max(1, timings.tracked_frames);
  state.counters["tracking_ms"] = 1000.0 * timings.tracking / tracked;
  state.counters["mapping_ms"] = 1000.0 * (timings.depth_update + timings.keyframes) / tracked;
  state.counters["depth_update_ms"] = 1000.0 * timings.depth_update / tracked;
  state.counters["keyframe_adjustment_ms"] = 1000.0 * timings.keyframe_adjustment / tracked;
  if (async_adjustment) {
    // The adjustment's own thread, and the tracking core's load with it there: tracking plus adjustment.
    state.counters["adjustment_thread_ms"] = 1000.0 * timings.keyframe_adjustment_thread / tracked;
    state.counters["adjustment_wait_ms"] = 1000.0 * timings.keyframe_adjustment_wait / tracked;
    state.counters["tracking_core_ms"] = 1000.0 * (timings.tracking + timings.keyframe_adjustment_thread) / tracked;
    state.counters["keyframes_before_adjustment"] = timings.keyframes_made_before_adjustment;
    state.counters["window_adjustments"] = adjustments;
  }
  // Stereo updates made, per tracked frame (below 1 under a mapping budget; the first keyframe's frame
  // and those tracked during the initialisation have none).
  state.counters["updates_per_frame"] = timings.depth_updates / tracked;
  // The start check's time inside the frames (StartCheckReport::seconds) and on its own thread.
  state.counters["start_check_frame_ms"] = 1000.0 * check.seconds;
  state.counters["start_check_thread_ms"] = 1000.0 * check.thread_seconds;
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
// Every standard preset, everything on one core (the depth filter's pool has one thread): the
// per-preset figures of the speed bar (tracking and mapping together within 33 ms keeps up with 30 fps
// on one core, so a second core is spare). preset_*: the defaults. budget_*: with
// SlamOptions::mapping_budget_ms = 33.3 (off by default), stereo updates are left out when the mapping
// would fall behind 30 frames/s on its core; wall-time dependent: mapping_ms should be about 33.3 or
// less, except where the keyframe work alone nearly fills the budget, and updates_per_frame says what
// was left out (`--benchmark_filter=SlamSequence/budget_`). async_*: with
// SlamOptions::keyframe_adjustment_async, the window adjustment on a thread of its own (the second
// core, beside the tracking): mapping_ms is then the mapping core's share without it, and
// tracking_core_ms the tracking plus the adjustment's thread (adjustment_thread_ms); adjustment_wait_ms
// is what the mapping waited for an adjustment to finish (part of mapping_ms). paced_*: async_*, with
// the frames handed in at 30 frames/s as a camera would (the others hand each frame in as soon as the
// last one is done, which leaves the adjustment less time between keyframes than it has live): its
// adjustment_wait_ms is the live one. Its time (real_time) is the sequence's length at 30 frames/s.
// async_* and paced_* wait for the adjustment at the next keyframe
// (SlamOptions::keyframe_adjustment_max_wait_ms = -1, the default).
// bounded_*: paced_*, with keyframe_adjustment_max_wait_ms = 0, as prism-server's live sessions (a new keyframe goes on
// without the adjustment still running; keyframes_before_adjustment counts those keyframes, and
// window_adjustments the adjustments run): the tail of the frame times (p95_frame_ms, max_frame_ms)
// without the waits. These run the start check's pair scales on their own thread (SlamOptions::start_check_async,
// the default; the other cases too); bounded_inline_check_*: bounded_* with them inside the frame that brings the
// sixth keyframe (start_check_async = false; start_check_frame_ms is then the pause).
// One thread, one pass per repetition, medians of 3.
void WholeSequenceSettings(benchmark::internal::Benchmark* b) {
  b->Arg(1)->Unit(benchmark::kMillisecond)->Iterations(1)->UseRealTime()->Repetitions(3)->ReportAggregatesOnly(true);
}
#define PRISM_SLAM_PRESET_BENCHMARK(NAME, PRESET)                                                                   \
  BENCHMARK_CAPTURE(BM_SlamSequence, preset_##NAME, std::string(PRESET), true, 0.0)->Apply(WholeSequenceSettings);  \
  BENCHMARK_CAPTURE(BM_SlamSequence, budget_##NAME, std::string(PRESET), true, 33.3)->Apply(WholeSequenceSettings); \
  BENCHMARK_CAPTURE(BM_SlamSequence, async_##NAME, std::string(PRESET), true, 0.0, true)                            \
      ->Apply(WholeSequenceSettings);                                                                               \
  BENCHMARK_CAPTURE(BM_SlamSequence, paced_##NAME, std::string(PRESET), true, 0.0, true, true)                      \
      ->Apply(WholeSequenceSettings);                                                                               \
  BENCHMARK_CAPTURE(BM_SlamSequence, bounded_##NAME, std::string(PRESET), true, 0.0, true, true, 0.0)               \
      ->Apply(WholeSequenceSettings);                                                                               \
  BENCHMARK_CAPTURE(BM_SlamSequence, bounded_inline_check_##NAME, std::string(PRESET), true, 0.0, true, true, 0.0,  \
                    false)                                                                                          \
      ->Apply(WholeSequenceSettings)
PRISM_SLAM_PRESET_BENCHMARK(bunny_multicolor_forward, "bunny-multicolor-forward");
PRISM_SLAM_PRESET_BENCHMARK(sphere_multicolor_sideways, "sphere-multicolor-sideways");
PRISM_SLAM_PRESET_BENCHMARK(dragon_multicolor_sideways, "dragon-multicolor-sideways");
PRISM_SLAM_PRESET_BENCHMARK(sphere_uniform_sideways, "sphere-uniform-sideways");
PRISM_SLAM_PRESET_BENCHMARK(relief_uniform_sideways, "relief-uniform-sideways");
PRISM_SLAM_PRESET_BENCHMARK(boxes_multicolor_forward, "boxes-multicolor-forward");
PRISM_SLAM_PRESET_BENCHMARK(bunny_uniform_sideways, "bunny-uniform-sideways");
PRISM_SLAM_PRESET_BENCHMARK(armadillo_textured_forward, "armadillo-textured-forward");
PRISM_SLAM_PRESET_BENCHMARK(torus_textured_forward, "torus-textured-forward");

// 22 keyframes 7 frames apart over the preset's 150 frames: their images (J with SlamOptions' box) and true
// poses.
struct FeatureArc {
  std::vector<FeatureImage> images;
  std::vector<Sim3d> truth;
};
FeatureArc MakeFeatureArc(const Frames& f) {
  FeatureArc a;
  const DepthFilterOptions depth = SlamOptions().depth;
  for (size_t i = 0; i < f.frames.size(); i += 7) {
    FeatureImage image;
    KeyframeDepth::NormalisedGrey(f.frames[i].rgb, depth, &image.grey_j, &image.local_mean);
    a.images.push_back(image);
    const Rigid3d& p = f.trajectory[i].world_from_camera;
    a.truth.push_back(Sim3d(1.0, p.rotation, p.translation));
  }
  return a;
}

void BM_FeatureTracks(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  const FeatureArc arc = MakeFeatureArc(*f);
  const int threads = static_cast<int>(state.range(0));
  std::unique_ptr<ThreadPool> pool = threads > 1 ? std::make_unique<ThreadPool>(threads) : nullptr;
  size_t tracks = 0;
  int pairs = 0;
  for (auto _ : state) {
    StatusOr<FeatureTracks> t =
        BuildFeatureTracks(f->setup.rig.camera, FeatureAdjustmentOptions(), arc.images, arc.truth, pool.get());
    if (!t.ok()) {
      state.SkipWithError(t.status().ToString().c_str());
      return;
    }
    tracks = t->tracks.size();
    pairs = t->pairs_tried;
  }
  state.counters["tracks"] = static_cast<double>(tracks);
  state.counters["pairs"] = pairs;
}
BENCHMARK_CAPTURE(BM_FeatureTracks, torus, std::string("torus-textured-forward"))
    ->Arg(1)
    ->Arg(2)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();
BENCHMARK_CAPTURE(BM_FeatureTracks, bunny, std::string("bunny-multicolor-forward"))
    ->Arg(1)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

void BM_FeatureAdjustment(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  const FeatureArc arc = MakeFeatureArc(*f);
  const FeatureAdjustmentOptions options;
  StatusOr<FeatureTracks> tracks = BuildFeatureTracks(f->setup.rig.camera, options, arc.images, arc.truth);
  if (!tracks.ok()) {
    state.SkipWithError(tracks.status().ToString().c_str());
    return;
  }
  std::vector<Sim3d> start = arc.truth;
  for (Sim3d& p : start) {
    const Eigen::AngleAxisd aa(arc.truth.front().rotation.conjugate() * p.rotation);
    p.rotation = arc.truth.front().rotation * Eigen::Quaterniond(Eigen::AngleAxisd(0.98 * aa.angle(), aa.axis()));
  }
  int iterations = 0, observations = 0;
  for (auto _ : state) {
    std::vector<Sim3d> poses = start;
    StatusOr<FeatureAdjustmentSummary> s = AdjustKeyframesByFeatures(f->setup.rig.camera, options, *tracks, &poses);
    if (!s.ok()) {
      state.SkipWithError(s.status().ToString().c_str());
      return;
    }
    iterations = s->iterations;
    observations = s->observations;
  }
  state.counters["iterations"] = iterations;
  state.counters["observations"] = observations;
}
BENCHMARK_CAPTURE(BM_FeatureAdjustment, torus, std::string("torus-textured-forward"))
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();
BENCHMARK_CAPTURE(BM_FeatureAdjustment, bunny, std::string("bunny-multicolor-forward"))
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// The initialisation's pause (SlamOptions::init_threads, the argument): the frames up to the first tracked
// one, on one core as in the bounded_* cases (the SLAM's pool has one thread). init_frame_ms is the frame
// that completes the initialisation (it tracks the buffered frames twice and refines the first keyframe's
// depth with each: the slowest frame of a run), initialisation_ms all the frames before the first keyframe
// (timings.initialisation, which includes it), buffered_frames how many it tracked.
void BM_SlamInitialisation(benchmark::State& state, const std::string& preset) {
  const Frames* f = GetFrames(preset);
  if (!f) {
    state.SkipWithError("preset unavailable");
    return;
  }
  ThreadPool pool(1);
  double init_frame_ms = 0, initialisation_ms = 0;
  int buffered = 0;
  for (auto _ : state) {
    SlamOptions options;
    options.init_threads = static_cast<int>(state.range(0));
    StatusOr<std::unique_ptr<SlamSystem>> slam = SlamSystem::Create(f->setup.rig, options, &pool);
    if (!slam.ok()) {
      state.SkipWithError(slam.status().ToString().c_str());
      return;
    }
    bool initialised = false;
    for (size_t i = 0; i < f->frames.size() && !initialised; ++i) {
      const auto t0 = std::chrono::steady_clock::now();
      StatusOr<SlamFrameResult> r = (*slam)->ProcessFrame(f->trajectory[i].timestamp_s, f->frames[i].rgb);
      const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      if (!r.ok()) {
        state.SkipWithError(r.status().ToString().c_str());
        return;
      }
      if (r->state == SlamState::kTracking) {
        initialised = true;
        init_frame_ms = ms;
        buffered = static_cast<int>(i);
      }
    }
    if (!initialised) {
      state.SkipWithError("not initialised");
      return;
    }
    initialisation_ms = 1000.0 * (*slam)->timings().initialisation;
  }
  state.counters["init_frame_ms"] = init_frame_ms;
  state.counters["initialisation_ms"] = initialisation_ms;
  state.counters["buffered_frames"] = buffered;
}
void InitialisationSettings(benchmark::internal::Benchmark* b) {
  b->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond)->Iterations(1)->UseRealTime()->Repetitions(5);
  b->ReportAggregatesOnly(true);
}
#define PRISM_SLAM_INIT_BENCHMARK(NAME, PRESET) \
  BENCHMARK_CAPTURE(BM_SlamInitialisation, NAME, std::string(PRESET))->Apply(InitialisationSettings)
PRISM_SLAM_INIT_BENCHMARK(bunny_multicolor_forward, "bunny-multicolor-forward");
PRISM_SLAM_INIT_BENCHMARK(sphere_multicolor_sideways, "sphere-multicolor-sideways");
PRISM_SLAM_INIT_BENCHMARK(dragon_multicolor_sideways, "dragon-multicolor-sideways");
PRISM_SLAM_INIT_BENCHMARK(sphere_uniform_sideways, "sphere-uniform-sideways");
PRISM_SLAM_INIT_BENCHMARK(relief_uniform_sideways, "relief-uniform-sideways");
PRISM_SLAM_INIT_BENCHMARK(boxes_multicolor_forward, "boxes-multicolor-forward");
PRISM_SLAM_INIT_BENCHMARK(bunny_uniform_sideways, "bunny-uniform-sideways");
PRISM_SLAM_INIT_BENCHMARK(armadillo_textured_forward, "armadillo-textured-forward");
PRISM_SLAM_INIT_BENCHMARK(torus_textured_forward, "torus-textured-forward");

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
