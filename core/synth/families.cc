#include "core/synth/families.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <random>
#include <sstream>

#include "core/io/ply_io.h"
#include "core/synth/shapes.h"

namespace prism::synth {
namespace {

constexpr double kDeg = M_PI / 180.0;

// Uniform, log-uniform and Bernoulli draws from one generator.
class Draw {
 public:
  explicit Draw(uint32_t seed) : rng_(seed * 2654435761u + 12345u) {}
  double Uniform(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng_); }
  double LogUniform(double lo, double hi) { return std::exp(Uniform(std::log(lo), std::log(hi))); }
  int Int(int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(rng_); }  // inclusive
  bool Chance(double p) { return Uniform(0, 1) < p; }
  double Gauss() { return std::normal_distribution<double>(0, 1)(rng_); }
  uint32_t Seed() { return static_cast<uint32_t>(rng_()); }
  template <typename T>
  const T& Pick(const std::vector<T>& v) {
    return v[static_cast<size_t>(Int(0, static_cast<int>(v.size()) - 1))];
  }

 private:
  std::mt19937 rng_;
};

Eigen::Vector3d RandomColour(Draw& d, double min_value = 0.25) {
  // Saturated or pale, never black: each band in [min_value, 0.9].
  return Eigen::Vector3d(d.Uniform(min_value, 0.9), d.Uniform(min_value, 0.9), d.Uniform(min_value, 0.9));
}

AlbedoOptions RandomAlbedo(Draw& d, double object_size_m, const std::string& kind) {
  AlbedoOptions a;
  a.seed = d.Seed();
  if (kind == "uniform") {
    a.kind = AlbedoKind::kUniform;
    a.base = RandomColour(d, 0.3);
  } else if (kind == "textured") {
    a.kind = AlbedoKind::kTextured;
    a.base = RandomColour(d, 0.35);
    a.feature_size_m = object_size_m * d.LogUniform(0.05, 0.25);
    a.contrast = d.Uniform(0.2, 0.7);
    a.octaves = d.Int(2, 4);
  } else {
    a.kind = AlbedoKind::kMultiColor;
    const int colours = d.Int(2, 6);
    for (int i = 0; i < colours; ++i) a.palette.push_back(RandomColour(d, 0.2));
    a.feature_size_m = object_size_m * d.LogUniform(0.15, 0.5);
  }
  return a;
}

struct Placement {
  Eigen::Vector2d xy;
  double size_m;
};

// One object of `kind` with largest extent size_m, standing on the ground at xy.
Status AddObject(Draw& d, const std::string& kind, const Placement& at, const AlbedoOptions& albedo,
                 const std::string& mesh_dir, Scene* scene) {
  SceneObject o;
  o.albedo = albedo;
  o.specular = d.Chance(0.2) ? d.Uniform(0.05, 0.2) : 0.0;
  const double yaw = d.Uniform(0, 2 * M_PI);
  const double s = at.size_m;
  if (kind == "sphere") {
    o.shape = ShapeKind::kSphere;
    o.radius_m = 0.5 * s;
    o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), 0.5 * s);
    o.world_from_object.rotation = Eigen::AngleAxisd(yaw, Eigen::Vector3d(0.2, 0.4, 1).normalized());
  } else if (kind == "box") {
    o.shape = ShapeKind::kBox;
    o.half_extents_m = 0.5 * s * Eigen::Vector3d(d.Uniform(0.4, 1), d.Uniform(0.4, 1), d.Uniform(0.3, 1));
    o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), o.half_extents_m.z());
    o.world_from_object.rotation = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ());
  } else {
    TriangleMesh mesh;
    if (kind == "ellipsoid") {
      const double a = 0.5 * s, b = a * d.Uniform(0.45, 1), c = a * d.Uniform(0.45, 1);
      mesh = MakeEllipsoid(a, b, c, 96);
      o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), c);
    } else if (kind == "torus") {
      const double r = 0.5 * s * d.Uniform(0.2, 0.4);
      mesh = MakeTorus(0.5 * s - r, r, 160, 64);
      o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), r);
    } else if (kind == "relief") {
      mesh = MakeRelief(0.7 * s, 0.25 * s, d.Int(4, 9), 200, d.Seed());
      o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), 0);
    } else {
      static const std::vector<std::pair<std::string, std::string>> kMeshes = {
          {"bunny", "bunny00.off"}, {"dragon", "ChineseDragon-10kv.off"}, {"armadillo", "armadillo.off"}};
      std::string file;
      for (const auto& [name, f] : kMeshes)
        if (name == kind) file = f;
      if (file.empty()) return InvalidArgumentError("unknown object kind '" + kind + "'");
      StatusOr<TriangleMesh> loaded = NotFoundError("mesh '" + file + "' not found");
      for (const std::string& dir : MeshSearchPath(mesh_dir)) {
        if (!std::filesystem::exists(dir + "/" + file)) continue;
        loaded = ReadTriangleMesh(dir + "/" + file);
        break;
      }
      if (!loaded.ok())
        return NotFoundError("mesh '" + file + "' not found (Debian's libcgal-demo): " + loaded.status().message());
      mesh = std::move(loaded).value();
      mesh.ComputeVertexNormals();
      NormaliseMesh(1, 1, s, &mesh);
      o.world_from_object.translation = Eigen::Vector3d(at.xy.x(), at.xy.y(), 0);
    }
    o.shape = ShapeKind::kMesh;
    o.mesh = std::make_shared<MeshBvh>(std::move(mesh));
    o.world_from_object.rotation = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ());
  }
  scene->AddObject(o);
  return Status::Ok();
}

