// The client SDK's rig (prism/client/client.h) on the wire (proto/prism/v1/session.proto
// RigCalibration) and back: the one place a rig's fields are copied to or from the wire. The server
// reads its core RigCalibration through it (server/rig_wire.h), so every form of the rig goes to
// and from the wire the same way.
#pragma once

#include "prism/client/client.h"
#include "prism/v1/session.pb.h"

namespace prism::client {

// Every field of `rig` into *wire (cleared first).
void RigToWire(const Rig& rig, v1::RigCalibration* wire);

// kInvalidArgument, naming the field, when the wire's shape does not fit a Rig: a size outside
// [1, 16384], distortion other than 0 or 5 values, not 3 lights, not 9 crosstalk values. Values are
// not checked further here (the server checks the calibration as a whole).
Status RigFromWire(const v1::RigCalibration& wire, Rig* rig);

}  // namespace prism::client
