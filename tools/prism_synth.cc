// prism-synth: renders a synthetic multispectral sequence with ground truth (core/synth).
#include <array>
#include <cstdio>
#include <iostream>
#include <optional>
#include <string>

#include "core/calibration/synthetic_captures.h"
#include "core/io/ply_io.h"
#include "core/io/sequence.h"
#include "core/synth/families.h"
#include "core/synth/ground_truth_cloud.h"
#include "core/synth/presets.h"
#include "core/synth/synthesize.h"
#include "core/util/thread_pool.h"
#include "tools/cli.h"
#include "tools/json_output.h"

namespace {

using namespace prism;

constexpr char kNotes[] = R"(Writes the TUM RGB-D layout (rgb/, depth/, normals/, mask/, groundtruth.txt, camera.yaml,
scene.yaml) and prints a JSON summary. --random draws a whole scene from a family's ranges
(docs/scene_families.md): objects, albedo, ground, lights, crosstalk, path, jitter, noise; seeds
1-999 are for tuning, 100000-100999 are held out for reporting.)";

int Fail(const std::string& message) {
  std::cerr << "prism-synth: " << message << "\n";
  return 2;
}

// The command line (flags and the values --size and --distortion hold).
struct Settings {
  synth::PresetOptions options;
  std::string preset, out, gt_cloud, charuco_board, family = "mixed", size = "512x512", distortion_text;
  bool list = false, list_families = false, describe = false, no_shadows = false, world_lights = false;
  uint32_t random_seed = 0;
  int threads = 0, supersampling = 0, light_views = 8;
  double noise = -1, ambient = -1;
  bool frames_given = false, random_scene = false;
  std::optional<std::array<double, 5>> distortion;
};

