// A small three-light rig (160x120) for the integration suites that open sessions with the client SDK.
#pragma once

#include <prism/client/client.h>

namespace prism::test {

inline client::Rig SmallRig() {
  client::Rig rig;
  rig.camera = {160, 120, 150, 150, 80, 60, {0, 0, 0, 0, 0}};
  const double x[3] = {-0.2, 0.2, 0.0}, y[3] = {0.0, 0.0, -0.2};
  for (int l = 0; l < 3; ++l) {
    rig.lights[l].name = l == 0 ? "red" : l == 1 ? "green" : "blue";
    rig.lights[l].position_in_camera = {x[l], y[l], 0.0};
    rig.lights[l].color = {l == 0 ? 1.0 : 0.0, l == 1 ? 1.0 : 0.0, l == 2 ? 1.0 : 0.0};
  }
  return rig;
}

}  // namespace prism::test