// Three point lights 0.08-0.3 m from the lens at well-separated angles around the optical axis, with
// intensities that give the object a usable exposure at the working distance.
void RandomRig(Draw& d, int width, int height, double distance_m, RigCalibration* rig) {
  rig->camera = PinholeCamera::FromFov(width, height, d.Uniform(45, 65));
  const double first = d.Uniform(0, 2 * M_PI);
  const double names_angle[3] = {first, first + d.Uniform(100, 140) * kDeg, first + d.Uniform(220, 260) * kDeg};
  const char* names[3] = {"red", "green", "blue"};
  for (int l = 0; l < 3; ++l) {
    const double r = d.Uniform(0.08, 0.3), a = names_angle[l];
    Light& light = rig->lights[l];
    light.name = names[l];
    light.type = LightType::kPoint;
    light.position_in_camera = Eigen::Vector3d(r * std::cos(a), r * std::sin(a), d.Uniform(-0.05, 0.02));
    light.color = Eigen::Vector3d::Zero();
    light.color[l] = 1.0;
    // Irradiance at the object intensity / d^2 of 0.3-0.8 (the presets give about 0.55).
    light.intensity = d.Uniform(0.3, 0.8) * distance_m * distance_m;
  }
  rig->crosstalk = Eigen::Matrix3d::Identity();
  for (int c = 0; c < 3; ++c)
    for (int l = 0; l < 3; ++l)
      if (c != l) rig->crosstalk(c, l) = d.Uniform(0.0, 0.2);
}

enum class PathKind { kOrbit, kArc, kForward, kBackward, kSideways, kWander };
const char* PathName(PathKind k) {
  switch (k) {
    case PathKind::kOrbit:
      return "orbit";
    case PathKind::kArc:
      return "arc";
    case PathKind::kForward:
      return "forward";
    case PathKind::kBackward:
      return "backward";
    case PathKind::kSideways:
      return "sideways";
    case PathKind::kWander:
      return "wander";
  }
  return "?";
}

struct PathDraw {
  PathKind kind = PathKind::kOrbit;
  double distance_m = 1;      // from the target at the start
  double elevation_deg = 25;  // of the viewing direction above the ground
  double rotation_deg_per_frame = 1;
  double speed_fraction = 0.01;  // translation per frame, fraction of the distance
  double jitter_position_m = 0, jitter_rotation_deg = 0;
};