// Parses the command line into `settings`, with --size and --distortion: cli::kContinue or the exit status.
int ParseCommandLine(int argc, char** argv, Settings* settings) {
  Settings& s = *settings;
  synth::PresetOptions& options = s.options;
  CLI::App app{"", "prism-synth"};
  cli::Setup(&app, "renders a synthetic multispectral sequence of the three-light rig with ground truth",
             {"prism-synth --list-presets [--describe]", "prism-synth --preset NAME --out DIR [options]",
              "prism-synth --random SEED [--family NAME] [--world-lights] --out DIR [options]",
              "prism-synth --charuco-board DIR [--size WxH] [--seed S] [--noise SIGMA] [--distortion ...]"},
             kNotes);
  app.add_flag("--list-presets", s.list, "print one preset name per line (the first is the demo scene)");
  app.add_flag("--describe", s.describe, "with --list-presets or --list-families: a tab and a description per line");
  app.add_option("--preset", s.preset, "scene, material and trajectory (see --list-presets)")->type_name("NAME");
  CLI::Option* random = app.add_option("--random", s.random_seed, "a scene drawn at random from a family's ranges")
                            ->type_name("SEED")
                            ->default_str("")
                            ->check(CLI::Range(0u, 2147483647u));
  app.add_option("--family", s.family, "with --random: the family (see --list-families)")->type_name("NAME");
  app.add_flag("--list-families", s.list_families, "print one family name per line");
  app.add_flag("--world-lights", s.world_lights,
               "with --random: the lights stay where they were at the first frame\n"
               "(ordinary lighting; camera.yaml gives them intensity 0)");
  app.add_option("--out", s.out, "output folder (created)")->type_name("DIR");
  app.add_option("--charuco-board", s.charuco_board,
                 "render prism-calibrate's input instead: a ChArUco board (8x6 squares of 45 mm,\n"
                 "DICT_4X4_50, paper albedo 0.85) at random poses 0.3-1 m, lit by each light alone\n"
                 "and all together; the default rig's truth in DIR/truth.yaml")
      ->type_name("DIR");
  app.add_option("--light-views", s.light_views, "with --charuco-board: board poses per light folder")
      ->type_name("N")
      ->check(CLI::Range(1, 200));
  CLI::Option* frames = app.add_option("--frames", options.frames, "frames at 30 fps (with --random: drawn, 150-300)")
                            ->type_name("N")
                            ->check(CLI::Range(2, 100000));
  app.add_option("--size", s.size, "image size")->type_name("WxH");
  app.add_option("--seed", options.seed, "random seed for textures, jitter and noise")
      ->type_name("S")
      ->check(CLI::Range(0u, 2147483647u));
  app.add_option("--threads", s.threads, "worker threads, 1-256 (default: all cores)")
      ->type_name("T")
      ->default_str("")
      ->check(CLI::Range(1, 256));
  app.add_option("--mesh-dir", options.mesh_dir, "folder with bunny00.off, armadillo.off, ChineseDragon-10kv.off")
      ->type_name("DIR");
  app.add_option("--noise", s.noise, "read-noise standard deviation, 8-bit levels (default: the preset's)")
      ->type_name("SIGMA")
      ->default_str("");
  app.add_option("--ambient", s.ambient, "white ambient light in [0, 1] (default 0: dark room)")
      ->type_name("A")
      ->default_str("");
  app.add_option("--supersampling", s.supersampling,
                 "N x N rays per pixel, averaged: pixel-area integration, 1-8\n(default: the preset's)")
      ->type_name("N")
      ->default_str("")
      ->check(CLI::Range(1, 8));
  app.add_flag("--no-shadows", s.no_shadows, "disable cast shadows");
  app.add_option("--distortion", s.distortion_text,
                 "render through this lens distortion (OpenCV's radial-tangential model;\n"
                 "written to camera.yaml), e.g. -0.25,0.08,0,0,0 for a webcam's barrel")
      ->type_name("K1,K2,P1,P2,K3");
  app.add_option("--gt-cloud", s.gt_cloud,
                 "also write a dense ground-truth cloud (PLY: positions, normals, colours;\n"
                 "every 10th frame back-projected, 2 mm voxels)")
      ->type_name("FILE");
  if (const int exit = cli::Parse(&app, argc, argv); exit != cli::kContinue) return exit;
  s.frames_given = frames->count() > 0;
  s.random_scene = random->count() > 0;
  {
    char extra;
    if (std::sscanf(s.size.c_str(), "%dx%d%c", &options.width, &options.height, &extra) != 2)
      return Fail("--size must look like 512x512");
  }
  if (!s.distortion_text.empty()) {
    std::array<double, 5> d{};
    char extra;
    if (std::sscanf(s.distortion_text.c_str(), "%lf,%lf,%lf,%lf,%lf%c", &d[0], &d[1], &d[2], &d[3], &d[4], &extra) != 5)
      return Fail("--distortion must be five comma-separated numbers K1,K2,P1,P2,K3");
    s.distortion = d;
  }
  return cli::kContinue;
}

// --list-presets and --list-families: one name per line, with --describe a tab and a description.
void PrintPresets(bool describe) {
  for (const synth::PresetInfo& p : synth::ListPresets()) {
    std::cout << p.name;
    if (describe) std::cout << "\t" << p.description;
    std::cout << "\n";
  }
}

void PrintFamilies(bool describe) {
  for (const synth::FamilyInfo& f : synth::ListFamilies()) {
    std::cout << f.name;
    if (describe) std::cout << "\t" << f.description;
    std::cout << "\n";
  }
}

// --charuco-board: prism-calibrate's input rendered into the folder, and its JSON summary printed.
int RenderCharucoBoard(const Settings& s) {
  calibration::SyntheticCaptureOptions co;
  co.seed = s.options.seed;
  co.light_views = s.light_views;
  if (s.noise >= 0) co.render.noise_sigma = s.noise;
  if (s.supersampling > 0) co.render.supersampling = s.supersampling;
  RigCalibration rig = synth::MakeDefaultRig(s.options.width, s.options.height);
  if (s.distortion) rig.camera.distortion = *s.distortion;
  if (Status st = rig.camera.Check(); !st.ok()) return Fail(st.ToString());
  if (Status st = calibration::WriteSyntheticCaptures(rig, co, s.charuco_board); !st.ok()) return Fail(st.ToString());
  std::cout << JsonText({{"charuco_board", s.charuco_board},
                         {"board", co.board.Describe()},
                         {"width", s.options.width},
                         {"height", s.options.height},
                         {"intrinsics_views", co.intrinsics_views},
                         {"light_views", co.light_views},
                         {"white_albedo", co.white_albedo},
                         {"seed", co.seed}});
  return 0;
}

