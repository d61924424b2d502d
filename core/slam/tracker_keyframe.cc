// Tracker::SetKeyframe: the keyframe image's pyramid and the selection of the tracked points
// (tracker.cc has the tracking).
#include <algorithm>
#include <cmath>
#include <memory>
#include <sstream>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <opencv2/imgproc.hpp>

#include "core/slam/image_bytes.h"
#include "core/slam/tracker.h"
#include "core/slam/tracker_internal.h"

namespace prism {
namespace {

using internal::Downsample;
using internal::NormalizeShading;
using internal::RigLights;
using internal::ToGrey;

// Inverse depth and variance at the next level: the mean of the valid pixels of each 2x2 block;
// blocks straddling a depth discontinuity (spread > 10%) become invalid.
void DownsampleInverseDepth(const cv::Mat& idepth, const cv::Mat& var, cv::Mat* idepth_out, cv::Mat* var_out) {
  idepth_out->create(idepth.rows / 2, idepth.cols / 2, CV_32F);
  var_out->create(idepth.rows / 2, idepth.cols / 2, CV_32F);
  for (int y = 0; y < idepth_out->rows; ++y) {
    for (int x = 0; x < idepth_out->cols; ++x) {
      float sum = 0, sum_var = 0, lo = 1e30f, hi = 0;
      int n = 0;
      for (int dy = 0; dy < 2; ++dy) {
        for (int dx = 0; dx < 2; ++dx) {
          const float d = idepth.at<float>(2 * y + dy, 2 * x + dx);
          if (!(d > 0)) continue;
          sum += d;
          sum_var += var.at<float>(2 * y + dy, 2 * x + dx);
          lo = std::min(lo, d);
          hi = std::max(hi, d);
          ++n;
        }
      }
      const bool valid = n > 0 && hi <= 1.1f * lo;
      idepth_out->at<float>(y, x) = valid ? sum / n : 0.0f;
      var_out->at<float>(y, x) = valid ? sum_var / (n * n) : 0.0f;
    }
  }
}

// 2x2 box average of an RGB image (CV_32FC3; drops an odd last row / column).
void DownsampleRgb(const cv::Mat& in, cv::Mat* out) {
  out->create(in.rows / 2, in.cols / 2, CV_32FC3);
  for (int y = 0; y < out->rows; ++y) {
    const float* a = in.ptr<float>(2 * y);
    const float* b = in.ptr<float>(2 * y + 1);
    float* o = out->ptr<float>(y);
    for (int x = 0; x < out->cols; ++x)
      for (int c = 0; c < 3; ++c)
        o[3 * x + c] = 0.25f * (a[6 * x + c] + a[6 * x + 3 + c] + b[6 * x + c] + b[6 * x + 3 + c]);
  }
}

// Unit normal (towards the camera) of the plane fitted to the back-projected depth map in a
// (2 radius + 1)^2 window around (x, y); false at depth edges (a valid depth more than `max_jump`
// relative from the centre's, or a missing one), with too few samples, or at grazing view.
bool FitNormal(const cv::Mat& idepth, const PinholeCamera& camera, int x, int y, const TrackerOptions& options,
               Eigen::Vector3f* normal) {
  const int r = options.normal_window_radius_px;
  if (x - r < 0 || y - r < 0 || x + r >= idepth.cols || y + r >= idepth.rows) return false;
  const float z0 = 1.0f / idepth.at<float>(y, x);
  const float max_jump = static_cast<float>(options.normal_max_depth_jump);
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  Eigen::Matrix3d sum_sq = Eigen::Matrix3d::Zero();
  int n = 0;
  for (int v = y - r; v <= y + r; ++v) {
    for (int u = x - r; u <= x + r; ++u) {
      const float d = idepth.at<float>(v, u);
      if (!(d > 0) || !std::isfinite(d)) return false;
      const float z = 1.0f / d;
      if (std::abs(z - z0) > max_jump * z0) return false;
      const Eigen::Vector3d p((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z);
      sum += p;
      sum_sq += p * p.transpose();
      ++n;
    }
  }
  if (n < 6) return false;
  const Eigen::Vector3d mean = sum / n;
  const Eigen::Matrix3d cov = sum_sq / n - mean * mean.transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
  eig.computeDirect(cov);
  Eigen::Vector3d nrm = eig.eigenvectors().col(0);
  const Eigen::Vector3d ray((x - camera.cx) / camera.fx, (y - camera.cy) / camera.fy, 1.0);
  if (nrm.dot(ray) > 0) nrm = -nrm;
  if (-nrm.dot(ray.normalized()) < options.normal_min_view_cosine) return false;
  *normal = nrm.cast<float>();
  return true;
}

}  // namespace

Status Tracker::SetKeyframe(const cv::Mat& rgb, const InverseDepthMap& depth) {
  const cv::Size size(camera_.width, camera_.height);
  if (rgb.type() != CV_8UC3 || rgb.size() != size)
    return InvalidArgumentError("Tracker::SetKeyframe: the image must be CV_8UC3 of the camera's size");
  if (depth.inverse_depth.type() != CV_32F || depth.inverse_depth.size() != size)
    return InvalidArgumentError("Tracker::SetKeyframe: inverse_depth must be CV_32F of the camera's size");
  cv::Mat idepth = depth.inverse_depth, var;
  if (depth.variance.empty()) {
    var = 1e-4f * idepth.mul(idepth);
  } else {
    if (depth.variance.type() != CV_32F || depth.variance.size() != size)
      return InvalidArgumentError("Tracker::SetKeyframe: variance must be empty or CV_32F of the camera's size");
    var = depth.variance;
  }

  TrackingKeyframe kf;
  kf.levels.resize(options_.pyramid_levels);
  const bool predict = options_.shading_model == ShadingModel::kPredictedShading;
  // Grey share per light of a colour: (1/3) 1^T X diag(X^-1 c).
  Eigen::Matrix3f demix = Eigen::Matrix3f::Identity();
  Eigen::RowVector3f grey_of_light = Eigen::RowVector3f::Constant(1.0f / 3);
  std::unique_ptr<RigLights> lights;
  if (predict) {
    demix = rig_.crosstalk.inverse().cast<float>();
    grey_of_light = rig_.crosstalk.colwise().sum().cast<float>() / 3.0f;
    lights = std::make_unique<RigLights>(rig_, static_cast<float>(options_.max_shading_ratio));
    lights->floor = static_cast<float>(options_.local_mean_floor);
  }
  // The image's own pyramid (it depends on nothing else: the options and the rig are fixed): kept
  // from the previous call when the image is the same, byte for byte (a refresh with new depth).
  // A refusal below leaves the tracker as it was: the previous image's pyramid and votes are put back.
  const bool new_image = !SameImageBytes(keyframe_image_, rgb);
  cv::Mat previous_image;
  std::vector<KeyframeImageLevel> previous_levels;
  std::vector<cv::Mat> previous_attached, previous_moving;
  if (new_image) {
    previous_image = std::move(keyframe_image_);
    previous_levels = std::move(keyframe_image_levels_);
    previous_attached = std::move(attached_votes_);
    previous_moving = std::move(moving_votes_);
    BuildKeyframeImage(rgb, predict, demix, grey_of_light);
  }
  for (int l = 0; l < options_.pyramid_levels; ++l) {
    TrackingKeyframe::Level& level = kf.levels[l];
    level.camera = camera_.AtPyramidLevel(l);
    if (l > 0) {
      cv::Mat idepth_next, var_next;
      DownsampleInverseDepth(idepth, var, &idepth_next, &var_next);
      idepth = idepth_next;
      var = var_next;
    }
    const KeyframeImageLevel& im = keyframe_image_levels_[static_cast<size_t>(l)];
    const cv::Mat& raw = im.raw;
    const cv::Mat& colour = im.colour;
    const cv::Mat& bright = im.bright;
    const cv::Mat* share_mean = im.share_mean;
    level.grey = im.grey;  // shared, read only
    // Grid selection: the strongest gradient per cell, above the threshold, with valid depth.
    const int w = level.grey.cols, h = level.grey.rows;
    const int cell = std::max(1, static_cast<int>(std::ceil(std::sqrt(double(w) * h / options_.max_points_per_level))));
    const float min_g2 = static_cast<float>(options_.min_gradient * options_.min_gradient);
    const float min_mean = static_cast<float>(options_.min_local_mean);
    for (int cy0 = 1; cy0 < h - 1; cy0 += cell) {
      for (int cx0 = 1; cx0 < w - 1; cx0 += cell) {
        float best = min_g2;
        int bx = -1, by = -1;
        for (int y = cy0; y < std::min(cy0 + cell, h - 1); ++y) {
          const float* row = level.grey.ptr<float>(y);
          const float* up = level.grey.ptr<float>(y - 1);
          const float* down = level.grey.ptr<float>(y + 1);
          const float* d = idepth.ptr<float>(y);
          for (int x = cx0; x < std::min(cx0 + cell, w - 1); ++x) {
            if (!(d[x] > 0) || !std::isfinite(d[x]) || bright.at<float>(y, x) < min_mean) continue;
            const float gx = 0.5f * (row[x + 1] - row[x - 1]), gy = 0.5f * (down[x] - up[x]);
            const float g2 = gx * gx + gy * gy;
            if (g2 >= best) {
              best = g2;
              bx = x;
              by = y;
            }
          }
        }
        if (bx < 0) continue;
        TrackingKeyframe::Point p;
        p.u = bx;
        p.v = by;
        p.inverse_depth = idepth.at<float>(by, bx);
        const float v = var.at<float>(by, bx);
        p.inverse_depth_var = std::isfinite(v) && v > 0 ? v : 1e-4f * p.inverse_depth * p.inverse_depth;
        p.intensity = level.grey.at<float>(by, bx);
        p.ray = Eigen::Vector3f((bx - level.camera.cx) / level.camera.fx, (by - level.camera.cy) / level.camera.fy, 1);
        if (predict && FitNormal(idepth, level.camera, bx, by, options_, &p.normal)) {
          p.keyframe_shading = lights->Shading(p.ray / p.inverse_depth, p.normal);
          const float strongest = p.keyframe_shading.maxCoeff();
          if (strongest > 0) {
            // Lights giving (almost) nothing in the keyframe keep ratio 1 (marked by shading 0).
            for (int l = 0; l < 3; ++l)
              if (p.keyframe_shading[l] < 0.05f * strongest) p.keyframe_shading[l] = 0;
            const cv::Vec3f c = colour.at<cv::Vec3f>(by, bx);
            // Channels R, G, B, as the crosstalk's rows.
            const Eigen::Vector3f band = demix * Eigen::Vector3f(c[0], c[1], c[2]);
            p.light_share = grey_of_light.transpose().cwiseProduct(band);
            for (int l = 0; l < 3; ++l) p.light_share_mean[l] = share_mean[l].at<float>(by, bx);
            // The shares must add up to the raw grey level (not so where the camera saturated).
            p.has_shading = std::abs(p.light_share.sum() - raw.at<float>(by, bx)) < 1.0f;
          }
        }
        level.points.push_back(p);
      }
    }
  }
  constexpr int kMinPoints = 10;
  for (int l = 0; l < options_.pyramid_levels; ++l) {
    if (static_cast<int>(kf.levels[l].points.size()) < kMinPoints) {
      std::ostringstream e;
      e << "Tracker::SetKeyframe: only " << kf.levels[l].points.size() << " points at pyramid level " << l << " (need "
        << kMinPoints << "): too little texture or depth";
      if (new_image) {
        keyframe_image_ = std::move(previous_image);
        keyframe_image_levels_ = std::move(previous_levels);
        attached_votes_ = std::move(previous_attached);
        moving_votes_ = std::move(previous_moving);
      }
      return FailedPreconditionError(e.str());
    }
  }
  point_arrays_.assign(kf.levels.size(), internal::TrackerPointArrays());
  for (size_t l = 0; l < kf.levels.size(); ++l) {
    internal::TrackerPointArrays& a = point_arrays_[l];
    for (const TrackingKeyframe::Point& p : kf.levels[l].points) {
      a.ray_x.push_back(p.ray.x());
      a.ray_y.push_back(p.ray.y());
      a.inverse_depth.push_back(p.inverse_depth);
      a.inverse_depth_var.push_back(p.inverse_depth_var);
      a.intensity.push_back(p.intensity);
    }
    a.keep.assign(a.ray_x.size(), 1.0f);
  }
  keyframe_ = std::move(kf);
  has_keyframe_ = true;
  if (options_.camera_attached_min_votes > 0) {
    if (attached_votes_.size() != keyframe_.levels.size()) {
      attached_votes_.assign(keyframe_.levels.size(), cv::Mat());
      moving_votes_.assign(keyframe_.levels.size(), cv::Mat());
      for (size_t l = 0; l < keyframe_.levels.size(); ++l) {
        const cv::Size size(keyframe_.levels[l].camera.width, keyframe_.levels[l].camera.height);
        attached_votes_[l] = cv::Mat::zeros(size, CV_8U);
        moving_votes_[l] = cv::Mat::zeros(size, CV_8U);
      }
    }
    UpdateKeep();
  }
  return Status::Ok();
}

void Tracker::BuildKeyframeImage(const cv::Mat& rgb, bool predict, const Eigen::Matrix3f& demix,
                                 const Eigen::RowVector3f& grey_of_light) {
  attached_votes_.clear();
  moving_votes_.clear();
  keyframe_image_ = rgb.clone();
  keyframe_image_levels_.assign(static_cast<size_t>(options_.pyramid_levels), KeyframeImageLevel());
  const int k = 2 * options_.local_mean_radius_px + 1;
  for (int l = 0; l < options_.pyramid_levels; ++l) {
    KeyframeImageLevel& im = keyframe_image_levels_[static_cast<size_t>(l)];
    if (l == 0) {
      ToGrey(rgb, &im.raw);
      if (predict) rgb.convertTo(im.colour, CV_32FC3);
    } else {
      const KeyframeImageLevel& finer = keyframe_image_levels_[static_cast<size_t>(l - 1)];
      Downsample(finer.raw, &im.raw);
      if (predict) DownsampleRgb(finer.colour, &im.colour);
    }
    im.grey = im.raw.clone();
    NormalizeShading(options_, &im.grey, &local_mean_);
    // kPredictedShading: per pixel, each light's share of the raw grey level, box-averaged as the
    // local mean (the frame's local mean is predicted from these).
    if (predict) {
      cv::Mat share[3];
      for (int c = 0; c < 3; ++c) share[c].create(im.raw.size(), CV_32F);
      for (int y = 0; y < im.raw.rows; ++y) {
        const cv::Vec3f* c = im.colour.ptr<cv::Vec3f>(y);
        for (int x = 0; x < im.raw.cols; ++x) {
          const Eigen::Vector3f band = demix * Eigen::Vector3f(c[x][0], c[x][1], c[x][2]);
          for (int j = 0; j < 3; ++j) share[j].at<float>(y, x) = grey_of_light[j] * band[j];
        }
      }
      for (int c = 0; c < 3; ++c)
        cv::blur(share[c], im.share_mean[c], cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
    }
    cv::blur(im.raw, im.bright, cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
  }
}

}  // namespace prism
