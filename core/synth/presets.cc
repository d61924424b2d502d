#include "core/synth/presets.h"

#include <cstdlib>
#include <filesystem>
#include <functional>
#include <sstream>

#include "core/io/ply_io.h"
#include "core/synth/shapes.h"

#ifndef PRISM_MESH_BUILD_DIR
#define PRISM_MESH_BUILD_DIR ""
#endif
#ifndef PRISM_MESH_INSTALL_DIR
#define PRISM_MESH_INSTALL_DIR ""
#endif

namespace prism::synth {
namespace {

// Albedo per light band. Values are what a white light would give in each band.
const std::vector<Eigen::Vector3d>& Palette() {
  static const std::vector<Eigen::Vector3d> p = {{0.85, 0.25, 0.20}, {0.25, 0.75, 0.30}, {0.20, 0.35, 0.85},
                                                 {0.85, 0.80, 0.25}, {0.80, 0.30, 0.75}, {0.30, 0.80, 0.80},
                                                 {0.80, 0.80, 0.80}};
  return p;
}

AlbedoOptions Uniform() {
  AlbedoOptions a;
  a.kind = AlbedoKind::kUniform;
  a.base = Eigen::Vector3d(0.8, 0.78, 0.75);
  return a;
}

AlbedoOptions Textured(uint32_t seed) {
  AlbedoOptions a;
  a.kind = AlbedoKind::kTextured;
  a.base = Eigen::Vector3d(0.85, 0.75, 0.65);
  a.feature_size_m = 0.02;
  a.contrast = 0.5;
  a.octaves = 3;
  a.seed = seed;
  return a;
}

AlbedoOptions MultiColor(uint32_t seed) {
  AlbedoOptions a;
  a.kind = AlbedoKind::kMultiColor;
  a.palette = Palette();
  a.feature_size_m = 0.05;
  a.seed = seed;
  return a;
}

SceneObject Ground(uint32_t seed) {
  SceneObject g;
  g.shape = ShapeKind::kPlane;
  g.half_extents_m = Eigen::Vector3d(1.5, 1.5, 0);
  g.is_object = false;
  g.albedo.kind = AlbedoKind::kTextured;
  g.albedo.base = Eigen::Vector3d(0.7, 0.65, 0.6);
  g.albedo.feature_size_m = 0.025;
  g.albedo.contrast = 0.75;
  g.albedo.octaves = 4;
  g.albedo.seed = seed * 31u + 7u;
  return g;
}

struct Ctx {
  const PresetOptions& options;
  uint32_t seed;
};

using SceneBuilder = std::function<Status(const Ctx&, Scene*)>;

Status AddSphere(const Ctx& ctx, const AlbedoOptions& albedo, Scene* scene, double specular = 0.0) {
  SceneObject s;
  s.shape = ShapeKind::kSphere;
  s.radius_m = 0.1;
  s.world_from_object.translation = Eigen::Vector3d(0, 0, 0.1);
  s.world_from_object.rotation = Eigen::AngleAxisd(0.3 + ctx.seed * 0.1, Eigen::Vector3d(0.2, 0.4, 1).normalized());
  s.albedo = albedo;
  s.specular = specular;
  scene->AddObject(s);
  return Status::Ok();
}

StatusOr<TriangleMesh> LoadNamedMesh(const std::string& file, const std::string& mesh_dir) {
  for (const std::string& dir : MeshSearchPath(mesh_dir)) {
    const std::string path = dir + "/" + file;
    if (std::filesystem::exists(path)) return ReadTriangleMesh(path);
  }
  std::ostringstream msg;
  msg << "mesh '" << file << "' not found; install Debian's libcgal-demo (its data.tar.gz holds "
      << "data/meshes/" << file << ") and re-run cmake, or pass --mesh-dir. Searched:";
  for (const std::string& dir : MeshSearchPath(mesh_dir)) msg << " '" << dir << "'";
  return NotFoundError(msg.str());
}

Status AddMesh(const Ctx& ctx, const std::string& file, int up_axis, double up_sign, double yaw_deg,
               const AlbedoOptions& albedo, Scene* scene, double size_m = 0.2) {
  PRISM_ASSIGN_OR_RETURN(TriangleMesh mesh, LoadNamedMesh(file, ctx.options.mesh_dir));
  mesh.ComputeVertexNormals();
  NormaliseMesh(up_axis, up_sign, size_m, &mesh);
  SceneObject o;
  o.shape = ShapeKind::kMesh;
  o.mesh = std::make_shared<MeshBvh>(std::move(mesh));
  o.world_from_object.rotation = Eigen::AngleAxisd(yaw_deg * M_PI / 180, Eigen::Vector3d::UnitZ());
  o.albedo = albedo;
  scene->AddObject(o);
  return Status::Ok();
}

struct PresetDef {
  PresetInfo info;
  SceneBuilder build;
  TrajectoryStart start;
  double target_z;
  double arc_deg;
  std::function<void(SynthSetup*)> tweak;  // optional
};

const std::vector<PresetDef>& Definitions() {
  static const std::vector<PresetDef> defs = [] {
    std::vector<PresetDef> d;
    d.push_back({{"bunny-multicolor-forward", "Stanford bunny, multi-coloured regions, forward start (the demo)"},
                 [](const Ctx& c, Scene* s) { return AddMesh(c, "bunny00.off", 1, 1, 200, MultiColor(c.seed), s); },
                 TrajectoryStart::kForward,
                 0.08,
                 120,
                 nullptr});
    d.push_back({{"bunny-multicolor-orbit",
                  "Stanford bunny, multi-coloured regions, forward start, then a full orbit and 40 deg beyond "
                  "(returns to where it started: loop closure; use >= 450 frames)"},
                 [](const Ctx& c, Scene* s) { return AddMesh(c, "bunny00.off", 1, 1, 200, MultiColor(c.seed), s); },
                 TrajectoryStart::kForward,
                 0.08,
                 400,
                 nullptr});
    d.push_back({{"sphere-uniform-sideways", "uniform-albedo sphere, sideways start"},
                 [](const Ctx& c, Scene* s) { return AddSphere(c, Uniform(), s); },
                 TrajectoryStart::kSideways,
                 0.1,
                 120,
                 nullptr});
    d.push_back({{"sphere-uniform-forward", "uniform-albedo sphere, forward start"},
                 [](const Ctx& c, Scene* s) { return AddSphere(c, Uniform(), s); },
                 TrajectoryStart::kForward,
                 0.1,
                 120,
                 nullptr});
    d.push_back({{"sphere-multicolor-sideways", "multi-coloured sphere, sideways start"},
                 [](const Ctx& c, Scene* s) { return AddSphere(c, MultiColor(c.seed), s); },
                 TrajectoryStart::kSideways,
                 0.1,
                 120,
                 nullptr});
    d.push_back({{"torus-textured-forward", "textured torus lying on the ground, forward start"},
                 [](const Ctx& c, Scene* s) {
                   SceneObject o;
                   o.shape = ShapeKind::kMesh;
                   o.mesh = std::make_shared<MeshBvh>(MakeTorus(0.08, 0.035, 160, 64));
                   o.world_from_object.translation = Eigen::Vector3d(0, 0, 0.035);
                   o.albedo = Textured(c.seed);
                   s->AddObject(o);
                   return Status::Ok();
                 },
                 TrajectoryStart::kForward,
                 0.03,
                 120,
                 nullptr});
    d.push_back({{"relief-uniform-sideways", "uniform-albedo bumpy relief on the ground, sideways start"},
                 [](const Ctx& c, Scene* s) {
                   SceneObject o;
                   o.shape = ShapeKind::kMesh;
                   o.mesh = std::make_shared<MeshBvh>(MakeRelief(0.14, 0.05, 7, 200, c.seed));
                   o.albedo = Uniform();
                   s->AddObject(o);
                   return Status::Ok();
                 },
                 TrajectoryStart::kSideways,
                 0.02,
                 120,
                 nullptr});
    d.push_back({{"boxes-multicolor-forward", "three multi-coloured boxes, forward start"},
                 [](const Ctx& c, Scene* s) {
                   const double sizes[3][3] = {{0.06, 0.05, 0.05}, {0.04, 0.07, 0.035}, {0.035, 0.035, 0.08}};
                   const double pos[3][2] = {{-0.08, 0.02}, {0.07, -0.05}, {0.04, 0.09}};
                   for (int i = 0; i < 3; ++i) {
                     SceneObject o;
                     o.shape = ShapeKind::kBox;
                     o.half_extents_m = Eigen::Vector3d(sizes[i][0], sizes[i][1], sizes[i][2]);
                     o.world_from_object.translation = Eigen::Vector3d(pos[i][0], pos[i][1], sizes[i][2]);
                     o.world_from_object.rotation = Eigen::AngleAxisd(0.4 + 0.7 * i, Eigen::Vector3d::UnitZ());
                     o.albedo = MultiColor(c.seed + i);
                     s->AddObject(o);
                   }
                   return Status::Ok();
                 },
                 TrajectoryStart::kForward,
                 0.05,
                 120,
                 nullptr});
    d.push_back({{"bunny-uniform-sideways", "Stanford bunny, uniform albedo, sideways start"},
                 [](const Ctx& c, Scene* s) { return AddMesh(c, "bunny00.off", 1, 1, 200, Uniform(), s); },
                 TrajectoryStart::kSideways,
                 0.08,
                 120,
                 nullptr});
    d.push_back(
        {{"dragon-multicolor-sideways", "Chinese dragon (10k vertices), multi-coloured, sideways start"},
         [](const Ctx& c, Scene* s) { return AddMesh(c, "ChineseDragon-10kv.off", 1, 1, 90, MultiColor(c.seed), s); },
         TrajectoryStart::kSideways,
         0.08,
         120,
         nullptr});
    d.push_back(
        {{"armadillo-textured-forward", "armadillo, textured albedo, forward start"},
         [](const Ctx& c, Scene* s) { return AddMesh(c, "armadillo.off", 1, 1, 180, Textured(c.seed), s, 0.25); },
         TrajectoryStart::kForward,
         0.08,
         120,
         nullptr});
    d.push_back({{"sphere-robust-sideways",
                  "multi-coloured sphere with ambient light, mild specularity and more noise (robustness)"},
                 [](const Ctx& c, Scene* s) { return AddSphere(c, MultiColor(c.seed), s, 0.15); },
                 TrajectoryStart::kSideways,
                 0.1,
                 120,
                 [](SynthSetup* setup) {
                   setup->render.ambient = 0.05;
                   setup->render.noise_sigma = 2.0;
                 }});
    return d;
  }();
  return defs;
}

}  // namespace

Status PresetOptions::Check() const {
  std::ostringstream e;
  if (width < 16 || width > 4096 || height < 16 || height > 4096)
    e << "PresetOptions size = " << width << "x" << height << "; violated: each in [16, 4096]";
  else if (frames < 2 || frames > 100000) e << "PresetOptions.frames = " << frames << "; violated: in [2, 100000]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

std::vector<std::string> MeshSearchPath(const std::string& mesh_dir) {
  std::vector<std::string> path;
  if (!mesh_dir.empty()) path.push_back(mesh_dir);
  if (const char* env = std::getenv("PRISM_MESH_DIR"); env && *env) path.push_back(env);
  if (*PRISM_MESH_BUILD_DIR) path.push_back(PRISM_MESH_BUILD_DIR);
  if (*PRISM_MESH_INSTALL_DIR) path.push_back(PRISM_MESH_INSTALL_DIR);
  path.push_back("/usr/local/share/prism/meshes");
  path.push_back("/usr/share/prism/meshes");
  return path;
}

RigCalibration MakeDefaultRig(int width, int height) {
  RigCalibration rig;
  rig.camera = PinholeCamera::FromFov(width, height, 50.0);
  // Camera frame: x right, y down, z forward. Red left, green right (both slightly below), blue above.
  rig.lights[0] = {"red", LightType::kPoint, {-0.20, 0.08, 0.0}, {0, 0, -1}, {1, 0, 0}, 0.12};
  rig.lights[1] = {"green", LightType::kPoint, {0.20, 0.08, 0.0}, {0, 0, -1}, {0, 1, 0}, 0.10};
  rig.lights[2] = {"blue", LightType::kPoint, {0.0, -0.20, 0.0}, {0, 0, -1}, {0, 0, 1}, 0.13};
  // Response of camera channel (row) to light (column): the sensor's dyes overlap.
  rig.crosstalk << 1.00, 0.12, 0.02, 0.10, 1.00, 0.14, 0.03, 0.12, 1.00;
  return rig;
}

std::vector<PresetInfo> ListPresets() {
  std::vector<PresetInfo> out;
  for (const PresetDef& d : Definitions()) out.push_back(d.info);
  return out;
}

StatusOr<SynthSetup> MakePreset(const std::string& name, const PresetOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  const PresetDef* def = nullptr;
  for (const PresetDef& d : Definitions())
    if (d.info.name == name) def = &d;
  if (!def) {
    std::string names;
    for (const PresetDef& d : Definitions()) names += (names.empty() ? "" : ", ") + d.info.name;
    return NotFoundError("unknown preset '" + name + "'; known: " + names);
  }
  SynthSetup setup;
  setup.preset = name;
  setup.description = def->info.description;
  setup.rig = MakeDefaultRig(options.width, options.height);
  setup.scene.AddObject(Ground(options.seed));
  PRISM_RETURN_IF_ERROR(def->build(Ctx{options, options.seed}, &setup.scene));
  TrajectoryOptions& t = setup.trajectory;
  t.target = Eigen::Vector3d(0, 0, def->target_z);
  t.radius_m = 0.4;
  t.height_m = 0.25;
  t.start = def->start;
  t.arc_deg = def->arc_deg;
  t.frames = options.frames;
  t.seed = options.seed;
  if (def->tweak) def->tweak(&setup);
  PRISM_RETURN_IF_ERROR(setup.trajectory.Check());
  PRISM_RETURN_IF_ERROR(setup.render.Check());
  PRISM_RETURN_IF_ERROR(setup.rig.Check());
  return setup;
}

}  // namespace prism::synth
