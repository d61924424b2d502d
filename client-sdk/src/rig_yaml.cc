// LoadRig: a rig calibration (camera.yaml, OpenCV FileStorage YAML) into a Rig. The format is the one
// core/io/calibration_io.h reads and writes (README "Calibration"); it is read here with OpenCV alone so
// that the SDK needs none of the core libraries. tests/load_rig_test.cc checks that both readers agree.
#include <cmath>
#include <string>

#include <opencv2/core.hpp>

#include "prism/client/client.h"

namespace prism::client {
namespace {

Status Invalid(const std::string& path, const std::string& message) {
  return {Code::kInvalidArgument, "calibration '" + path + "': " + message, false};
}

// A 3-vector "[x, y, z]"; an absent node leaves `v` as it is.
bool ReadVec3(const cv::FileNode& node, std::array<double, 3>* v) {
  if (node.empty()) return true;
  if (!node.isSeq() || node.size() != 3) return false;
  for (int i = 0; i < 3; ++i) (*v)[i] = static_cast<double>(node[i]);
  return true;
}

bool AllFinite(const std::array<double, 3>& v) {
  return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]);
}

Status CheckRig(const std::string& path, const Rig& rig) {
  const Camera& c = rig.camera;
  if (c.width <= 0 || c.height <= 0 || c.width > 16384 || c.height > 16384)
    return Invalid(path, "width x height = " + std::to_string(c.width) + "x" + std::to_string(c.height) +
                             "; violated: in [1, 16384]");
  if (!(c.fx > 0) || !(c.fy > 0) || !std::isfinite(c.fx) || !std::isfinite(c.fy))
    return Invalid(path, "fx and fy must be finite and > 0");
  if (!std::isfinite(c.cx) || !std::isfinite(c.cy)) return Invalid(path, "cx and cy must be finite");
  for (double d : c.distortion)
    if (!std::isfinite(d)) return Invalid(path, "distortion must be finite");
  for (const Light& l : rig.lights) {
    if (!(l.intensity >= 0) || !std::isfinite(l.intensity))
      return Invalid(path, "light '" + l.name + "': intensity must be finite and >= 0");
    if (!AllFinite(l.position_in_camera) || !AllFinite(l.direction_in_camera) || !AllFinite(l.color))
      return Invalid(path, "light '" + l.name + "': position, direction and color must be finite");
    const auto& d = l.direction_in_camera;
    if (l.directional && std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) < 1e-9)
      return Invalid(path, "light '" + l.name + "': a directional light needs a non-zero direction");
  }
  const auto& x = rig.crosstalk;
  for (double v : x)
    if (!std::isfinite(v)) return Invalid(path, "crosstalk must be finite");
  const double det =
      x[0] * (x[4] * x[8] - x[5] * x[7]) - x[1] * (x[3] * x[8] - x[5] * x[6]) + x[2] * (x[3] * x[7] - x[4] * x[6]);
  if (std::abs(det) < 1e-9) return Invalid(path, "crosstalk must be invertible");
  return {};
}

Status ReadRig(const std::string& path, const cv::FileStorage& fs, Rig* out) {
  Rig rig;
  Camera& c = rig.camera;
  for (const char* key : {"width", "height", "fx", "fy", "cx", "cy"})
    if (fs[key].empty() || (!fs[key].isReal() && !fs[key].isInt()))
      return Invalid(path, std::string("missing or non-numeric '") + key + "'");
  c.width = static_cast<int>(fs["width"]);
  c.height = static_cast<int>(fs["height"]);
  c.fx = static_cast<double>(fs["fx"]);
  c.fy = static_cast<double>(fs["fy"]);
  c.cx = static_cast<double>(fs["cx"]);
  c.cy = static_cast<double>(fs["cy"]);
  cv::Mat dist;
  fs["distortion"] >> dist;
  if (!dist.empty()) {
    if (dist.total() != 5) return Invalid(path, "distortion must have 5 coefficients (k1 k2 p1 p2 k3)");
    dist.convertTo(dist, CV_64F);
    for (int i = 0; i < 5; ++i) c.distortion[i] = dist.at<double>(i);
  }
  cv::Mat crosstalk;
  fs["crosstalk"] >> crosstalk;
  if (!crosstalk.empty()) {
    if (crosstalk.rows != 3 || crosstalk.cols != 3) return Invalid(path, "crosstalk must be 3x3");
    crosstalk.convertTo(crosstalk, CV_64F);
    for (int k = 0; k < 9; ++k) rig.crosstalk[k] = crosstalk.at<double>(k / 3, k % 3);
  }
  const cv::FileNode lights = fs["lights"];
  if (lights.empty()) return Invalid(path, "missing 'lights' (3 entries: red, green, blue)");
  if (!lights.isSeq() || lights.size() != 3) return Invalid(path, "'lights' must have 3 entries (red, green, blue)");
  for (int i = 0; i < 3; ++i) {
    const cv::FileNode n = lights[i];
    Light& l = rig.lights[i];
    l.name = static_cast<std::string>(n["name"]);
    const std::string type = n["type"].empty() ? "point" : static_cast<std::string>(n["type"]);
    if (type != "point" && type != "directional")
      return Invalid(path, "light " + std::to_string(i) + " has unknown type '" + type + "' (point or directional)");
    l.directional = type == "directional";
    // As core/io: an absent position is the camera centre, an absent color white.
    l.position_in_camera = {0, 0, 0};
    if (!ReadVec3(n["position"], &l.position_in_camera) || !ReadVec3(n["direction"], &l.direction_in_camera) ||
        !ReadVec3(n["color"], &l.color))
      return Invalid(path, "light " + std::to_string(i) + " has a malformed 3-vector");
    l.intensity = static_cast<double>(n["intensity"]);
  }
  if (Status s = CheckRig(path, rig); !s.ok()) return s;
  *out = rig;
  return {};
}

}  // namespace

Status LoadRig(const std::string& path, Rig* rig) {
  if (!rig) return {Code::kInvalidArgument, "LoadRig: rig is null", false};
  try {
    cv::FileStorage fs;
    if (!fs.open(path, cv::FileStorage::READ))
      return {Code::kNotFound, "cannot open calibration '" + path + "'", false};
    return ReadRig(path, fs, rig);
  } catch (const cv::Exception& e) {
    return Invalid(path, std::string("not valid OpenCV YAML: ") + e.what());
  }
}

}  // namespace prism::client
