// prism-synth: renders a synthetic multispectral sequence with ground truth (core/synth).
//   prism-synth --list-presets
//   prism-synth --preset NAME --out DIR [--frames N] [--size WxH] [--seed S] [options]
#include <array>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <optional>
#include <string>

#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/synth/families.h"
#include "core/synth/ground_truth_cloud.h"
#include "core/synth/presets.h"
#include "core/synth/synthesize.h"
#include "core/util/thread_pool.h"

namespace {

constexpr char kUsage[] = R"(usage:
  prism-synth --list-presets
  prism-synth --preset NAME --out DIR [--frames N] [--size WxH] [--seed S] [options]
  prism-synth --random SEED [--family NAME] [--world-lights] --out DIR [--frames N] [--size WxH] [options]

Renders a synthetic sequence of the three-light rig in the TUM RGB-D layout (rgb/, depth/,
normals/, mask/, groundtruth.txt, camera.yaml, scene.yaml) and prints a JSON summary.

options:
  --list-presets      print one preset name per line (the first is the demo scene)
  --describe          with --list-presets: add a tab and a description to each line
  --preset NAME       scene, material and trajectory (see --list-presets)
  --random SEED       a scene drawn at random from a family's ranges instead (docs/scene_families.md):
                      objects, albedo, ground, lights, crosstalk, path, jitter, noise; seeds 1-999 are
                      for tuning, 100000-100999 are held out for reporting
  --family NAME       with --random: the family (default mixed; --list-families)
  --list-families     print one family name per line (with --describe: a tab and its ranges)
  --world-lights      with --random: the rig's lights stay where they were at the first frame (ordinary
                      lighting; camera.yaml then gives them intensity 0: none moves with the camera)
  --out DIR           output folder (created)
  --frames N          number of frames at 30 fps (default 300; with --random, drawn: 150-300)
  --size WxH          image size (default 512x512)
  --seed S            random seed for textures, jitter and noise (default 1)
  --threads T         worker threads (default: all cores)
  --mesh-dir DIR      folder with bunny00.off, armadillo.off, ChineseDragon-10kv.off
  --noise SIGMA       read-noise standard deviation in 8-bit levels (default from the preset)
  --ambient A         white ambient light in [0, 1] (default 0: dark room)
  --supersampling N   N x N rays per pixel, averaged: pixel-area integration (default from the preset)
  --no-shadows        disable cast shadows
  --distortion K1,K2,P1,P2,K3  render through this lens distortion (OpenCV's radial-tangential model;
                      written to camera.yaml), e.g. -0.25,0.08,0,0,0 for a webcam's barrel distortion
  --gt-cloud FILE     also write a dense ground-truth cloud (PLY: positions, normals, colours;
                      every 10th frame back-projected, 2 mm voxels)
  --help              this text
)";

int Fail(const std::string& message) {
  std::cerr << "prism-synth: " << message << "\n";
  return 2;
}

bool ParseInt(const char* s, long lo, long hi, int* out) {
  char* end = nullptr;
  const long v = std::strtol(s, &end, 10);
  if (end == s || *end != '\0' || v < lo || v > hi) return false;
  *out = static_cast<int>(v);
  return true;
}

bool ParseDouble(const char* s, double* out) {
  char* end = nullptr;
  *out = std::strtod(s, &end);
  return end != s && *end == '\0';
}

}  // namespace

