// Camera intrinsics from the calibration files users already have:
//  - OpenCV YAML (cv::calibrateCamera / the OpenCV calibration sample, FileStorage): image_width,
//    image_height, camera_matrix (3x3 opencv-matrix), distortion_coefficients (4, 5, 8, 12 or 14
//    values; OpenCV order k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]).
//  - ROS sensor_msgs/CameraInfo YAML (camera_calibration_parsers, what `rosrun camera_calibration`
//    writes): image_width, image_height, camera_name, camera_matrix {rows, cols, data},
//    distortion_model (plumb_bob | rational_polynomial), distortion_coefficients {rows, cols, data},
//    rectification_matrix, projection_matrix.
// Prism's model is pinhole + k1 k2 p1 p2 k3: higher-order coefficients must be zero (else
// INVALID_ARGUMENT naming them). Both use OpenCV's pixel convention, as Prism does (centres at integers).
#pragma once

#include <string>

#include "core/geometry/camera.h"
#include "core/util/status.h"

namespace prism {

StatusOr<PinholeCamera> ReadOpenCvCameraYaml(const std::string& path);
Status WriteOpenCvCameraYaml(const std::string& path, const PinholeCamera& camera);

StatusOr<PinholeCamera> ReadRosCameraInfoYaml(const std::string& path);
Status WriteRosCameraInfoYaml(const std::string& path, const PinholeCamera& camera,
                              const std::string& camera_name = "prism_camera");

// DSO's and LSD-SLAM's camera.txt (plain text, not YAML):
//   [Model] fx fy cx cy p1 ... pn      model RadTan (8 numbers: k1 k2 p1 p2) or Pinhole (fx fy cx cy 0);
//                                      without a model name, 8 numbers are RadTan and 5 are FOV (ATAN)
//   width height                       the input images
//   crop | full | none | fx fy cx cy 0 and the output size (their own rectification; ignored here:
//                                      Prism undistorts itself, core/slam/undistort.h)
// When cx < 1 and cy < 1 the values are relative (DSO's convention): fx * width, fy * height,
// cx * width - 0.5, cy * height - 0.5 (their pixel (0, 0) spans [0, 1]^2; Prism's, OpenCV's, is
// centred at 0). FOV with a non-zero omega, KannalaBrandt and EquiDistant are not Prism's model:
// INVALID_ARGUMENT naming the model.
StatusOr<PinholeCamera> ReadDsoCameraTxt(const std::string& path);

// Any of the above, or the camera part of Prism's camera.yaml (calibration_io.h): a file whose first
// line holds no ':' and is not a YAML header is read as DSO / LSD-SLAM camera.txt, YAML files are told
// apart by keys.
StatusOr<PinholeCamera> ReadCameraIntrinsics(const std::string& path);

}  // namespace prism
