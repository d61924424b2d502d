// The core's rig calibration on the wire (proto/prism/v1/session.proto RigCalibration) and back, the
// one conversion of this form (the SDK's client::Rig has its own, client-sdk/src/rig_wire.h): the
// server reads the one a client opens a session with; tests, tools and the fuzz corpus write them.
#pragma once

#include "core/io/calibration_io.h"
#include "core/util/status.h"
#include "prism/v1/session.pb.h"

namespace prism {

// INVALID_ARGUMENT, naming the field, on a calibration the pipeline cannot use (size outside
// [1, 16384], distortion other than 0 or 5 values, not 3 lights, not 9 crosstalk values, or one that
// fails RigCalibration::Check).
StatusOr<RigCalibration> RigFromWire(const v1::RigCalibration& wire);

// Every field of `rig` into *wire (cleared first).
void RigToWire(const RigCalibration& rig, v1::RigCalibration* wire);

}  // namespace prism
