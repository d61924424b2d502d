#include "server/rig_wire.h"

#include <string>

namespace prism {
namespace {

Eigen::Vector3d FromWire(const v1::Vector3& v) { return Eigen::Vector3d(v.x(), v.y(), v.z()); }

void ToWire(const Eigen::Vector3d& v, v1::Vector3* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

}  // namespace

StatusOr<RigCalibration> RigFromWire(const v1::RigCalibration& w) {
  RigCalibration rig;
  const v1::CameraIntrinsics& c = w.camera();
  if (c.width() == 0 || c.height() == 0 || c.width() > 16384 || c.height() > 16384)
    return InvalidArgumentError("calibration.camera: width and height must be in [1, 16384], got " +
                                std::to_string(c.width()) + "x" + std::to_string(c.height()));
  rig.camera.width = static_cast<int>(c.width());
  rig.camera.height = static_cast<int>(c.height());
  rig.camera.fx = c.fx();
  rig.camera.fy = c.fy();
  rig.camera.cx = c.cx();
  rig.camera.cy = c.cy();
  if (c.distortion_size() != 0 && c.distortion_size() != 5)
    return InvalidArgumentError("calibration.camera.distortion needs 0 or 5 values, got " +
                                std::to_string(c.distortion_size()));
  for (int i = 0; i < c.distortion_size(); ++i) rig.camera.distortion[static_cast<size_t>(i)] = c.distortion(i);
  if (w.lights_size() != 3)
    return InvalidArgumentError("calibration needs exactly 3 lights, got " + std::to_string(w.lights_size()));
  for (int i = 0; i < 3; ++i) {
    const v1::LightCalibration& l = w.lights(i);
    Light& light = rig.lights[static_cast<size_t>(i)];
    light.name = l.name();
    light.type = l.type() == v1::LightCalibration::TYPE_DIRECTIONAL ? LightType::kDirectional : LightType::kPoint;
    light.position_in_camera = FromWire(l.position_in_camera());
    light.direction_in_camera = FromWire(l.direction_in_camera());
    light.color = FromWire(l.color());
    light.intensity = l.intensity();
  }
  if (w.crosstalk_size() != 9)
    return InvalidArgumentError("calibration.crosstalk needs 9 values, got " + std::to_string(w.crosstalk_size()));
  for (int i = 0; i < 9; ++i) rig.crosstalk(i / 3, i % 3) = w.crosstalk(i);
  if (Status s = rig.Check(); !s.ok()) return InvalidArgumentError("calibration: " + s.message());
  return rig;
}

void RigToWire(const RigCalibration& rig, v1::RigCalibration* wire) {
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
    w->set_type(l.type == LightType::kDirectional ? v1::LightCalibration::TYPE_DIRECTIONAL
                                                  : v1::LightCalibration::TYPE_POINT);
    ToWire(l.position_in_camera, w->mutable_position_in_camera());
    ToWire(l.direction_in_camera, w->mutable_direction_in_camera());
    ToWire(l.color, w->mutable_color());
    w->set_intensity(l.intensity);
  }
  for (int i = 0; i < 9; ++i) wire->add_crosstalk(rig.crosstalk(i / 3, i % 3));
}

}  // namespace prism