// The scene to render (a preset, or a random one whose seed becomes the render seed) with the command
// line's render settings over it: cli::kContinue or the exit status.
int MakeScene(Settings* settings, synth::SynthSetup* scene) {
  Settings& s = *settings;
  synth::PresetOptions& options = s.options;
  if (s.preset.empty() == !s.random_scene) return Fail("one of --preset or --random is required (see --help)");
  if (s.world_lights && !s.random_scene) return Fail("--world-lights goes with --random");
  if (s.out.empty()) return Fail("--out is required");

  StatusOr<synth::SynthSetup> setup = NotFoundError("no scene");
  if (s.random_scene) {
    synth::FamilyOptions fo;
    fo.family = s.family;
    fo.lights_fixed_in_world = s.world_lights;
    fo.frames = s.frames_given ? options.frames : 0;
    fo.width = options.width;
    fo.height = options.height;
    fo.mesh_dir = options.mesh_dir;
    setup = synth::MakeRandomScene(s.random_seed, fo);
    options.seed = s.random_seed;
    s.preset = setup.ok() ? setup->preset : s.preset;
  } else {
    setup = synth::MakePreset(s.preset, options);
  }
  if (!setup.ok()) return Fail(setup.status().ToString());
  if (s.noise >= 0) setup->render.noise_sigma = s.noise;
  if (s.ambient >= 0) setup->render.ambient = s.ambient;
  if (s.supersampling > 0) setup->render.supersampling = s.supersampling;
  if (s.no_shadows) setup->render.cast_shadows = false;
  if (s.distortion) {
    setup->rig.camera.distortion = *s.distortion;
    if (Status st = setup->rig.camera.Check(); !st.ok()) return Fail("--distortion: " + st.ToString());
  }
  if (Status st = setup->render.Check(); !st.ok()) return Fail(st.ToString());
  *scene = std::move(setup).value();
  return cli::kContinue;
}

// Renders the sequence (and --gt-cloud) and prints the JSON summary: the exit status.
int Synthesize(const Settings& s, const synth::SynthSetup& setup) {
  const synth::PresetOptions& options = s.options;
  ThreadPool pool(s.threads);
  StatusOr<synth::SynthesizeSummary> summary = synth::SynthesizeSequence(setup, options.seed, s.out, &pool);
  if (!summary.ok()) return Fail(summary.status().ToString());
  size_t cloud_points = 0;
  if (!s.gt_cloud.empty()) {
    StatusOr<Sequence> seq = LoadSequence(s.out);
    if (!seq.ok()) return Fail(seq.status().ToString());
    StatusOr<PointCloud> cloud = synth::GroundTruthCloud(*seq, synth::GroundTruthCloudOptions());
    if (!cloud.ok()) return Fail(cloud.status().ToString());
    if (Status st = WritePointCloudPly(s.gt_cloud, *cloud); !st.ok()) return Fail(st.ToString());
    cloud_points = cloud->size();
  }
  const Json json = {{"preset", s.preset},
                     {"out", s.out},
                     {"frames", summary->frames},
                     {"width", options.width},
                     {"height", options.height},
                     {"seed", options.seed},
                     {"threads", pool.num_threads()},
                     {"seconds", summary->seconds},
                     {"frames_per_second", summary->frames / summary->seconds},
                     {"path_length_m", summary->path_length_m},
                     {"object_radius_m", summary->object_radius_m},
                     {"gt_cloud_points", cloud_points}};
  std::cout << JsonText(json);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Settings settings;
  if (const int exit = ParseCommandLine(argc, argv, &settings); exit != cli::kContinue) return exit;
  if (settings.list) {
    PrintPresets(settings.describe);
    return 0;
  }
  if (settings.list_families) {
    PrintFamilies(settings.describe);
    return 0;
  }
  if (!settings.charuco_board.empty()) return RenderCharucoBoard(settings);
  synth::SynthSetup setup;
  if (const int exit = MakeScene(&settings, &setup); exit != cli::kContinue) return exit;
  return Synthesize(settings, setup);
}
