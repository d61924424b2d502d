// Dense keyframe clouds back-projected from synthetic renders: the test and benchmark input of the
// mapping module (what the fusion stage will hand it for real sequences). Not part of prism_mapping:
// it lives in prism_mapping_testing, which links the renderer.
#pragma once

#include <cstdint>

#include "core/geometry/camera.h"
#include "core/geometry/point_cloud.h"
#include "core/geometry/rigid3.h"
#include "core/synth/presets.h"
#include "core/synth/renderer.h"

namespace prism {

// One point per pixel with depth > 0 (every `stride`-th pixel in x and y), in the camera frame:
// position Unproject(pixel) * depth, the rendered normal, the rendered colour and confidence 1.
// PRISM_CHECK on stride < 1 or images that do not match the camera size (a bug of the caller).
PointCloud BackProjectFrame(const PinholeCamera& camera, const synth::RenderedFrame& frame, int stride = 1);

// Renders the preset's scene at world_from_camera (noise seeded by `noise_seed`) and back-projects it.
PointCloud RenderKeyframeCloud(const synth::SynthSetup& setup, const Rigid3d& world_from_camera, uint64_t noise_seed,
                               int stride = 1);

}  // namespace prism
