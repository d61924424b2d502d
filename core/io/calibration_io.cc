#include "core/io/calibration_io.h"

#include <cmath>
#include <sstream>

#include <Eigen/LU>
#include <opencv2/core.hpp>

namespace prism {

Status RigCalibration::Check() const {
  PRISM_RETURN_IF_ERROR(camera.Check());
  for (const Light& l : lights) {
    if (!(l.intensity >= 0) || !std::isfinite(l.intensity))
      return InvalidArgumentError("light '" + l.name + "': intensity must be finite and >= 0");
    if (!l.position_in_camera.allFinite() || !l.direction_in_camera.allFinite())
      return InvalidArgumentError("light '" + l.name + "': position/direction must be finite");
    if (l.type == LightType::kDirectional && l.direction_in_camera.norm() < 1e-9)
      return InvalidArgumentError("light '" + l.name + "': directional light needs a non-zero direction");
  }
  if (!crosstalk.allFinite() || std::abs(crosstalk.determinant()) < 1e-9)
    return InvalidArgumentError("crosstalk matrix must be finite and invertible");
  return Status::Ok();
}

namespace {

Eigen::Vector3d ReadVec3(const cv::FileNode& node, bool* ok) {
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  if (node.empty()) return v;
  if (!node.isSeq() || node.size() != 3) {
    *ok = false;
    return v;
  }
  for (int i = 0; i < 3; ++i) v[i] = static_cast<double>(node[i]);
  return v;
}

void WriteVec3(cv::FileStorage& fs, const std::string& key, const Eigen::Vector3d& v) {
  fs << key << "[:" << v.x() << v.y() << v.z() << "]";
}

}  // namespace

StatusOr<RigCalibration> ReadCalibrationYaml(const std::string& path) {
  cv::FileStorage fs;
  try {
    if (!fs.open(path, cv::FileStorage::READ)) return NotFoundError("cannot open calibration '" + path + "'");
  } catch (const cv::Exception& e) {
    return InvalidArgumentError("calibration '" + path + "' is not valid OpenCV YAML: " + e.what());
  }
  RigCalibration c;
  try {
    c.camera.width = static_cast<int>(fs["width"]);
    c.camera.height = static_cast<int>(fs["height"]);
    c.camera.fx = static_cast<double>(fs["fx"]);
    c.camera.fy = static_cast<double>(fs["fy"]);
    c.camera.cx = static_cast<double>(fs["cx"]);
    c.camera.cy = static_cast<double>(fs["cy"]);
    cv::Mat dist;
    fs["distortion"] >> dist;
    if (!dist.empty()) {
      if (dist.total() != 5) return InvalidArgumentError(path + ": distortion must have 5 coefficients");
      dist.convertTo(dist, CV_64F);
      for (int i = 0; i < 5; ++i) c.camera.distortion[i] = dist.at<double>(i);
    }
    cv::Mat xt;
    fs["crosstalk"] >> xt;
    if (!xt.empty()) {
      if (xt.rows != 3 || xt.cols != 3) return InvalidArgumentError(path + ": crosstalk must be 3x3");
      xt.convertTo(xt, CV_64F);
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) c.crosstalk(r, k) = xt.at<double>(r, k);
    }
    const cv::FileNode lights = fs["lights"];
    if (lights.empty()) return InvalidArgumentError(path + ": missing 'lights' (3 entries)");
    if (!lights.isSeq() || lights.size() != 3) return InvalidArgumentError(path + ": 'lights' must have 3 entries");
    for (int i = 0; i < 3; ++i) {
      const cv::FileNode n = lights[i];
      Light& l = c.lights[i];
      bool ok = true;
      l.name = static_cast<std::string>(n["name"]);
      const std::string type = n["type"].empty() ? "point" : static_cast<std::string>(n["type"]);
      if (type == "point") l.type = LightType::kPoint;
      else if (type == "directional") l.type = LightType::kDirectional;
      else return InvalidArgumentError(path + ": light " + std::to_string(i) + " has unknown type '" + type + "'");
      l.position_in_camera = ReadVec3(n["position"], &ok);
      if (!n["direction"].empty()) l.direction_in_camera = ReadVec3(n["direction"], &ok);
      if (!n["color"].empty()) l.color = ReadVec3(n["color"], &ok);
      l.intensity = static_cast<double>(n["intensity"]);
      if (!ok) return InvalidArgumentError(path + ": light " + std::to_string(i) + " has a malformed 3-vector");
    }
  } catch (const cv::Exception& e) {
    return InvalidArgumentError("calibration '" + path + "': " + e.what());
  }
  PRISM_RETURN_IF_ERROR(c.Check());
  return c;
}

Status WriteCalibrationYaml(const std::string& path, const RigCalibration& c) {
  cv::FileStorage fs;
  try {
    if (!fs.open(path, cv::FileStorage::WRITE)) return UnavailableError("cannot write '" + path + "'");
    fs << "width" << c.camera.width << "height" << c.camera.height;
    fs << "fx" << c.camera.fx << "fy" << c.camera.fy << "cx" << c.camera.cx << "cy" << c.camera.cy;
    cv::Mat dist(1, 5, CV_64F);
    for (int i = 0; i < 5; ++i) dist.at<double>(i) = c.camera.distortion[i];
    fs << "distortion" << dist;
    cv::Mat xt(3, 3, CV_64F);
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) xt.at<double>(r, k) = c.crosstalk(r, k);
    fs << "crosstalk" << xt;
    fs << "lights"
       << "[";
    for (const Light& l : c.lights) {
      fs << "{"
         << "name" << l.name << "type" << (l.type == LightType::kPoint ? "point" : "directional");
      WriteVec3(fs, "position", l.position_in_camera);
      WriteVec3(fs, "direction", l.direction_in_camera);
      WriteVec3(fs, "color", l.color);
      fs << "intensity" << l.intensity << "}";
    }
    fs << "]";
    fs.release();
  } catch (const cv::Exception& e) {
    return UnavailableError("writing '" + path + "': " + e.what());
  }
  return Status::Ok();
}

}  // namespace prism