int main(int argc, char** argv) {
  using namespace prism;
  synth::PresetOptions options;
  std::string preset, out, gt_cloud;
  bool list = false, list_families = false, describe = false, no_shadows = false, world_lights = false;
  std::string family = "mixed";
  std::optional<uint32_t> random_seed;
  bool frames_given = false;
  int threads = 0;
  double noise = -1, ambient = -1;
  int supersampling = 0;
  std::optional<std::array<double, 5>> distortion;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&](const char* flag) -> const char* {
      if (i + 1 >= argc) return nullptr;
      (void)flag;
      return argv[++i];
    };
    if (a == "--help" || a == "-h") {
      std::cout << kUsage;
      return 0;
    } else if (a == "--list-presets") {
      list = true;
    } else if (a == "--describe") {
      describe = true;
    } else if (a == "--no-shadows") {
      no_shadows = true;
    } else if (a == "--list-families") {
      list_families = true;
    } else if (a == "--world-lights") {
      world_lights = true;
    } else if (a == "--preset" || a == "--out" || a == "--frames" || a == "--size" || a == "--seed" ||
               a == "--threads" || a == "--mesh-dir" || a == "--noise" || a == "--ambient" || a == "--supersampling" ||
               a == "--gt-cloud" || a == "--distortion" || a == "--random" || a == "--family") {
      const char* v = value(a.c_str());
      if (!v) return Fail(a + " needs a value (see --help)");
      if (a == "--preset") preset = v;
      else if (a == "--family") family = v;
      else if (a == "--random") {
        int s;
        if (!ParseInt(v, 0, 2147483647L, &s)) return Fail("--random must be a non-negative integer seed");
        random_seed = static_cast<uint32_t>(s);
      } else if (a == "--out") out = v;
      else if (a == "--mesh-dir") options.mesh_dir = v;
      else if (a == "--gt-cloud") gt_cloud = v;
      else if (a == "--frames") {
        if (!ParseInt(v, 2, 100000, &options.frames)) return Fail("--frames must be an integer in [2, 100000]");
        frames_given = true;
      } else if (a == "--seed") {
        int s;
        if (!ParseInt(v, 0, 2147483647L, &s)) return Fail("--seed must be a non-negative integer");
        options.seed = static_cast<uint32_t>(s);
      } else if (a == "--threads") {
        if (!ParseInt(v, 1, 256, &threads)) return Fail("--threads must be an integer in [1, 256]");
      } else if (a == "--size") {
        int w = 0, h = 0;
        char extra;
        if (std::sscanf(v, "%dx%d%c", &w, &h, &extra) != 2) return Fail("--size must look like 512x512");
        options.width = w;
        options.height = h;
      } else if (a == "--noise") {
        if (!ParseDouble(v, &noise)) return Fail("--noise must be a number");
      } else if (a == "--supersampling") {
        if (!ParseInt(v, 1, 8, &supersampling)) return Fail("--supersampling must be an integer in [1, 8]");
      } else if (a == "--ambient") {
        if (!ParseDouble(v, &ambient)) return Fail("--ambient must be a number");
      } else if (a == "--distortion") {
        std::array<double, 5> d{};
        char extra;
        if (std::sscanf(v, "%lf,%lf,%lf,%lf,%lf%c", &d[0], &d[1], &d[2], &d[3], &d[4], &extra) != 5)
          return Fail("--distortion must be five comma-separated numbers K1,K2,P1,P2,K3");
        distortion = d;
      }
    } else {
      return Fail("unknown argument '" + a + "' (see --help)");
    }
  }

  if (list) {
    for (const synth::PresetInfo& p : synth::ListPresets()) {
      std::cout << p.name;
      if (describe) std::cout << "\t" << p.description;
      std::cout << "\n";
    }
    return 0;
  }
  if (list_families) {
    for (const synth::FamilyInfo& f : synth::ListFamilies()) {
      std::cout << f.name;
      if (describe) std::cout << "\t" << f.description;
      std::cout << "\n";
    }
    return 0;
  }
  if (preset.empty() == !random_seed) return Fail("one of --preset or --random is required (see --help)");
  if (world_lights && !random_seed) return Fail("--world-lights goes with --random");
  if (out.empty()) return Fail("--out is required");

  StatusOr<synth::SynthSetup> setup = NotFoundError("no scene");
  if (random_seed) {
    synth::FamilyOptions fo;
    fo.family = family;
    fo.lights_fixed_in_world = world_lights;
    fo.frames = frames_given ? options.frames : 0;
    fo.width = options.width;
    fo.height = options.height;
    fo.mesh_dir = options.mesh_dir;
    setup = synth::MakeRandomScene(*random_seed, fo);
    options.seed = *random_seed;
    preset = setup.ok() ? setup->preset : preset;
  } else {
    setup = synth::MakePreset(preset, options);
  }
  if (!setup.ok()) return Fail(setup.status().ToString());
  if (noise >= 0) setup->render.noise_sigma = noise;
  if (ambient >= 0) setup->render.ambient = ambient;
  if (supersampling > 0) setup->render.supersampling = supersampling;
  if (no_shadows) setup->render.cast_shadows = false;
  if (distortion) {
    setup->rig.camera.distortion = *distortion;
    if (Status s = setup->rig.camera.Check(); !s.ok()) return Fail("--distortion: " + s.ToString());
  }
  if (Status s = setup->render.Check(); !s.ok()) return Fail(s.ToString());

  ThreadPool pool(threads);
  StatusOr<synth::SynthesizeSummary> summary = synth::SynthesizeSequence(*setup, options.seed, out, &pool);
  if (!summary.ok()) return Fail(summary.status().ToString());
  size_t cloud_points = 0;
  if (!gt_cloud.empty()) {
    StatusOr<Sequence> seq = LoadSequence(out);
    if (!seq.ok()) return Fail(seq.status().ToString());
    StatusOr<PointCloud> cloud = synth::GroundTruthCloud(*seq, synth::GroundTruthCloudOptions());
    if (!cloud.ok()) return Fail(cloud.status().ToString());
    if (Status s = WritePointCloudPly(gt_cloud, *cloud); !s.ok()) return Fail(s.ToString());
    cloud_points = cloud->size();
  }
  std::printf(
      "{\"preset\": \"%s\", \"out\": \"%s\", \"frames\": %d, \"width\": %d, \"height\": %d, \"seed\": %u, "
      "\"threads\": %d, \"seconds\": %.3f, \"frames_per_second\": %.2f, \"path_length_m\": %.6f, "
      "\"object_radius_m\": %.6f, \"gt_cloud_points\": %zu}\n",
      preset.c_str(), out.c_str(), summary->frames, options.width, options.height, options.seed, pool.num_threads(),
      summary->seconds, summary->frames / summary->seconds, summary->path_length_m, summary->object_radius_m,
      cloud_points);
  return 0;
}