// Camera poses looking at `target` (with per-frame jitter), world z up.
Trajectory MakePath(Draw& d, const PathDraw& p, const Eigen::Vector3d& target, int frames, double fps) {
  const double azimuth0 = d.Uniform(0, 2 * M_PI);
  const double direction = d.Chance(0.5) ? 1.0 : -1.0;
  const double el = p.elevation_deg * kDeg;
  auto eye_at = [&](double distance, double azimuth, double elevation) -> Eigen::Vector3d {
    return target + distance * Eigen::Vector3d(std::cos(elevation) * std::cos(azimuth),
                                               std::cos(elevation) * std::sin(azimuth), std::sin(elevation));
  };
  // Hand-held wander: a smooth random walk of the eye and of the look-at point.
  std::vector<Eigen::Vector3d> wander_eye, wander_look;
  if (p.kind == PathKind::kWander) {
    Eigen::Vector3d v = Eigen::Vector3d::Zero(), e = Eigen::Vector3d::Zero(), w = Eigen::Vector3d::Zero(),
                    l = Eigen::Vector3d::Zero();
    const double step = p.speed_fraction * p.distance_m;
    for (int i = 0; i < frames; ++i) {
      v = 0.9 * v + 0.1 * step * Eigen::Vector3d(d.Gauss(), d.Gauss(), 0.5 * d.Gauss());
      if (v.norm() > step) v *= step / v.norm();
      e += v;
      // Stay within 40% of the distance from the start.
      if (e.norm() > 0.4 * p.distance_m) e *= 0.4 * p.distance_m / e.norm();
      w = 0.95 * w + 0.05 * 0.1 * p.distance_m * Eigen::Vector3d(d.Gauss(), d.Gauss(), 0.3 * d.Gauss());
      l += w * 0.05;
      if (l.norm() > 0.15 * p.distance_m) l *= 0.15 * p.distance_m / l.norm();
      wander_eye.push_back(e);
      wander_look.push_back(l);
    }
  }
  Trajectory traj;
  const double total_rotation = p.rotation_deg_per_frame * (frames - 1) * kDeg;
  for (int i = 0; i < frames; ++i) {
    const double f = static_cast<double>(i);
    Eigen::Vector3d eye = target, look = target;
    switch (p.kind) {
      case PathKind::kOrbit:
      case PathKind::kArc:
        eye = eye_at(p.distance_m, azimuth0 + direction * p.rotation_deg_per_frame * f * kDeg, el);
        break;
      case PathKind::kForward:
      case PathKind::kBackward: {
        // Along the line of sight, from 1 to 0.55 of the distance (or back), with a slow turn.
        const double total = std::min(0.45, p.speed_fraction * (frames - 1));
        const double s = p.kind == PathKind::kForward ? f / (frames - 1) : 1 - f / (frames - 1);
        eye = eye_at(p.distance_m * (1 - total * s), azimuth0 + direction * 0.25 * total_rotation * s, el);
        break;
      }
      case PathKind::kSideways: {
        // Translation across the view at a constant viewing direction, within the object's reach.
        const Eigen::Vector3d start = eye_at(p.distance_m, azimuth0, el);
        const Eigen::Vector3d forward = (target - start).normalized();
        const Eigen::Vector3d side = forward.cross(Eigen::Vector3d::UnitZ()).normalized();
        const double total = std::min(0.5, p.speed_fraction * (frames - 1)) * p.distance_m;
        const double s = f / (frames - 1) - 0.5;
        eye = start + direction * total * s * side;
        look = eye + forward * p.distance_m;
        break;
      }
      case PathKind::kWander:
        eye = eye_at(p.distance_m, azimuth0, el) + wander_eye[i];
        look = target + wander_look[i];
        break;
    }
    // Per-frame jitter (hand shake): independent on every frame.
    eye += p.jitter_position_m * Eigen::Vector3d(d.Gauss(), d.Gauss(), d.Gauss()) / std::sqrt(3.0);
    Rigid3d pose = LookAt(eye, look, Eigen::Vector3d::UnitZ());
    const Eigen::Vector3d axis(d.Gauss(), d.Gauss(), d.Gauss());
    const double angle = p.jitter_rotation_deg * kDeg * std::abs(d.Gauss()) / 1.25;
    if (axis.norm() > 1e-9)
      pose.rotation = pose.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(angle, axis.normalized()));
    pose.rotation.normalize();
    traj.push_back({std::round((1000.0 + f / fps) * 1e6) / 1e6, pose});
  }
  return traj;
}

struct FamilyDef {
  FamilyInfo info;
  std::vector<std::string> objects;  // kinds drawn from
  std::vector<std::string> albedos;  // uniform, textured, multicolor
  std::vector<PathKind> paths;       // drawn from
  double min_distance_m, max_distance_m;
  int min_objects, max_objects;
  double min_rotation_deg, max_rotation_deg;  // per frame (orbits and arcs)
  double max_jitter_position_m, max_jitter_rotation_deg;
  bool extras;  // ambient light, motion blur, specularity, noise ranges
};

