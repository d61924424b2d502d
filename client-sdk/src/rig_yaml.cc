// LoadRig: a rig calibration (camera.yaml, OpenCV FileStorage YAML) into a Rig. The format is the one
// core/io/calibration_io.h reads and writes with OpenCV (README "Calibration"); it is read here with
// yaml-cpp so that the SDK needs neither OpenCV nor the core libraries. tests/load_rig_test.cc checks
// that both readers agree and refuse the same malformed files.
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <string>
#include <vector>

#include "prism/client/client.h"

namespace prism::client {
namespace {

Status Invalid(const std::string& path, const std::string& message) {
  return {Code::kInvalidArgument, "calibration '" + path + "': " + message, false};
}

// A number; false when the node is absent or not one.
bool ReadNumber(const YAML::Node& node, double* v) {
  if (!node || !node.IsScalar()) return false;
  try {
    *v = node.as<double>();
    return true;
  } catch (const YAML::Exception&) {
    return false;
  }
}

// A 3-vector "[x, y, z]"; an absent node leaves `v` as it is.
bool ReadVec3(const YAML::Node& node, std::array<double, 3>* v) {
  if (!node) return true;
  if (!node.IsSequence() || node.size() != 3) return false;
  for (size_t i = 0; i < 3; ++i)
    if (!ReadNumber(node[i], &(*v)[i])) return false;
  return true;
}

// An OpenCV matrix (!!opencv-matrix: rows, cols, data) or a plain list: its values in row-major
// order, with its rows and columns. An absent node gives no values.
bool ReadMatrix(const YAML::Node& node, std::vector<double>* values, size_t* rows, size_t* cols) {
  values->clear();
  *rows = *cols = 0;
  if (!node) return true;
  if (node.IsMap()) {
    double r = 0, c = 0;
    if (!ReadNumber(node["rows"], &r) || !ReadNumber(node["cols"], &c)) return false;
    *rows = static_cast<size_t>(r);
    *cols = static_cast<size_t>(c);
  }
  // Bound once: assigning to a yaml-cpp Node would overwrite the node it refers to.
  const YAML::Node data = node.IsMap() ? node["data"] : node;
  if (!data.IsSequence()) return false;
  if (!node.IsMap()) {
    *rows = 1;
    *cols = data.size();
  }
  values->resize(data.size());
  for (size_t i = 0; i < data.size(); ++i)
    if (!ReadNumber(data[i], &(*values)[i])) return false;
  return values->size() == *rows * *cols;
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

Status ReadRig(const std::string& path, const YAML::Node& fs, Rig* out) {
  Rig rig;
  Camera& c = rig.camera;
  double number[6];
  const char* keys[6] = {"width", "height", "fx", "fy", "cx", "cy"};
  for (int k = 0; k < 6; ++k)
    if (!ReadNumber(fs[keys[k]], &number[k]))
      return Invalid(path, std::string("missing or non-numeric '") + keys[k] + "'");
  // Sizes round as OpenCV's FileNode does.
  c.width = static_cast<int>(std::lround(number[0]));
  c.height = static_cast<int>(std::lround(number[1]));
  c.fx = number[2];
  c.fy = number[3];
  c.cx = number[4];
  c.cy = number[5];
  std::vector<double> values;
  size_t rows = 0, cols = 0;
  const bool distortion_read = ReadMatrix(fs["distortion"], &values, &rows, &cols);
  if (!values.empty() || !distortion_read) {
    if (!distortion_read || values.size() != 5)
      return Invalid(path, "distortion must have 5 coefficients (k1 k2 p1 p2 k3)");
    for (int i = 0; i < 5; ++i) c.distortion[i] = values[i];
  }
  const bool crosstalk_read = ReadMatrix(fs["crosstalk"], &values, &rows, &cols);
  if (!values.empty() || !crosstalk_read) {
    if (!crosstalk_read || rows != 3 || cols != 3) return Invalid(path, "crosstalk must be 3x3");
    for (int k = 0; k < 9; ++k) rig.crosstalk[k] = values[k];
  }
  const YAML::Node lights = fs["lights"];
  if (!lights) return Invalid(path, "missing 'lights' (3 entries: red, green, blue)");
  if (!lights.IsSequence() || lights.size() != 3)
    return Invalid(path, "'lights' must have 3 entries (red, green, blue)");
  for (int i = 0; i < 3; ++i) {
    const YAML::Node n = lights[i];
    Light& l = rig.lights[i];
    if (!n.IsMap()) return Invalid(path, "light " + std::to_string(i) + " is not a map of its fields");
    l.name = n["name"] && n["name"].IsScalar() ? n["name"].as<std::string>() : "";
    const std::string type = n["type"] && n["type"].IsScalar() ? n["type"].as<std::string>() : "point";
    if (type != "point" && type != "directional")
      return Invalid(path, "light " + std::to_string(i) + " has unknown type '" + type + "' (point or directional)");
    l.directional = type == "directional";
    // As core/io: an absent position is the camera centre, an absent color white, an absent intensity 0.
    l.position_in_camera = {0, 0, 0};
    if (!ReadVec3(n["position"], &l.position_in_camera) || !ReadVec3(n["direction"], &l.direction_in_camera) ||
        !ReadVec3(n["color"], &l.color))
      return Invalid(path, "light " + std::to_string(i) + " has a malformed 3-vector");
    l.intensity = 0;
    if (n["intensity"] && !ReadNumber(n["intensity"], &l.intensity))
      return Invalid(path, "light " + std::to_string(i) + " has a non-numeric intensity");
  }
  if (Status s = CheckRig(path, rig); !s.ok()) return s;
  *out = rig;
  return {};
}

}  // namespace

Status LoadRig(const std::string& path, Rig* rig) {
  if (!rig) return {Code::kInvalidArgument, "LoadRig: rig is null", false};
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::BadFile&) {
    return {Code::kNotFound, "cannot open calibration '" + path + "'", false};
  } catch (const YAML::Exception& e) {
    return Invalid(path, std::string("not valid YAML: ") + e.what());
  }
  if (!root.IsMap()) return Invalid(path, "not a map of calibration fields");
  try {
    return ReadRig(path, root, rig);
  } catch (const YAML::Exception& e) {
    return Invalid(path, std::string("malformed: ") + e.what());
  }
}

}  // namespace prism::client
