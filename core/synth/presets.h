// Named synthetic sequences used by tests, benchmarks and the demo. Every preset is a dark room
// (only the rig's three lights, as in the paper's experiments) unless its name says otherwise.
#pragma once

#include <string>
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