const std::vector<FamilyDef>& Families() {
  static const std::vector<FamilyDef> defs = {
      {{"mixed",
        "one to four objects (primitives and the CGAL meshes) on a low- or high-texture ground, uniform, "
        "textured or multi-coloured, 0.3-3 m away; orbits, arcs, forward, backward, sideways and hand-held "
        "paths up to 3% of the distance and 3 deg per frame with per-frame jitter; random lights, crosstalk, "
        "noise, and sometimes ambient light and motion blur"},
       {"sphere", "ellipsoid", "box", "torus", "relief", "bunny", "dragon", "armadillo"},
       {"uniform", "textured", "multicolor"},
       {PathKind::kOrbit, PathKind::kArc, PathKind::kForward, PathKind::kBackward, PathKind::kSideways,
        PathKind::kWander},
       0.3,
       3.0,
       1,
       4,
       0.3,
       3.0,
       0.015,
       1.0,
       true},
      {{"orbits",
        "untextured spheres and ellipsoids, one- or multi-coloured, on a textured ground 1.5-2.2 m away; "
        "orbits and arcs of 1.3-2.2 deg per frame with about 1 cm and 0.5 deg of per-frame jitter"},
       {"sphere", "ellipsoid"},
       {"uniform", "multicolor"},
       {PathKind::kOrbit, PathKind::kArc},
       1.5,
       2.2,
       1,
       2,
       1.3,
       2.2,
       0.012,
       0.6,
       false},
  };
  return defs;
}

}  // namespace

std::vector<FamilyInfo> ListFamilies() {
  std::vector<FamilyInfo> out;
  for (const FamilyDef& f : Families()) out.push_back(f.info);
  return out;
}

TriangleMesh MakeEllipsoid(double a, double b, double c, int n) {
  TriangleMesh m;
  const int rings = n / 2;
  for (int i = 0; i <= rings; ++i) {
    const double theta = M_PI * i / rings;  // from the +z pole
    for (int j = 0; j < n; ++j) {
      const double phi = 2 * M_PI * j / n;
      const Eigen::Vector3d u(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta));
      m.vertices.emplace_back(a * u.x(), b * u.y(), c * u.z());
      m.vertex_normals.push_back(Eigen::Vector3d(u.x() / a, u.y() / b, u.z() / c).normalized());
    }
  }
  for (int i = 0; i < rings; ++i)
    for (int j = 0; j < n; ++j) {
      const int p = i * n + j, q = i * n + (j + 1) % n, r = (i + 1) * n + (j + 1) % n, s = (i + 1) * n + j;
      if (i > 0) m.faces.emplace_back(p, s, q);
      if (i + 1 < rings) m.faces.emplace_back(q, s, r);
    }
  return m;
}

