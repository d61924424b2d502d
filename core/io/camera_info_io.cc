#include "core/io/camera_info_io.h"

#include <cctype>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <sstream>
#include <vector>

#include <opencv2/core.hpp>

#include "core/io/calibration_io.h"

namespace prism {
namespace {

// Opens a YAML file with FileStorage. ROS writes plain YAML without OpenCV's "%YAML:1.0" line, which
// FileStorage requires: it is added in memory.
StatusOr<cv::FileStorage> OpenYaml(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return NotFoundError("cannot open '" + path + "'");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (text.rfind("%YAML", 0) != 0) text = "%YAML:1.0\n---\n" + text;
  try {
    cv::FileStorage fs(text, cv::FileStorage::READ | cv::FileStorage::MEMORY | cv::FileStorage::FORMAT_YAML);
    if (!fs.isOpened()) return InvalidArgumentError(path + ": not a YAML file OpenCV can read");
    return fs;
  } catch (const cv::Exception& e) {
    return InvalidArgumentError(path + ": not valid YAML (" + e.what() + ")");
  }
}

// Distortion in OpenCV order into the camera; any coefficient beyond k3 must be zero.
Status SetDistortion(const std::string& path, const std::vector<double>& d, PinholeCamera* camera) {
  if (d.size() != 0 && d.size() != 4 && d.size() != 5 && d.size() != 8 && d.size() != 12 && d.size() != 14)
    return InvalidArgumentError(path + ": " + std::to_string(d.size()) +
                                " distortion coefficients (expected 4, 5, 8, 12 or 14)");
  for (size_t i = 5; i < d.size(); ++i)
    if (d[i] != 0)
      return InvalidArgumentError(path + ": distortion coefficient " + std::to_string(i) + " = " +
                                  std::to_string(d[i]) +
                                  "; Prism models k1 k2 p1 p2 k3 only (rational and thin-prism terms must be 0)");
  camera->distortion = {0, 0, 0, 0, 0};
  for (size_t i = 0; i < std::min<size_t>(5, d.size()); ++i) camera->distortion[i] = d[i];
  return Status::Ok();
}

Status SetMatrix(const std::string& path, const std::vector<double>& k, PinholeCamera* camera) {
  if (k.size() != 9)
    return InvalidArgumentError(path + ": camera_matrix needs 9 values, has " + std::to_string(k.size()));
  if (k[1] != 0 || k[3] != 0 || k[6] != 0 || k[7] != 0 || k[8] != 1)
    return InvalidArgumentError(path + ": camera_matrix must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)");
  camera->fx = k[0];
  camera->cx = k[2];
  camera->fy = k[4];
  camera->cy = k[5];
  return Status::Ok();
}

std::vector<double> Numbers(const cv::FileNode& node) {
  std::vector<double> v;
  if (node.isSeq())
    for (const cv::FileNode& e : node) v.push_back(static_cast<double>(e));
  return v;
}

// An opencv-matrix node or a plain sequence, flattened row-major.
std::vector<double> MatrixValues(const cv::FileNode& node) {
  if (node.isMap() && !node["data"].empty() && !node["rows"].empty() && !node["dt"].empty()) {
    cv::Mat m;
    node >> m;
    m.convertTo(m, CV_64F);
    return std::vector<double>(m.begin<double>(), m.end<double>());
  }
  if (node.isMap()) return Numbers(node["data"]);  // ROS {rows, cols, data}
  return Numbers(node);
}

std::string Join(const double* v, size_t n) {
  std::ostringstream s;
  s.precision(17);
  for (size_t i = 0; i < n; ++i) s << (i ? ", " : "") << v[i];
  return s.str();
}

Status FinishCamera(const std::string& path, PinholeCamera camera, PinholeCamera* out) {
  const Status s = camera.Check();
  if (!s.ok()) return InvalidArgumentError(path + ": " + s.message());
  *out = camera;
  return Status::Ok();
}

}  // namespace

StatusOr<PinholeCamera> ReadOpenCvCameraYaml(const std::string& path) {
  StatusOr<cv::FileStorage> fs = OpenYaml(path);
  if (!fs.ok()) return fs.status();
  try {
    PinholeCamera camera;
    if ((*fs)["image_width"].empty() || (*fs)["camera_matrix"].empty())
      return InvalidArgumentError(path + ": needs image_width, image_height and camera_matrix");
    camera.width = static_cast<int>((*fs)["image_width"]);
    camera.height = static_cast<int>((*fs)["image_height"]);
    PRISM_RETURN_IF_ERROR(SetMatrix(path, MatrixValues((*fs)["camera_matrix"]), &camera));
    PRISM_RETURN_IF_ERROR(SetDistortion(path, MatrixValues((*fs)["distortion_coefficients"]), &camera));
    PinholeCamera out;
    PRISM_RETURN_IF_ERROR(FinishCamera(path, camera, &out));
    return out;
  } catch (const cv::Exception& e) {
    return InvalidArgumentError(path + ": " + e.what());
  }
}

Status WriteOpenCvCameraYaml(const std::string& path, const PinholeCamera& camera) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  try {
    cv::FileStorage fs(path, cv::FileStorage::WRITE | cv::FileStorage::FORMAT_YAML);
    if (!fs.isOpened()) return UnavailableError("cannot write '" + path + "'");
    fs << "image_width" << camera.width << "image_height" << camera.height;
    const cv::Matx33d k(camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
    fs << "camera_matrix" << cv::Mat(k);
    fs << "distortion_coefficients" << cv::Mat(1, 5, CV_64F, const_cast<double*>(camera.distortion.data()));
  } catch (const cv::Exception& e) {
    return UnavailableError("cannot write '" + path + "': " + e.what());
  }
  return Status::Ok();
}

StatusOr<PinholeCamera> ReadRosCameraInfoYaml(const std::string& path) {
  StatusOr<cv::FileStorage> fs = OpenYaml(path);
  if (!fs.ok()) return fs.status();
  try {
    if ((*fs)["image_width"].empty() || (*fs)["camera_matrix"].empty())
      return InvalidArgumentError(path + ": needs image_width, image_height and camera_matrix");
    PinholeCamera camera;
    camera.width = static_cast<int>((*fs)["image_width"]);
    camera.height = static_cast<int>((*fs)["image_height"]);
    PRISM_RETURN_IF_ERROR(SetMatrix(path, MatrixValues((*fs)["camera_matrix"]), &camera));
    const std::string model = (*fs)["distortion_model"].empty() ? "plumb_bob" : (std::string)(*fs)["distortion_model"];
    if (model != "plumb_bob" && model != "rational_polynomial")
      return InvalidArgumentError(path + ": distortion_model '" + model +
                                  "' is not supported (plumb_bob or rational_polynomial with k4..k6 = 0)");
    PRISM_RETURN_IF_ERROR(SetDistortion(path, MatrixValues((*fs)["distortion_coefficients"]), &camera));
    PinholeCamera out;
    PRISM_RETURN_IF_ERROR(FinishCamera(path, camera, &out));
    return out;
  } catch (const cv::Exception& e) {
    return InvalidArgumentError(path + ": " + e.what());
  }
}

Status WriteRosCameraInfoYaml(const std::string& path, const PinholeCamera& camera, const std::string& camera_name) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  std::ofstream out(path);
  if (!out) return UnavailableError("cannot write '" + path + "'");
  const double k[9] = {camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1};
  const double r[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  const double p[12] = {camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0};
  out << "image_width: " << camera.width << "\nimage_height: " << camera.height << "\ncamera_name: " << camera_name
      << "\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [" << Join(k, 9)
      << "]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: ["
      << Join(camera.distortion.data(), 5) << "]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [" << Join(r, 9)
      << "]\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: [" << Join(p, 12) << "]\n";
  if (!out) return UnavailableError("write failed: '" + path + "'");
  return Status::Ok();
}

StatusOr<PinholeCamera> ReadDsoCameraTxt(const std::string& path) {
  std::ifstream in(path);
  if (!in) return NotFoundError("cannot open '" + path + "'");
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) {
    const size_t b = line.find_first_not_of(" \t\r");
    if (b != std::string::npos) lines.push_back(line.substr(b));
  }
  if (lines.size() < 2)
    return InvalidArgumentError(path + ": a camera.txt needs the intrinsics line and the 'width height' line");
  std::istringstream first(lines[0]);
  std::string model;
  if (!lines[0].empty() && std::isalpha(static_cast<unsigned char>(lines[0][0]))) first >> model;
  std::vector<double> v;
  for (double x; first >> x;) v.push_back(x);
  if (!first.eof())
    return InvalidArgumentError(path + ":1: expected numbers after the model name, got '" + lines[0] + "'");
  if (model.empty()) model = v.size() == 8 ? "RadTan" : v.size() == 5 ? "FOV" : "";
  const auto want = [&](size_t n) -> Status {
    if (v.size() == n) return Status::Ok();
    return InvalidArgumentError(path + ":1: the " + model + " model has " + std::to_string(n) + " numbers, got " +
                                std::to_string(v.size()));
  };
  PinholeCamera c;
  if (model == "RadTan") {
    PRISM_RETURN_IF_ERROR(want(8));
    c.distortion = {v[4], v[5], v[6], v[7], 0};
  } else if (model == "Pinhole" || (model == "FOV" && v.size() == 5 && v[4] == 0)) {
    PRISM_RETURN_IF_ERROR(want(5));
  } else if (model == "FOV" || model == "KannalaBrandt" || model == "EquiDistant") {
    return InvalidArgumentError(path + ": the " + model +
                                " camera model is not Prism's (pinhole + k1 k2 p1 p2 k3); calibrate with the "
                                "radial-tangential (RadTan) model");
  } else {
    return InvalidArgumentError(path + ":1: unknown camera model or parameter count ('" + lines[0] +
                                "'); expected RadTan fx fy cx cy k1 k2 p1 p2 or Pinhole fx fy cx cy 0");
  }
  std::istringstream size_line(lines[1]);
  std::string extra;
  if (!(size_line >> c.width >> c.height) || (size_line >> extra))
    return InvalidArgumentError(path + ":2: expected 'width height', got '" + lines[1] + "'");
  c.fx = v[0];
  c.fy = v[1];
  c.cx = v[2];
  c.cy = v[3];
  if (c.cx < 1 && c.cy < 1) {  // relative
    c.fx *= c.width;
    c.fy *= c.height;
    c.cx = c.cx * c.width - 0.5;
    c.cy = c.cy * c.height - 0.5;
  }
  if (Status s = c.Check(); !s.ok()) return InvalidArgumentError(path + ": " + s.message());
  return c;
}

