// Scene families: each seed draws a whole scene (objects, albedo, ground, rig, lights, path, noise)
// from documented ranges (docs/scene_families.md), so the SLAM and the dense stage are measured on
// scenes they were never tuned on: tune on the training seeds, report on the held-out ones.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/synth/presets.h"

namespace prism::synth {

// Seed ranges: defaults and options are set on kTrainingSeeds; results are reported on
// kHeldOutSeeds.
constexpr uint32_t kTrainingSeedsBegin = 1, kTrainingSeedsEnd = 1000;
constexpr uint32_t kHeldOutSeedsBegin = 100000, kHeldOutSeedsEnd = 101000;

struct FamilyInfo {
  std::string name;
  std::string description;
};

// "mixed" first (everything the rig may meet), then narrower ones.
std::vector<FamilyInfo> ListFamilies();

struct FamilyOptions {
  std::string family = "mixed";
  // The rig's three lights stay where they were at the first frame (ordinary lighting): the frames
  // follow brightness constancy, and the written camera.yaml says no light moves with the camera
  // (intensity 0).
  bool lights_fixed_in_world = false;
  // Frames (0 = drawn by the family: 150-300).
  int frames = 0;
  int width = 512, height = 512;
  std::string mesh_dir;  // as PresetOptions::mesh_dir
};

// The scene of `seed` in a family. Deterministic for (seed, options). NOT_FOUND for an unknown family or
// a missing mesh.
StatusOr<SynthSetup> MakeRandomScene(uint32_t seed, const FamilyOptions& options);

// Ellipsoid with semi-axes (a, b, c) along the object x, y, z axes; analytic normals.
TriangleMesh MakeEllipsoid(double a, double b, double c, int segments);

}  // namespace prism::synth