StatusOr<SynthSetup> MakeRandomScene(uint32_t seed, const FamilyOptions& options) {
  const FamilyDef* def = nullptr;
  for (const FamilyDef& f : Families())
    if (f.info.name == options.family) def = &f;
  if (!def) {
    std::string names;
    for (const FamilyDef& f : Families()) names += (names.empty() ? "" : ", ") + f.info.name;
    return NotFoundError("unknown scene family '" + options.family + "'; known: " + names);
  }
  PresetOptions size;
  size.width = options.width;
  size.height = options.height;
  size.frames = std::max(2, options.frames);
  PRISM_RETURN_IF_ERROR(size.Check());
  Draw d(seed);
  SynthSetup setup;
  setup.preset = "random-" + def->info.name;
  setup.description = def->info.description;

  // Working distance, the objects' scale and placement.
  PathDraw path;
  path.distance_m = d.LogUniform(def->min_distance_m, def->max_distance_m);
  const int count = d.Int(def->min_objects, def->max_objects);
  // The group spans 25-55% of the view's width at the working distance.
  const double view_width = 2 * path.distance_m * std::tan(25 * kDeg);
  const double group = view_width * d.Uniform(0.25, 0.55);
  std::vector<Placement> places;
  for (int i = 0; i < count; ++i) {
    Placement p;
    p.size_m = group * (count == 1 ? 1.0 : d.Uniform(0.35, 0.6));
    const double r = count == 1 ? 0.0 : 0.5 * group * d.Uniform(0.3, 1.0);
    const double a = d.Uniform(0, 2 * M_PI);
    p.xy = Eigen::Vector2d(r * std::cos(a), r * std::sin(a));
    places.push_back(p);
  }
  // The ground: low to high texture, scaled with the distance.
  SceneObject ground;
  ground.shape = ShapeKind::kPlane;
  ground.half_extents_m = Eigen::Vector3d(6 * path.distance_m, 6 * path.distance_m, 0);
  ground.is_object = false;
  ground.albedo.kind = AlbedoKind::kTextured;
  ground.albedo.base = RandomColour(d, 0.35);
  ground.albedo.contrast = d.Chance(0.3) ? d.Uniform(0.05, 0.2) : d.Uniform(0.3, 0.8);
  ground.albedo.feature_size_m = path.distance_m * d.LogUniform(0.01, 0.06);
  ground.albedo.octaves = d.Int(2, 4);
  ground.albedo.seed = d.Seed();
  setup.scene.AddObject(ground);
  std::ostringstream objects;
  for (const Placement& p : places) {
    const std::string kind = d.Pick(def->objects);
    const std::string albedo_kind = d.Pick(def->albedos);
    PRISM_RETURN_IF_ERROR(
        AddObject(d, kind, p, RandomAlbedo(d, p.size_m, albedo_kind), options.mesh_dir, &setup.scene));
    objects << (objects.str().empty() ? "" : " ") << kind << "/" << albedo_kind;
  }
  Eigen::Vector3d centre;
  double radius = 0;
  setup.scene.ObjectBounds(&centre, &radius);

  // The path: its kind, length, speed, rotation and jitter.
  path.kind = d.Pick(def->paths);
  path.elevation_deg = d.Uniform(12, 45);
  const int frames = options.frames > 0 ? options.frames : d.Int(150, 300);
  // Orbits turn 200-400 deg in all, arcs 40-180 deg, within the family's rate; a mixed scene's camera
  // moves at most 3% of the distance per frame (an orbit's translation is its turn times the radius).
  const double turn_deg = path.kind == PathKind::kOrbit ? d.Uniform(200, 400) : d.Uniform(40, 180);
  path.rotation_deg_per_frame = std::clamp(turn_deg / frames, def->min_rotation_deg, def->max_rotation_deg);
  if (def->extras && (path.kind == PathKind::kOrbit || path.kind == PathKind::kArc))
    path.rotation_deg_per_frame =
        std::min(path.rotation_deg_per_frame, 0.03 / std::cos(path.elevation_deg * kDeg) / kDeg);
  if (path.kind != PathKind::kOrbit && path.kind != PathKind::kArc)
    path.rotation_deg_per_frame = d.Uniform(def->min_rotation_deg, def->max_rotation_deg);
  path.speed_fraction = d.Uniform(0.003, 0.03);
  path.jitter_position_m = d.Uniform(0, std::min(def->max_jitter_position_m, 0.01 * path.distance_m));
  path.jitter_rotation_deg = d.Uniform(0, def->max_jitter_rotation_deg);
  // The lights are set for the closest approach (a forward path ends at 55% of the distance).
  const bool approaches = path.kind == PathKind::kForward || path.kind == PathKind::kBackward;
  RandomRig(d, options.width, options.height, path.distance_m * (approaches ? 0.7 : 1.0), &setup.rig);
  setup.trajectory.fps = 30;
  setup.trajectory.frames = frames;
  setup.trajectory.seed = seed;
  setup.poses = MakePath(d, path, centre, frames, setup.trajectory.fps);

  // Sensor and light extras.
  setup.render.noise_sigma = def->extras ? d.Uniform(0.5, 2.5) : 1.0;
  if (def->extras && d.Chance(0.3)) setup.render.ambient = d.Uniform(0.01, 0.08);
  if (def->extras && d.Chance(0.3)) {
    setup.blur_samples = 4;
    setup.exposure = d.Uniform(0.2, 0.6);
  }
  if (!def->extras) setup.render.specular_scale = 0;
  setup.lights_fixed_in_world = options.lights_fixed_in_world;

  setup.notes = {{"family", def->info.name},
                 {"objects", objects.str()},
                 {"path", PathName(path.kind)},
                 {"distance_m", std::to_string(path.distance_m)},
                 {"rotation_deg_per_frame", std::to_string(path.rotation_deg_per_frame)},
                 {"speed_fraction_per_frame", std::to_string(path.speed_fraction)},
                 {"jitter_position_m", std::to_string(path.jitter_position_m)},
                 {"jitter_rotation_deg", std::to_string(path.jitter_rotation_deg)},
                 {"exposure", std::to_string(setup.exposure)},
                 {"lights_fixed_in_world", options.lights_fixed_in_world ? "1" : "0"}};
  PRISM_RETURN_IF_ERROR(setup.render.Check());
  PRISM_RETURN_IF_ERROR(setup.rig.Check());
  return setup;
}

}  // namespace prism::synth