StatusOr<PinholeCamera> ReadCameraIntrinsics(const std::string& path) {
  {
    std::ifstream in(path);
    if (!in) return NotFoundError("cannot open '" + path + "'");
    std::string line;
    while (std::getline(in, line) && line.find_first_not_of(" \t\r") == std::string::npos) {
    }
    if (line.find(':') == std::string::npos && line.rfind("%YAML", 0) != 0 && line.rfind("---", 0) != 0)
      return ReadDsoCameraTxt(path);
  }
  StatusOr<cv::FileStorage> fs = OpenYaml(path);
  if (!fs.ok()) return fs.status();
  bool ros = false, opencv = false, prism = false;
  try {
    ros = !(*fs)["distortion_model"].empty() ||
          (!(*fs)["camera_matrix"].empty() && (*fs)["camera_matrix"].isMap() && (*fs)["camera_matrix"]["dt"].empty());
    opencv = !ros && !(*fs)["camera_matrix"].empty();
    prism = !(*fs)["fx"].empty() && !(*fs)["lights"].empty();
  } catch (const cv::Exception& e) {
    return InvalidArgumentError(path + ": " + e.what());
  }
  if (ros) return ReadRosCameraInfoYaml(path);
  if (opencv) return ReadOpenCvCameraYaml(path);
  if (prism) {
    StatusOr<RigCalibration> rig = ReadCalibrationYaml(path);
    if (!rig.ok()) return rig.status();
    return rig->camera;
  }
  return InvalidArgumentError(path +
                              ": neither an OpenCV calibration (camera_matrix), a ROS camera_info "
                              "(distortion_model, camera_matrix.data) nor a Prism camera.yaml (fx, lights)");
}

}  // namespace prism
