// Renders a whole sequence of a SynthSetup to disk in the TUM layout (core/io/sequence.h), plus
// scene.yaml (preset, seed, object centre and size, path length).
#pragma once

#include <cstdint>
#include <string>

#include "core/synth/presets.h"
#include "core/util/status.h"

namespace prism {
class ThreadPool;
}

namespace prism::synth {

struct SynthesizeSummary {
  int frames = 0;
  double seconds = 0.0;  // wall time of rendering and writing
  double path_length_m = 0.0;
  double object_radius_m = 0.0;  // radius of the sphere bounding the object(s)
};

// The renderer's noise seed of frame `frame` of a sequence synthesised with `seed` (prism-synth --seed):
// what SynthesizeSequence passes to RenderFrame, for code that renders the same frames in memory.
inline uint64_t FrameNoiseSeed(uint32_t seed, int64_t frame) {
  return static_cast<uint64_t>(seed) * 1000003ull + static_cast<uint64_t>(frame);
}

// Frame i of the setup's path as SynthesizeSequence renders it: the rig's lights where the setup has them
// (fixed in the world or moving with the camera) and motion blur.
RenderedFrame RenderSequenceFrame(const SynthSetup& setup, const Trajectory& traj, size_t i, uint64_t noise_seed);
// The rig at frame i: setup.rig, or with the lights fixed in the world, their place in frame i's camera.
RigCalibration RigAtFrame(const SynthSetup& setup, const Trajectory& traj, size_t i);

// Frames are rendered in parallel on `pool` (one frame per task) when given. Deterministic for the
// setup's seed whatever the thread count.
StatusOr<SynthesizeSummary> SynthesizeSequence(const SynthSetup& setup, uint32_t seed, const std::string& out_dir,
                                               ThreadPool* pool);

}  // namespace prism::synth
