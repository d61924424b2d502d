// A rig calibration (core/io/calibration_io.h) in the client SDK's form (prism/client/client.h), for
// the tools and tests that open sessions from a sequence's camera.yaml or a rendered preset's rig. It
// goes through the wire form, the one conversion each form has (server/rig_wire.h for the core's,
// client-sdk/src/rig_wire.h for the SDK's), so the SDK's rig is what the server would be sent.
#pragma once

#include <prism/client/client.h>

#include "client-sdk/src/rig_wire.h"
#include "core/io/calibration_io.h"
#include "core/util/check.h"
#include "server/rig_wire.h"

namespace prism {

// The camera (intrinsics and distortion), the three lights and the crosstalk of `calibration`.
inline client::Rig ToClientRig(const RigCalibration& calibration) {
  v1::RigCalibration wire;
  RigToWire(calibration, &wire);
  client::Rig rig;
  const client::Status s = client::RigFromWire(wire, &rig);
  PRISM_CHECK(s.ok()) << "a RigCalibration always has the wire's shape: " << s.ToString();
  return rig;
}

}  // namespace prism
