// Image files of a sequence. In memory: colour images are RGB (CV_8UC3, channel 0 = red), depth is
// CV_32F metres (0 = no surface), normal maps are CV_32FC3 unit vectors in the camera frame
// (x right, y down, z forward; (0,0,0) = no surface), masks are CV_8U.
//
// On disk:
//   depth:   16-bit PNG, value = round(depth_m * 5000) (TUM RGB-D), 0 = invalid; 0.2 mm steps, <= 13.1 m.
//   normals: 16-bit 3-channel PNG, channel k (R,G,B order = x,y,z) = round((n_k + 1) / 2 * 65535);
//            (0,0,0) = no surface. Step 3e-5, i.e. under 0.003 degrees. Viewable as a normal map.
//   mask:    8-bit PNG, 255 = object, 64 = other surface (ground), 0 = no surface.
#pragma once

#include <string>

#include <opencv2/core.hpp>

#include "core/util/status.h"

namespace prism {

constexpr double kTumDepthScale = 5000.0;  // depth PNG units per metre
constexpr uint8_t kMaskObject = 255;
constexpr uint8_t kMaskBackground = 64;

StatusOr<cv::Mat> ReadRgbImage(const std::string& path);  // any 8-bit colour or grey image -> RGB
Status WriteRgbImage(const std::string& path, const cv::Mat& rgb);
StatusOr<cv::Mat> ReadDepthPng(const std::string& path);
Status WriteDepthPng(const std::string& path, const cv::Mat& depth_m);
StatusOr<cv::Mat> ReadNormalPng(const std::string& path);
Status WriteNormalPng(const std::string& path, const cv::Mat& normals);
StatusOr<cv::Mat> ReadMaskPng(const std::string& path);
Status WriteMaskPng(const std::string& path, const cv::Mat& mask);

// PNG compression level used by the writers (0-9). Level 1 is ~4x faster than OpenCV's default 3
// and ~10% larger.
constexpr int kPngCompression = 1;

}  // namespace prism
