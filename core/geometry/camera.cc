#include "core/geometry/camera.h"

#include <cmath>
#include <sstream>

namespace prism {

PinholeCamera PinholeCamera::FromFov(int width, int height, double hfov_deg) {
  PinholeCamera c;
  c.width = width;
  c.height = height;
  c.fx = c.fy = 0.5 * width / std::tan(0.5 * hfov_deg * M_PI / 180.0);
  c.cx = 0.5 * (width - 1);
  c.cy = 0.5 * (height - 1);
  return c;
}

Status PinholeCamera::Check() const {
  std::ostringstream err;
  if (width <= 0 || height <= 0 || width > 16384 || height > 16384)
    err << "PinholeCamera: width x height = " << width << "x" << height << "; violated: in [1, 16384]";
  else if (!(fx > 0) || !(fy > 0) || !std::isfinite(fx) || !std::isfinite(fy))
    err << "PinholeCamera: fx = " << fx << ", fy = " << fy << "; violated: finite and > 0";
  else if (!std::isfinite(cx) || !std::isfinite(cy)) err << "PinholeCamera: cx, cy must be finite";
  for (double d : distortion)
    if (!std::isfinite(d)) err << "PinholeCamera: distortion must be finite";
  if (err.str().empty()) return Status::Ok();
  return InvalidArgumentError(err.str());
}

PinholeCamera PinholeCamera::AtPyramidLevel(int level) const {
  PinholeCamera c = *this;
  const double s = 1.0 / (1 << level);
  c.width = width >> level;
  c.height = height >> level;
  c.fx = fx * s;
  c.fy = fy * s;
  // 2x2 averaging: pixel centre x at level l+1 covers x' = 2x + 0.5 at level l.
  c.cx = (cx + 0.5) * s - 0.5;
  c.cy = (cy + 0.5) * s - 0.5;
  return c;
}

bool PinholeCamera::HasDistortion() const {
  for (double d : distortion)
    if (d != 0.0) return true;
  return false;
}

Eigen::Matrix3d PinholeCamera::K() const {
  Eigen::Matrix3d k;
  k << fx, 0, cx, 0, fy, cy, 0, 0, 1;
  return k;
}

namespace {
Eigen::Vector2d Distort(const std::array<double, 5>& d, const Eigen::Vector2d& p) {
  const double x = p.x(), y = p.y();
  const double r2 = x * x + y * y;
  const double radial = 1 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2;
  return {x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x),
          y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y};
}
}  // namespace

Eigen::Vector2d PinholeCamera::Project(const Eigen::Vector3d& p) const {
  Eigen::Vector2d n(p.x() / p.z(), p.y() / p.z());
  if (HasDistortion()) n = Distort(distortion, n);
  return {fx * n.x() + cx, fy * n.y() + cy};
}

Eigen::Vector3d PinholeCamera::Unproject(const Eigen::Vector2d& pixel) const {
  const Eigen::Vector2d d((pixel.x() - cx) / fx, (pixel.y() - cy) / fy);
  Eigen::Vector2d n = d;
  if (HasDistortion()) {
    // Fixed-point iteration, as in OpenCV's undistortPoints.
    for (int i = 0; i < 20; ++i) {
      const Eigen::Vector2d err = Distort(distortion, n) - d;
      n -= err;
      if (err.squaredNorm() < 1e-24) break;
    }
  }
  return {n.x(), n.y(), 1.0};
}

}  // namespace prism
