// Codec speed and size: frame encode/decode per codec on a rendered 512x512 frame, and map-chunk
// encode/decode on a keyframe-sized chunk. Counters: bytes per frame, bits per point.
//   codec_benchmark --benchmark_format=json
#include <unistd.h>

#include <filesystem>
#include <random>
#include <string>

#include <benchmark/benchmark.h>

#include "core/codec/frame_codec.h"
#include "core/codec/map_chunk_codec.h"
#include "core/io/sequence.h"
#include "core/mapping/global_map.h"
#include "core/synth/presets.h"
#include "core/synth/synthesize.h"

namespace prism {
namespace {

const cv::Mat& Frame() {
  static const cv::Mat frame = [] {
    synth::PresetOptions po;
    po.frames = 2;
    StatusOr<synth::SynthSetup> setup = synth::MakePreset("bunny-multicolor-forward", po);
    if (!setup.ok()) setup = synth::MakePreset("sphere-multicolor-sideways", po);
    PRISM_CHECK(setup.ok()) << setup.status();
    const std::string dir =
        (std::filesystem::temp_directory_path() / ("prism_codec_bench_" + std::to_string(getpid()))).string();
    PRISM_CHECK(synth::SynthesizeSequence(*setup, 1, dir, nullptr).ok());
    StatusOr<Sequence> seq = LoadSequence(dir);
    PRISM_CHECK(seq.ok());
    cv::Mat rgb = *seq->ReadRgb(0);
    std::filesystem::remove_all(dir);
    return rgb;
  }();
  return frame;
}

FrameEncodeOptions Options(int codec, int quality) {
  FrameEncodeOptions o;
  o.codec = static_cast<FrameCodec>(codec);
  if (quality > 0) o.jpeg_quality = quality;
  return o;
}

void BM_EncodeFrame(benchmark::State& state) {
  const cv::Mat& rgb = Frame();
  const FrameEncodeOptions o = Options(static_cast<int>(state.range(0)), static_cast<int>(state.range(1)));
  std::vector<uint8_t> bytes;
  for (auto _ : state) PRISM_CHECK(EncodeFrame(rgb, o, &bytes).ok());
  state.counters["bytes"] = static_cast<double>(bytes.size());
  state.SetLabel(FrameCodecName(o.codec));
}

void BM_DecodeFrame(benchmark::State& state) {
  const cv::Mat& rgb = Frame();
  const FrameEncodeOptions o = Options(static_cast<int>(state.range(0)), static_cast<int>(state.range(1)));
  std::vector<uint8_t> bytes;
  PRISM_CHECK(EncodeFrame(rgb, o, &bytes).ok());
  cv::Mat out;
  for (auto _ : state) PRISM_CHECK(DecodeFrame(bytes.data(), bytes.size(), o.codec, rgb.cols, rgb.rows, &out).ok());
  state.counters["bytes"] = static_cast<double>(bytes.size());
  state.SetLabel(FrameCodecName(o.codec));
}

// A keyframe-sized chunk: a 2 mm map of a noisy sphere patch (~1e5 voxels).
const MapChunk& Chunk() {
  static const MapChunk chunk = [] {
    std::mt19937 rng(1);
    std::normal_distribution<float> g(0.0f, 1.0f);
    PointCloud cloud;
    for (int i = 0; i < 400000; ++i) {
      Eigen::Vector3f d(g(rng), g(rng), -std::abs(g(rng)));
      d.normalize();
      cloud.positions.push_back(Eigen::Vector3f(0, 0, 0.6f) + 0.15f * d +
                                0.0003f * Eigen::Vector3f(g(rng), g(rng), g(rng)));
      cloud.normals.push_back(d);
      cloud.colors.push_back(Eigen::Matrix<uint8_t, 3, 1>(200, static_cast<uint8_t>(100 + 50 * d.x()), 40));
    }
    GlobalMap map;
    PRISM_CHECK(map.Insert(cloud, 1).ok());
    return map.TakeChanges();
  }();
  return chunk;
}

void BM_EncodeMapChunk(benchmark::State& state) {
  MapChunkCodecOptions o;
  o.compression_level = static_cast<int>(state.range(0));
  StatusOr<EncodedMapChunk> e = EncodedMapChunk();
  for (auto _ : state) e = EncodeMapChunk(Chunk().cloud, o);
  state.counters["points"] = static_cast<double>(e->num_points);
  state.counters["bits_per_point"] = 8.0 * e->bytes.size() / e->num_points;
}

void BM_DecodeMapChunk(benchmark::State& state) {
  StatusOr<EncodedMapChunk> e = EncodeMapChunk(Chunk().cloud, MapChunkCodecOptions());
  PRISM_CHECK(e.ok());
  for (auto _ : state) benchmark::DoNotOptimize(DecodeMapChunk(e->bytes.data(), e->bytes.size()));
  state.counters["points"] = static_cast<double>(e->num_points);
}

BENCHMARK(BM_EncodeFrame)->Args({0, 0})->Args({1, 95})->Args({1, 90})->Args({2, 0})->Unit(benchmark::kMillisecond);
BENCHMARK(BM_DecodeFrame)->Args({0, 0})->Args({1, 95})->Args({1, 90})->Args({2, 0})->Unit(benchmark::kMillisecond);
BENCHMARK(BM_EncodeMapChunk)->Arg(3)->Arg(7)->Arg(10)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_DecodeMapChunk)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace prism

BENCHMARK_MAIN();
