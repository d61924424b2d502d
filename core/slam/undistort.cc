#include "core/slam/undistort.h"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace prism {

StatusOr<ImageUndistorter> ImageUndistorter::Create(const PinholeCamera& distorted) {
  PRISM_RETURN_IF_ERROR(distorted.Check());
  ImageUndistorter u;
  u.distorted_ = distorted;
  u.camera_ = distorted;
  u.camera_.distortion = {0, 0, 0, 0, 0};
  if (!distorted.HasDistortion()) return u;
  const cv::Mat K = (cv::Mat_<double>(3, 3) << distorted.fx, 0, distorted.cx, 0, distorted.fy, distorted.cy, 0, 0, 1);
  cv::Mat D(1, 5, CV_64F);
  for (int i = 0; i < 5; ++i) D.at<double>(0, i) = distorted.distortion[static_cast<size_t>(i)];
  const cv::Size size(distorted.width, distorted.height);
  const cv::Mat new_k = cv::getOptimalNewCameraMatrix(K, D, size, /*alpha=*/0.0, size, nullptr,
                                                      /*centerPrincipalPoint=*/true);
  const double fx = new_k.at<double>(0, 0), fy = new_k.at<double>(1, 1);
  if (!(fx > 0 && fy > 0 && std::isfinite(fx) && std::isfinite(fy)))
    return InvalidArgumentError("ImageUndistorter: no valid undistorted camera for this distortion");
  u.camera_.fx = fx;
  u.camera_.fy = fy;
  u.camera_.cx = new_k.at<double>(0, 2);
  u.camera_.cy = new_k.at<double>(1, 2);
  PRISM_RETURN_IF_ERROR(u.camera_.Check());
  cv::initUndistortRectifyMap(K, D, cv::Mat(), new_k, size, CV_32FC1, u.map_x_, u.map_y_);
  cv::convertMaps(u.map_x_, u.map_y_, u.map1_, u.map2_, CV_16SC2);
  return u;
}

StatusOr<cv::Mat> ImageUndistorter::Remap(const cv::Mat& image, int interpolation) const {
  if (image.cols != distorted_.width || image.rows != distorted_.height)
    return InvalidArgumentError("ImageUndistorter: image is " + std::to_string(image.cols) + "x" +
                                std::to_string(image.rows) + ", the camera " + std::to_string(distorted_.width) + "x" +
                                std::to_string(distorted_.height));
  if (identity()) return image;
  cv::Mat out;
  if (interpolation == cv::INTER_NEAREST)
    cv::remap(image, out, map_x_, map_y_, cv::INTER_NEAREST, cv::BORDER_REPLICATE);
  else cv::remap(image, out, map1_, map2_, interpolation, cv::BORDER_REPLICATE);
  return out;
}

StatusOr<cv::Mat> ImageUndistorter::Undistort(const cv::Mat& image) const { return Remap(image, cv::INTER_CUBIC); }

StatusOr<cv::Mat> ImageUndistorter::UndistortNearest(const cv::Mat& image) const {
  return Remap(image, cv::INTER_NEAREST);
}

}  // namespace prism
