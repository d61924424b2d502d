// Named synthetic sequences used by tests, benchmarks and the demo. Every preset is a dark room
// (only the rig's three lights, as in the paper's experiments) unless its name says otherwise.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "core/io/calibration_io.h"
#include "core/synth/renderer.h"
#include "core/synth/scene.h"
#include "core/synth/trajectory.h"
#include "core/util/status.h"

namespace prism::synth {

struct PresetInfo {
  std::string name;
  std::string description;
};

struct PresetOptions {
  int width = 512;   // pixels, in [16, 4096]
  int height = 512;  // pixels, in [16, 4096]
  int frames = 300;  // >= 2
  uint32_t seed = 1;
  // Folder holding bunny00.off, armadillo.off, ChineseDragon-10kv.off (Debian libcgal-demo); empty =
  // $PRISM_MESH_DIR, then the build tree's copy, then the installed copy.
  std::string mesh_dir;

  Status Check() const;
};

struct SynthSetup {
  std::string preset;
  std::string description;
  Scene scene;
  RigCalibration rig;
  TrajectoryOptions trajectory;
  RenderOptions render;
  // The camera path when not empty (scene families); else MakeTrajectory(trajectory). trajectory.fps
  // applies either way.
  Trajectory poses;
  // Motion blur: each frame averages blur_samples renders spread over `exposure` (a fraction in
  // [0, 1]) of the motion since the previous frame; 1 sample = none.
  int blur_samples = 1;
  double exposure = 0;
  // The rig's lights stay where they were at the first frame instead of moving with the camera; the
  // written camera.yaml then gives them intensity 0 (no light moves with the camera).
  bool lights_fixed_in_world = false;
  // Extra key/value lines for scene.yaml (what a scene family drew).
  std::vector<std::pair<std::string, std::string>> notes;

  Trajectory Poses() const { return poses.empty() ? MakeTrajectory(trajectory) : poses; }
};

// The presets in a fixed order; the first is the demo scene.
std::vector<PresetInfo> ListPresets();

StatusOr<SynthSetup> MakePreset(const std::string& name, const PresetOptions& options);

// The rig of the paper's setup at this image size: 50 degree horizontal field of view, red, green
// and blue point lights 0.2 m around the lens, and a non-identity crosstalk matrix.
RigCalibration MakeDefaultRig(int width, int height);

// Where mesh files are looked up (see PresetOptions::mesh_dir).
std::vector<std::string> MeshSearchPath(const std::string& mesh_dir);

}  // namespace prism::synth
