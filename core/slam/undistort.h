// Undistortion of a camera's images for the SLAM and the dense stage, which model a pinhole camera
// (Tracker, KeyframeDepth and the keyframe adjustment refuse distortion; so do photometric stereo and
// fusion through their pixel rays). Real capture devices have lens distortion (OpenCV's k1 k2 p1 p2
// k3 in camera.yaml and in the wire calibration), so prism-slam and the session pipeline remap every
// frame into an undistorted pinhole camera of the same size and run everything on that camera. Poses
// are unchanged by this (same centre, same orientation); pixel quantities (keyframe depth maps,
// normals) are in the undistorted camera.
//
// The undistorted camera is OpenCV's optimal new camera matrix with alpha = 0 and the principal point
// at the image centre: every output pixel sees the scene (no black border, which would be an edge
// fixed in the image for the tracker), at the cost of the outermost field of view.
#pragma once

#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/util/status.h"

namespace prism {

class ImageUndistorter {
 public:
  // INVALID_ARGUMENT when the camera fails Check. A camera without distortion gives an identity
  // remap (Undistort returns the image unchanged).
  static StatusOr<ImageUndistorter> Create(const PinholeCamera& distorted);

  // The pinhole camera (no distortion, same size) the output images are in.
  const PinholeCamera& camera() const { return camera_; }
  const PinholeCamera& distorted_camera() const { return distorted_; }
  bool identity() const { return map1_.empty(); }

  // Bicubic remap of an image of the distorted camera's size (any type OpenCV remaps), border pixels
  // replicated. INVALID_ARGUMENT on a size mismatch. Bicubic, not bilinear: a bilinear read between
  // pixels averages them, so the remap blurs and denoises the image by an amount that varies across it.
  StatusOr<cv::Mat> Undistort(const cv::Mat& image) const;
  // Nearest-neighbour remap, for depth maps and labels (no mixing across edges).
  StatusOr<cv::Mat> UndistortNearest(const cv::Mat& image) const;

 private:
  StatusOr<cv::Mat> Remap(const cv::Mat& image, int interpolation) const;

  PinholeCamera distorted_, camera_;
  cv::Mat map1_, map2_;    // fixed-point maps (cv::convertMaps), empty for no distortion
  cv::Mat map_x_, map_y_;  // float maps, for the nearest-neighbour remap
};

}  // namespace prism
