// A rig calibration (core/io/calibration_io.h) in the client SDK's form (prism/client/client.h), for
// the tools and tests that open sessions from a sequence's camera.yaml or a rendered preset's rig.
#pragma once

#include <prism/client/client.h>

#include "core/io/calibration_io.h"

namespace prism {

// The camera (intrinsics and distortion), the three lights and the crosstalk of `calibration`.
inline client::Rig ToClientRig(const RigCalibration& calibration) {
  client::Rig rig;
  rig.camera.width = calibration.camera.width;
  rig.camera.height = calibration.camera.height;
  rig.camera.fx = calibration.camera.fx;
  rig.camera.fy = calibration.camera.fy;
  rig.camera.cx = calibration.camera.cx;
  rig.camera.cy = calibration.camera.cy;
  rig.camera.distortion = calibration.camera.distortion;
  for (size_t l = 0; l < 3; ++l) {
    const Light& src = calibration.lights[l];
    client::Light& dst = rig.lights[l];
    dst.name = src.name;
    dst.directional = src.type == LightType::kDirectional;
    for (int k = 0; k < 3; ++k) {
      dst.position_in_camera[k] = src.position_in_camera[k];
      dst.direction_in_camera[k] = src.direction_in_camera[k];
      dst.color[k] = src.color[k];
    }
    dst.intensity = src.intensity;
  }
  for (int k = 0; k < 9; ++k) rig.crosstalk[k] = calibration.crosstalk(k / 3, k % 3);
  return rig;
}

}  // namespace prism
