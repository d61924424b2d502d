#include "core/io/image_io.h"

#include <cmath>
#include <vector>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace prism {
namespace {

StatusOr<cv::Mat> Load(const std::string& path, int flags) {
  cv::Mat m;
  try {
    m = cv::imread(path, flags);
  } catch (const cv::Exception& e) {
    return DataLossError("cannot decode image '" + path + "': " + e.what());
  }
  if (m.empty()) return NotFoundError("cannot read image '" + path + "' (missing or not a decodable image)");
  return m;
}

Status Save(const std::string& path, const cv::Mat& m) {
  const std::vector<int> params = {cv::IMWRITE_PNG_COMPRESSION, kPngCompression};
  bool ok = false;
  try {
    ok = cv::imwrite(path, m, params);
  } catch (const cv::Exception& e) {
    return UnavailableError("cannot write image '" + path + "': " + e.what());
  }
  if (!ok) return UnavailableError("cannot write image '" + path + "'");
  return Status::Ok();
}

}  // namespace

StatusOr<cv::Mat> ReadRgbImage(const std::string& path) {
  PRISM_ASSIGN_OR_RETURN(cv::Mat m, Load(path, cv::IMREAD_UNCHANGED));
  if (m.depth() != CV_8U) return InvalidArgumentError("image '" + path + "' is not 8-bit");
  cv::Mat rgb;
  if (m.channels() == 1) cv::cvtColor(m, rgb, cv::COLOR_GRAY2RGB);
  else if (m.channels() == 3) cv::cvtColor(m, rgb, cv::COLOR_BGR2RGB);
  else if (m.channels() == 4) cv::cvtColor(m, rgb, cv::COLOR_BGRA2RGB);
  else return InvalidArgumentError("image '" + path + "' has " + std::to_string(m.channels()) + " channels");
  return rgb;
}

Status WriteRgbImage(const std::string& path, const cv::Mat& rgb) {
  if (rgb.type() != CV_8UC3) return InvalidArgumentError("WriteRgbImage needs CV_8UC3");
  cv::Mat bgr;
  cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
  return Save(path, bgr);
}

StatusOr<cv::Mat> ReadDepthPng(const std::string& path) {
  PRISM_ASSIGN_OR_RETURN(cv::Mat m, Load(path, cv::IMREAD_UNCHANGED));
  if (m.type() != CV_16UC1) return InvalidArgumentError("depth image '" + path + "' is not 16-bit single-channel");
  cv::Mat depth;
  m.convertTo(depth, CV_32F, 1.0 / kTumDepthScale);
  return depth;
}

Status WriteDepthPng(const std::string& path, const cv::Mat& depth_m) {
  if (depth_m.type() != CV_32FC1) return InvalidArgumentError("WriteDepthPng needs CV_32FC1");
  cv::Mat out(depth_m.size(), CV_16UC1);
  for (int y = 0; y < depth_m.rows; ++y) {
    const float* d = depth_m.ptr<float>(y);
    uint16_t* o = out.ptr<uint16_t>(y);
    for (int x = 0; x < depth_m.cols; ++x) {
      const double v = std::round(d[x] * kTumDepthScale);
      o[x] = (std::isfinite(d[x]) && d[x] > 0 && v <= 65535.0) ? static_cast<uint16_t>(v) : 0;
    }
  }
  return Save(path, out);
}

StatusOr<cv::Mat> ReadNormalPng(const std::string& path) {
  PRISM_ASSIGN_OR_RETURN(cv::Mat m, Load(path, cv::IMREAD_UNCHANGED));
  if (m.type() != CV_16UC3) return InvalidArgumentError("normal map '" + path + "' is not 16-bit 3-channel");
  cv::Mat n(m.size(), CV_32FC3);
  for (int y = 0; y < m.rows; ++y) {
    const cv::Vec3w* s = m.ptr<cv::Vec3w>(y);
    cv::Vec3f* d = n.ptr<cv::Vec3f>(y);
    for (int x = 0; x < m.cols; ++x) {
      // OpenCV stores BGR: file channel R (= x) is s[x][2].
      if (s[x][0] == 0 && s[x][1] == 0 && s[x][2] == 0) {
        d[x] = cv::Vec3f(0, 0, 0);
        continue;
      }
      cv::Vec3f v(s[x][2] / 65535.f * 2.f - 1.f, s[x][1] / 65535.f * 2.f - 1.f, s[x][0] / 65535.f * 2.f - 1.f);
      const float len = std::sqrt(v.dot(v));
      d[x] = len > 0 ? v / len : cv::Vec3f(0, 0, 0);
    }
  }
  return n;
}

Status WriteNormalPng(const std::string& path, const cv::Mat& normals) {
  if (normals.type() != CV_32FC3) return InvalidArgumentError("WriteNormalPng needs CV_32FC3");
  cv::Mat out(normals.size(), CV_16UC3);
  auto enc = [](float v) {
    return static_cast<uint16_t>(std::lround(std::min(1.f, std::max(-1.f, v)) * 0.5 * 65535.0 + 0.5 * 65535.0));
  };
  for (int y = 0; y < normals.rows; ++y) {
    const cv::Vec3f* s = normals.ptr<cv::Vec3f>(y);
    cv::Vec3w* d = out.ptr<cv::Vec3w>(y);
    for (int x = 0; x < normals.cols; ++x) {
      if (s[x].dot(s[x]) < 1e-12f || !std::isfinite(s[x][0])) {
        d[x] = cv::Vec3w(0, 0, 0);
        continue;
      }
      d[x] = cv::Vec3w(enc(s[x][2]), enc(s[x][1]), enc(s[x][0]));
    }
  }
  return Save(path, out);
}

StatusOr<cv::Mat> ReadMaskPng(const std::string& path) {
  PRISM_ASSIGN_OR_RETURN(cv::Mat m, Load(path, cv::IMREAD_UNCHANGED));
  if (m.type() != CV_8UC1) return InvalidArgumentError("mask '" + path + "' is not 8-bit single-channel");
  return m;
}

Status WriteMaskPng(const std::string& path, const cv::Mat& mask) {
  if (mask.type() != CV_8UC1) return InvalidArgumentError("WriteMaskPng needs CV_8UC1");
  return Save(path, mask);
}

}  // namespace prism
