#include "client-sdk/src/rig_wire.h"

#include <string>

namespace prism::client {
namespace {

void ToWire(const std::array<double, 3>& a, v1::Vector3* v) {
  v->set_x(a[0]);
  v->set_y(a[1]);
  v->set_z(a[2]);
}

std::array<double, 3> FromWire(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

Status Invalid(const std::string& message) { return {Code::kInvalidArgument, message, false}; }

}  // namespace

void RigToWire(const Rig& rig, v1::RigCalibration* wire) {
  wire->Clear();
  v1::CameraIntrinsics* c = wire->mutable_camera();
  c->set_width(static_cast<uint32_t>(rig.camera.width));
  c->set_height(static_cast<uint32_t>(rig.camera.height));
  c->set_fx(rig.camera.fx);
  c->set_fy(rig.camera.fy);
  c->set_cx(rig.camera.cx);
  c->set_cy(rig.camera.cy);
  for (double d : rig.camera.distortion) c->add_distortion(d);
  for (const Light& l : rig.lights) {
    v1::LightCalibration* w = wire->add_lights();
    w->set_name(l.name);
    w->set_type(l.directional ? v1::LightCalibration::TYPE_DIRECTIONAL : v1::LightCalibration::TYPE_POINT);
    ToWire(l.position_in_camera, w->mutable_position_in_camera());
    ToWire(l.direction_in_camera, w->mutable_direction_in_camera());
    ToWire(l.color, w->mutable_color());
    w->set_intensity(l.intensity);
  }
  for (double x : rig.crosstalk) wire->add_crosstalk(x);
}

Status RigFromWire(const v1::RigCalibration& w, Rig* rig) {
  const v1::CameraIntrinsics& c = w.camera();
  if (c.width() == 0 || c.height() == 0 || c.width() > 16384 || c.height() > 16384)
    return Invalid("calibration.camera: width and height must be in [1, 16384], got " + std::to_string(c.width()) +
                   "x" + std::to_string(c.height()));
  if (c.distortion_size() != 0 && c.distortion_size() != 5)
    return Invalid("calibration.camera.distortion needs 0 or 5 values, got " + std::to_string(c.distortion_size()));
  if (w.lights_size() != 3)
    return Invalid("calibration needs exactly 3 lights, got " + std::to_string(w.lights_size()));
  if (w.crosstalk_size() != 9)
    return Invalid("calibration.crosstalk needs 9 values, got " + std::to_string(w.crosstalk_size()));
  Rig r;
  r.camera.width = static_cast<int>(c.width());
  r.camera.height = static_cast<int>(c.height());
  r.camera.fx = c.fx();
  r.camera.fy = c.fy();
  r.camera.cx = c.cx();
  r.camera.cy = c.cy();
  for (int i = 0; i < c.distortion_size(); ++i) r.camera.distortion[static_cast<size_t>(i)] = c.distortion(i);
  for (int i = 0; i < 3; ++i) {
    const v1::LightCalibration& l = w.lights(i);
    Light& light = r.lights[static_cast<size_t>(i)];
    light.name = l.name();
    light.directional = l.type() == v1::LightCalibration::TYPE_DIRECTIONAL;
    light.position_in_camera = FromWire(l.position_in_camera());
    light.direction_in_camera = FromWire(l.direction_in_camera());
    light.color = FromWire(l.color());
    light.intensity = l.intensity();
  }
  for (int i = 0; i < 9; ++i) r.crosstalk[static_cast<size_t>(i)] = w.crosstalk(i);
  *rig = r;
  return {};
}

}  // namespace prism::client
