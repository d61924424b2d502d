#include "core/slam/tracker.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <memory>
#include <sstream>

#include <Eigen/Cholesky>
#include <opencv2/imgproc.hpp>

#include "core/slam/tracker_internal.h"
#include "core/util/check.h"

namespace prism {
namespace internal {

// Grey = mean of the three channels, as float.
void ToGrey(const cv::Mat& rgb, cv::Mat* grey) {
  grey->create(rgb.rows, rgb.cols, CV_32F);
  for (int y = 0; y < rgb.rows; ++y) {
    const uint8_t* in = rgb.ptr<uint8_t>(y);
    float* out = grey->ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) out[x] = (in[3 * x] + in[3 * x + 1] + in[3 * x + 2]) * (1.0f / 3.0f);
  }
}

// 2x2 box average (drops an odd last row / column).
void Downsample(const cv::Mat& in, cv::Mat* out) {
  out->create(in.rows / 2, in.cols / 2, CV_32F);
  for (int y = 0; y < out->rows; ++y) {
    const float* a = in.ptr<float>(2 * y);
    const float* b = in.ptr<float>(2 * y + 1);
    float* o = out->ptr<float>(y);
    for (int x = 0; x < out->cols; ++x) o[x] = 0.25f * (a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1]);
  }
}

// J = 128 * I / (box_mean(I) + floor), in place (see TrackerOptions::normalize_shading).
void NormalizeShading(const TrackerOptions& options, cv::Mat* grey, cv::Mat* scratch) {
  if (options.shading_model == ShadingModel::kNone) return;
  const int k = 2 * options.local_mean_radius_px + 1;
  cv::blur(*grey, *scratch, cv::Size(k, k), cv::Point(-1, -1), cv::BORDER_REFLECT);
  const float floor = static_cast<float>(options.local_mean_floor);
  for (int y = 0; y < grey->rows; ++y) {
    float* g = grey->ptr<float>(y);
    const float* m = scratch->ptr<float>(y);
    for (int x = 0; x < grey->cols; ++x) g[x] = 128.0f * g[x] / (m[x] + floor);
  }
}

}  // namespace internal

namespace {

using internal::Downsample;
using internal::NormalizeShading;
using internal::RigLights;
using internal::ToGrey;

constexpr int kNumParams = 8;  // translation (3), rotation (3), affine a, affine b
using Matrix8d = Eigen::Matrix<double, kNumParams, kNumParams>;
using Vector8d = Eigen::Matrix<double, kNumParams, 1>;

// Interleaved (intensity, d/du, d/dv) with central differences (zero gradient on the border).
void WithGradients(const cv::Mat& grey, cv::Mat* out) {
  out->create(grey.rows, grey.cols, CV_32FC3);
  const int w = grey.cols, h = grey.rows;
  for (int y = 0; y < h; ++y) {
    const float* row = grey.ptr<float>(y);
    float* o = out->ptr<float>(y);
    if (y == 0 || y == h - 1) {
      for (int x = 0; x < w; ++x) {
        o[3 * x] = row[x];
        o[3 * x + 1] = 0;
        o[3 * x + 2] = 0;
      }
      continue;
    }
    const float* up = grey.ptr<float>(y - 1);
    const float* down = grey.ptr<float>(y + 1);
    o[0] = row[0];
    o[1] = o[2] = 0;
    for (int x = 1; x < w - 1; ++x) {
      o[3 * x] = row[x];
      o[3 * x + 1] = 0.5f * (row[x + 1] - row[x - 1]);
      o[3 * x + 2] = 0.5f * (down[x] - up[x]);
    }
    o[3 * (w - 1)] = row[w - 1];
    o[3 * (w - 1) + 1] = o[3 * (w - 1) + 2] = 0;
  }
}

struct Bilinear {
  float i, gu, gv;
};

// (u, v) must satisfy 0 <= u < w - 1, 0 <= v < h - 1.
inline Bilinear Sample(const cv::Mat& img, float u, float v) {
  const int x = static_cast<int>(u), y = static_cast<int>(v);
  const float fu = u - x, fv = v - y;
  const float* a = img.ptr<float>(y) + 3 * x;
  const float* b = img.ptr<float>(y + 1) + 3 * x;
  const float w00 = (1 - fu) * (1 - fv), w01 = fu * (1 - fv), w10 = (1 - fu) * fv, w11 = fu * fv;
  return {w00 * a[0] + w01 * a[3] + w10 * b[0] + w11 * b[3], w00 * a[1] + w01 * a[4] + w10 * b[1] + w11 * b[4],
          w00 * a[2] + w01 * a[5] + w10 * b[2] + w11 * b[5]};
}

struct Evaluation {
  Matrix8d hessian = Matrix8d::Zero();
  Vector8d gradient = Vector8d::Zero();
  double energy = 0;  // robust cost, out-of-image points at the Huber cost of the inlier threshold
  int visible = 0;
  int left_out = 0;  // visible points left out of the cost (camera-attached)
  int inliers = 0;
  double inlier_sq_sum = 0;  // raw residuals, grey levels^2
};

struct State {
  Rigid3d frame_from_keyframe;
  double a = 0, b = 0;
};

// Four floats as one SIMD register (a GCC / Clang vector extension; plain code where there is none).
typedef float Float4 __attribute__((vector_size(16)));

inline Float4 Load4(const float* p) {
  Float4 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

// sum_i (x_i y_i) z_i: summed in float in 16 lanes over blocks of 256 points (independent lanes
// hide the adds' latency), the blocks in double.
double TripleSum(const float* x, const float* y, const float* z, int n) {
  double sum = 0;
  for (int begin = 0; begin < n; begin += 256) {
    const int end = std::min(n, begin + 256);
    Float4 a0 = {0, 0, 0, 0}, a1 = a0, a2 = a0, a3 = a0;
    int i = begin;
    for (; i + 16 <= end; i += 16) {
      a0 += Load4(x + i) * Load4(y + i) * Load4(z + i);
      a1 += Load4(x + i + 4) * Load4(y + i + 4) * Load4(z + i + 4);
      a2 += Load4(x + i + 8) * Load4(y + i + 8) * Load4(z + i + 8);
      a3 += Load4(x + i + 12) * Load4(y + i + 12) * Load4(z + i + 12);
    }
    const Float4 a = (a0 + a1) + (a2 + a3);
    float block = (a[0] + a[1]) + (a[2] + a[3]);
    for (; i < end; ++i) block += (x[i] * y[i]) * z[i];
    sum += block;
  }
  return sum;
}

// D: the normal equations as sums over the points, H = sum w j j^T (lower triangle, mirrored),
// g = sum w r j; j7 = -1.
void NormalEquations(int n, internal::TrackerScratch* scratch, Evaluation* evaluation) {
  internal::TrackerScratch& sc = *scratch;
  Evaluation& e = *evaluation;
  const float* w = sc.weight.data();
  const float* j[8];
  for (int k = 0; k < 7; ++k) j[k] = sc.jacobian[k].data();
  for (int a = 0; a < 7; ++a) {
    for (int b = 0; b <= a; ++b) e.hessian(a, b) = TripleSum(w, j[a], j[b], n);
    e.gradient(a) = TripleSum(w, sc.residual.data(), j[a], n);
  }
  std::vector<float>& ones = sc.ones;
  ones.resize(n, 1.0f);  // all ones (never written)
  for (int b = 0; b < 7; ++b) e.hessian(7, b) = -TripleSum(w, j[b], ones.data(), n);
  const double sum_w = TripleSum(w, ones.data(), ones.data(), n);
  const double sum_wr = TripleSum(w, sc.residual.data(), ones.data(), n);
  e.hessian(7, 7) = sum_w;
  e.gradient(7) = -sum_wr;
  for (int a = 0; a < 8; ++a)
    for (int b = a + 1; b < 8; ++b) e.hessian(a, b) = e.hessian(b, a);
}

// The points are processed in passes over arrays, so that the arithmetic vectorises: warp (A),
// bilinear samples (B, scalar gathers), residuals, weights and Jacobians (C), then the normal
// equations as sums over the points (D). `lights`: non-null for ShadingModel::kPredictedShading.
Evaluation Evaluate(const TrackingKeyframe::Level& level, const internal::TrackerPointArrays& pts, const cv::Mat& frame,
                    const State& state, const TrackerOptions& options, const RigLights* lights,
                    internal::TrackerScratch* scratch) {
  internal::TrackerScratch& sc = *scratch;
  const int n = static_cast<int>(pts.ray_x.size());
  for (std::vector<float>* v : {&sc.ys_x, &sc.ys_y, &sc.ys_z, &sc.u, &sc.v, &sc.inside, &sc.intensity, &sc.grad_u,
                                &sc.grad_v, &sc.predicted, &sc.weight, &sc.residual, &sc.point_energy, &sc.inlier_sq})
    v->resize(n);
  for (std::vector<float>& v : sc.jacobian) v.resize(n);

  Evaluation e;
  const Eigen::Matrix3f rotation = state.frame_from_keyframe.RotationMatrix().cast<float>();
  const Eigen::Vector3f translation = state.frame_from_keyframe.translation.cast<float>();
  const float fx = level.camera.fx, fy = level.camera.fy, cx = level.camera.cx, cy = level.camera.cy;
  const float max_u = level.camera.width - 1.001f, max_v = level.camera.height - 1.001f;
  const float scale = std::exp(static_cast<float>(state.a)), offset = static_cast<float>(state.b);
  const float noise_var = 2.0f * static_cast<float>(options.image_noise_sigma * options.image_noise_sigma);
  const float huber = options.huber_threshold, inlier = options.inlier_threshold;
  const double outside_cost = huber * (2 * inlier - huber);

  // A: Y' = R ray + rho t is the point in the frame scaled by rho; it projects where Y does.
  {
    const float r00 = rotation(0, 0), r01 = rotation(0, 1), r02 = rotation(0, 2);
    const float r10 = rotation(1, 0), r11 = rotation(1, 1), r12 = rotation(1, 2);
    const float r20 = rotation(2, 0), r21 = rotation(2, 1), r22 = rotation(2, 2);
    const float tx = translation.x(), ty = translation.y(), tz = translation.z();
    const float* rx = pts.ray_x.data();
    const float* ry = pts.ray_y.data();
    const float* rho = pts.inverse_depth.data();
    float *ys_x = sc.ys_x.data(), *ys_y = sc.ys_y.data(), *ys_z = sc.ys_z.data();
    float *u = sc.u.data(), *v = sc.v.data(), *inside = sc.inside.data();
#pragma omp simd
    for (int i = 0; i < n; ++i) {
      const float x = r00 * rx[i] + r01 * ry[i] + r02 + rho[i] * tx;
      const float y = r10 * rx[i] + r11 * ry[i] + r12 + rho[i] * ty;
      const float z = r20 * rx[i] + r21 * ry[i] + r22 + rho[i] * tz;
      const float inv_z = 1.0f / z;
      const float pu = fx * x * inv_z + cx, pv = fy * y * inv_z + cy;
      ys_x[i] = x;
      ys_y[i] = y;
      ys_z[i] = z;
      u[i] = pu;
      v[i] = pv;
      inside[i] = (z > 1e-6f && pu >= 0 && pv >= 0 && pu < max_u && pv < max_v) ? 1.0f : 0.0f;
    }
  }

  // B: bilinear samples of the frame (and the predicted keyframe grey level) at the visible points.
  for (int i = 0; i < n; ++i) {
    float predicted = pts.intensity[i];
    if (sc.inside[i] == 0.0f) {
      sc.intensity[i] = sc.grad_u[i] = sc.grad_v[i] = 0;
      sc.predicted[i] = predicted;
      continue;
    }
    ++e.visible;
    const Bilinear s = Sample(frame, sc.u[i], sc.v[i]);
    sc.intensity[i] = s.i;
    sc.grad_u[i] = s.gu;
    sc.grad_v[i] = s.gv;
    const TrackingKeyframe::Point& p = level.points[i];
    if (lights != nullptr && p.has_shading) {
      // Predicted grey level at this pose: each light's share scaled by its shading ratio.
      const Eigen::Vector3f ys(sc.ys_x[i], sc.ys_y[i], sc.ys_z[i]);
      const Eigen::Vector3f shading = lights->Shading(ys / p.inverse_depth, rotation * p.normal);
      float grey = 0, mean = lights->floor;
      for (int l = 0; l < 3; ++l) {
        const float k = p.keyframe_shading[l];
        const float ratio = k > 0 ? std::min(shading[l] / k, lights->max_ratio) : 1.0f;
        grey += p.light_share[l] * ratio;
        mean += p.light_share_mean[l] * ratio;
      }
      // The frame's normalised grey level, with its local mean predicted from the same ratios.
      predicted = 128.0f * grey / mean;
    }
    sc.predicted[i] = predicted;
  }

  // C: residuals, variance-normalised Huber weights and Jacobians (zero weight outside the image).
  {
    const float tx = translation.x(), ty = translation.y(), tz = translation.z();
    const float* rho = pts.inverse_depth.data();
    const float* rho_var = pts.inverse_depth_var.data();
    const float *ys_x = sc.ys_x.data(), *ys_y = sc.ys_y.data(), *ys_z = sc.ys_z.data();
    const float *inside = sc.inside.data(), *sample = sc.intensity.data(), *sample_gu = sc.grad_u.data(),
                *sample_gv = sc.grad_v.data(), *predicted = sc.predicted.data(), *keep = pts.keep.data();
    float *weight = sc.weight.data(), *residual = sc.residual.data();
    float *j0 = sc.jacobian[0].data(), *j1 = sc.jacobian[1].data(), *j2 = sc.jacobian[2].data(),
          *j3 = sc.jacobian[3].data(), *j4 = sc.jacobian[4].data(), *j5 = sc.jacobian[5].data(),
          *j6 = sc.jacobian[6].data();
    float *point_energy = sc.point_energy.data(), *inlier_sq = sc.inlier_sq.data();
#pragma omp simd
    for (int i = 0; i < n; ++i) {
      const bool in = (inside[i] != 0.0f) & (keep[i] != 0.0f);
      const float r = sample[i] - (scale * predicted[i] + offset);
      const float inv_zs = 1.0f / ys_z[i];
      // d(u,v)/dY at the true point Y = Y' / rho (z = Y'z / rho).
      const float inv_z = rho[i] * inv_zs;
      const float x_n = ys_x[i] * inv_zs, y_n = ys_y[i] * inv_zs;
      const float gu = sample_gu[i] * fx, gv = sample_gv[i] * fy;
      // g^T dpi/dY = inv_z * (gu, gv, -(gu x_n + gv y_n)).
      const float jx = gu * inv_z, jy = gv * inv_z, jz = -(gu * x_n + gv * y_n) * inv_z;
      // dr/drho = g^T dpi/dY' t, with dpi/dY' = dpi/dY / rho.
      const float dr_drho = (jx * tx + jy * ty + jz * tz) / rho[i];
      const float var = noise_var + dr_drho * dr_drho * rho_var[i];
      const float inv_sigma = 1.0f / std::sqrt(var);
      const float rn = std::abs(r) * inv_sigma;
      const bool is_inlier = in & (rn < inlier);
      inlier_sq[i] = is_inlier ? r * r : -1.0f;
      const float huber_w = std::min(1.0f, huber / rn);  // 1 up to the threshold
      point_energy[i] = rn <= huber ? rn * rn : huber * (2 * rn - huber);
      // Y = (Y' / rho); dY/d(v, w) = [I, -[Y]x].
      const float yx = ys_x[i] / rho[i], yy = ys_y[i] / rho[i], yz = ys_z[i] / rho[i];
      const float w = huber_w / var;
      weight[i] = in ? w : 0.0f;
      residual[i] = in ? r : 0.0f;
      j0[i] = in ? jx : 0.0f;
      j1[i] = in ? jy : 0.0f;
      j2[i] = in ? jz : 0.0f;
      j3[i] = in ? jz * yy - jy * yz : 0.0f;
      j4[i] = in ? jx * yz - jz * yx : 0.0f;
      j5[i] = in ? jy * yx - jx * yy : 0.0f;
      j6[i] = in ? -scale * predicted[i] : 0.0f;
    }
  }
  // The sums in double, in a scalar pass (the visible points' energies, the inliers).
  e.energy = (n - e.visible) * outside_cost;
  for (int i = 0; i < n; ++i) {
    if (sc.inside[i] == 0.0f) continue;
    if (pts.keep[i] == 0.0f) {
      ++e.left_out;
      continue;
    }
    e.energy += sc.point_energy[i];
    if (sc.inlier_sq[i] >= 0) {
      ++e.inliers;
      e.inlier_sq_sum += sc.inlier_sq[i];
    }
  }

  // D: the normal equations.
  NormalEquations(n, &sc, &e);
  return e;
}

State Apply(const State& s, const Vector8d& delta) {
  State out;
  const Eigen::Vector3d w = delta.segment<3>(3);
  const double angle = w.norm();
  const Eigen::Quaterniond dq =
      angle > 1e-12 ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, w / angle)) : Eigen::Quaterniond::Identity();
  out.frame_from_keyframe = Rigid3d(dq, delta.head<3>()) * s.frame_from_keyframe;
  out.a = s.a + delta(6);
  out.b = s.b + delta(7);
  return out;
}

}  // namespace

Status TrackerOptions::Check() const {
  std::ostringstream e;
  if (pyramid_levels < 1 || pyramid_levels > 8)
    e << "TrackerOptions.pyramid_levels = " << pyramid_levels << "; violated: in [1, 8]";
  else if (!(min_gradient >= 0 && min_gradient <= 255))
    e << "TrackerOptions.min_gradient = " << min_gradient << "; violated: in [0, 255]";
  else if (max_points_per_level < 16)
    e << "TrackerOptions.max_points_per_level = " << max_points_per_level << "; violated: >= 16";
  else if (max_iterations < 1 || max_iterations > 100)
    e << "TrackerOptions.max_iterations = " << max_iterations << "; violated: in [1, 100]";
  else if (!(convergence_threshold > 0))
    e << "TrackerOptions.convergence_threshold = " << convergence_threshold << "; violated: > 0";
  else if (!(image_noise_sigma > 0))
    e << "TrackerOptions.image_noise_sigma = " << image_noise_sigma << "; violated: > 0";
  else if (!(huber_threshold > 0)) e << "TrackerOptions.huber_threshold = " << huber_threshold << "; violated: > 0";
  else if (!(inlier_threshold > 0)) e << "TrackerOptions.inlier_threshold = " << inlier_threshold << "; violated: > 0";
  else if (normal_window_radius_px < 1 || normal_window_radius_px > 8)
    e << "TrackerOptions.normal_window_radius_px = " << normal_window_radius_px << "; violated: in [1, 8]";
  else if (!(normal_max_depth_jump > 0 && normal_max_depth_jump <= 1))
    e << "TrackerOptions.normal_max_depth_jump = " << normal_max_depth_jump << "; violated: in (0, 1]";
  else if (!(normal_min_view_cosine >= 0 && normal_min_view_cosine < 1))
    e << "TrackerOptions.normal_min_view_cosine = " << normal_min_view_cosine << "; violated: in [0, 1)";
  else if (!(max_shading_ratio > 1))
    e << "TrackerOptions.max_shading_ratio = " << max_shading_ratio << "; violated: > 1";
  else if (local_mean_radius_px < 1 || local_mean_radius_px > 32)
    e << "TrackerOptions.local_mean_radius_px = " << local_mean_radius_px << "; violated: in [1, 32]";
  else if (!(local_mean_floor > 0)) e << "TrackerOptions.local_mean_floor = " << local_mean_floor << "; violated: > 0";
  else if (!(min_local_mean >= 0 && min_local_mean <= 255))
    e << "TrackerOptions.min_local_mean = " << min_local_mean << "; violated: in [0, 255]";
  else if (!(affine_prior_a >= 0)) e << "TrackerOptions.affine_prior_a = " << affine_prior_a << "; violated: >= 0";
  else if (!(affine_prior_b >= 0)) e << "TrackerOptions.affine_prior_b = " << affine_prior_b << "; violated: >= 0";
  else if (!(min_visible_fraction >= 0 && min_visible_fraction <= 1))
    e << "TrackerOptions.min_visible_fraction = " << min_visible_fraction << "; violated: in [0, 1]";
  else if (!(min_inlier_fraction >= 0 && min_inlier_fraction <= 1))
    e << "TrackerOptions.min_inlier_fraction = " << min_inlier_fraction << "; violated: in [0, 1]";
  else if (!(max_affine_gain > 1)) e << "TrackerOptions.max_affine_gain = " << max_affine_gain << "; violated: > 1";
  else if (!(max_residual_rms > 0)) e << "TrackerOptions.max_residual_rms = " << max_residual_rms << "; violated: > 0";
  else if (camera_attached_min_votes < 0)
    e << "TrackerOptions.camera_attached_min_votes = " << camera_attached_min_votes << "; violated: >= 0";
  else if (!(camera_attached_min_flow_px > 0))
    e << "TrackerOptions.camera_attached_min_flow_px = " << camera_attached_min_flow_px << "; violated: > 0";
  else if (!(camera_attached_residual_ratio > 0 && camera_attached_residual_ratio <= 1))
    e << "TrackerOptions.camera_attached_residual_ratio = " << camera_attached_residual_ratio
      << "; violated: in (0, 1]";
  if (!e.str().empty()) return InvalidArgumentError(e.str());
  return Status::Ok();
}

Tracker::Tracker(const PinholeCamera& camera, const TrackerOptions& options) : camera_(camera), options_(options) {}

StatusOr<Tracker> Tracker::Create(const RigCalibration& rig, const TrackerOptions& options) {
  PRISM_RETURN_IF_ERROR(rig.Check());
  TrackerOptions without_rig = options;
  without_rig.shading_model = ShadingModel::kNone;  // checked below, with the rig
  StatusOr<Tracker> tracker = Create(rig.camera, without_rig);
  if (!tracker.ok()) return tracker.status();
  tracker->options_ = options;
  tracker->has_rig_ = true;
  tracker->rig_ = rig;
  return tracker;
}

StatusOr<Tracker> Tracker::Create(const PinholeCamera& camera, const TrackerOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (options.shading_model == ShadingModel::kPredictedShading)
    return InvalidArgumentError("Tracker: ShadingModel::kPredictedShading needs the rig (Create(RigCalibration, ...))");
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (camera.HasDistortion()) return InvalidArgumentError("Tracker: the camera has distortion; undistort first");
  if ((camera.width >> (options.pyramid_levels - 1)) < 8 || (camera.height >> (options.pyramid_levels - 1)) < 8) {
    std::ostringstream e;
    e << "Tracker: image " << camera.width << "x" << camera.height << " too small for " << options.pyramid_levels
      << " pyramid levels";
    return InvalidArgumentError(e.str());
  }
  return Tracker(camera, options);
}

void Tracker::UpdateKeep() {
  const int min_votes = options_.camera_attached_min_votes;
  for (size_t l = 0; l < keyframe_.levels.size(); ++l) {
    const std::vector<TrackingKeyframe::Point>& points = keyframe_.levels[l].points;
    std::vector<float>& keep = point_arrays_[l].keep;
    for (size_t i = 0; i < points.size(); ++i) {
      const int x = static_cast<int>(points[i].u), y = static_cast<int>(points[i].v);
      const int attached = attached_votes_[l].at<uint8_t>(y, x), moving = moving_votes_[l].at<uint8_t>(y, x);
      keep[i] = attached >= min_votes && attached > moving ? 0.0f : 1.0f;
    }
  }
}

void Tracker::VoteCameraAttached(const Rigid3d& frame_from_keyframe, double a, double b) {
  const Eigen::Matrix3f rotation = frame_from_keyframe.RotationMatrix().cast<float>();
  const Eigen::Vector3f translation = frame_from_keyframe.translation.cast<float>();
  const float scale = std::exp(static_cast<float>(a)), offset = static_cast<float>(b);
  const float min_residual = 2.0f * std::sqrt(2.0f) * static_cast<float>(options_.image_noise_sigma);
  const float ratio = static_cast<float>(options_.camera_attached_residual_ratio);
  for (size_t l = 0; l < keyframe_.levels.size(); ++l) {
    const TrackingKeyframe::Level& level = keyframe_.levels[l];
    const cv::Mat& frame = frame_pyramid_[l];
    const float min_flow = static_cast<float>(options_.camera_attached_min_flow_px) / static_cast<float>(1 << l);
    const float max_u = level.camera.width - 1.001f, max_v = level.camera.height - 1.001f;
    for (const TrackingKeyframe::Point& p : level.points) {
      const Eigen::Vector3f y = rotation * p.ray + p.inverse_depth * translation;
      if (!(y.z() > 1e-6f)) continue;
      const float u = level.camera.fx * y.x() / y.z() + level.camera.cx;
      const float v = level.camera.fy * y.y() / y.z() + level.camera.cy;
      if (!(u >= 0 && v >= 0 && u < max_u && v < max_v)) continue;
      if (std::hypot(u - p.u, v - p.v) < min_flow) continue;
      const float expected = scale * p.intensity + offset;
      const float r_moving = std::abs(Sample(frame, u, v).i - expected);
      const float r_attached = std::abs(Sample(frame, p.u, p.v).i - expected);
      const int x = static_cast<int>(p.u), yy = static_cast<int>(p.v);
      uint8_t& attached = attached_votes_[l].at<uint8_t>(yy, x);
      uint8_t& moving = moving_votes_[l].at<uint8_t>(yy, x);
      if (r_moving > min_residual && r_attached < ratio * r_moving) {
        if (attached < 255) ++attached;
      } else if (moving < 255) {
        ++moving;
      }
    }
  }
  UpdateKeep();
}

StatusOr<TrackingResult> Tracker::Track(const cv::Mat& rgb, const Rigid3d& frame_from_keyframe_guess) {
  if (!has_keyframe_) return FailedPreconditionError("Tracker::Track: no keyframe set");
  if (rgb.type() != CV_8UC3 || rgb.cols != camera_.width || rgb.rows != camera_.height) {
    std::ostringstream e;
    e << "Tracker::Track: the image must be CV_8UC3 " << camera_.width << "x" << camera_.height << ", got " << rgb.cols
      << "x" << rgb.rows << " type " << rgb.type();
    return InvalidArgumentError(e.str());
  }
  const int levels = options_.pyramid_levels;
  grey_pyramid_.resize(levels);
  frame_pyramid_.resize(levels);
  ToGrey(rgb, &grey_pyramid_[0]);
  for (int l = 1; l < levels; ++l) Downsample(grey_pyramid_[l - 1], &grey_pyramid_[l]);
  for (int l = 0; l < levels; ++l) {
    // Normalise after the whole raw pyramid is built (each level from the raw level below).
    NormalizeShading(options_, &grey_pyramid_[l], &local_mean_);
    WithGradients(grey_pyramid_[l], &frame_pyramid_[l]);
  }

  TrackingResult result;
  result.iterations.assign(levels, 0);
  State state;
  state.frame_from_keyframe = frame_from_keyframe_guess;
  Vector8d prior = Vector8d::Zero();
  if (options_.estimate_affine_brightness) {
    prior(6) = options_.affine_prior_a;
    prior(7) = options_.affine_prior_b;
  }
  std::unique_ptr<RigLights> lights;
  if (options_.shading_model == ShadingModel::kPredictedShading) {
    lights = std::make_unique<RigLights>(rig_, static_cast<float>(options_.max_shading_ratio));
    lights->floor = static_cast<float>(options_.local_mean_floor);
  }
  Evaluation current;
  for (int l = levels - 1; l >= 0; --l) {
    const TrackingKeyframe::Level& level = keyframe_.levels[l];
    const cv::Mat& frame = frame_pyramid_[l];
    current = Evaluate(level, point_arrays_[l], frame, state, options_, lights.get(), &scratch_);
    double lambda = 1e-3;
    for (int it = 0; it < options_.max_iterations; ++it) {
      ++result.iterations[l];
      Matrix8d h = current.hessian;
      Vector8d g = current.gradient;
      // Prior on (a, b) towards 0; without affine estimation, (a, b) stay fixed.
      for (int k = 6; k < 8; ++k) {
        if (options_.estimate_affine_brightness) {
          h(k, k) += prior(k);
          g(k) += prior(k) * (k == 6 ? state.a : state.b);
        } else {
          h.row(k).setZero();
          h.col(k).setZero();
          h(k, k) = 1;
          g(k) = 0;
        }
      }
      for (int k = 0; k < kNumParams; ++k) h(k, k) *= 1 + lambda;
      const Vector8d delta = h.ldlt().solve(-g);
      if (!delta.allFinite()) break;
      const State candidate = Apply(state, delta);
      Evaluation next = Evaluate(level, point_arrays_[l], frame, candidate, options_, lights.get(), &scratch_);
      const double prior_energy = [&](const State& s) {
        return options_.estimate_affine_brightness ? prior(6) * s.a * s.a + prior(7) * s.b * s.b : 0.0;
      }(candidate);
      const double current_prior =
          options_.estimate_affine_brightness ? prior(6) * state.a * state.a + prior(7) * state.b * state.b : 0.0;
      if (next.energy + prior_energy < current.energy + current_prior) {
        state = candidate;
        current = std::move(next);
        lambda = std::max(lambda * 0.5, 1e-6);
      } else {
        lambda *= 4;
        if (lambda > 1e6) break;
        continue;
      }
      const double step = delta.head<6>().norm();
      if (step < options_.convergence_threshold) break;
    }
  }

  result.frame_from_keyframe = state.frame_from_keyframe;
  result.affine_a = state.a;
  result.affine_b = state.b;
  const int n = static_cast<int>(keyframe_.levels[0].points.size());
  result.visible_fraction = n > 0 ? double(current.visible) / n : 0.0;
  const int counted = current.visible - current.left_out;
  result.inlier_fraction = counted > 0 ? double(current.inliers) / counted : 0.0;
  result.residual_rms = current.inliers > 0 ? std::sqrt(current.inlier_sq_sum / current.inliers) : 0.0;
  std::ostringstream reason;
  if (!state.frame_from_keyframe.translation.allFinite() || !state.frame_from_keyframe.rotation.coeffs().allFinite())
    reason << "the pose diverged (not finite)";
  else if (result.visible_fraction < options_.min_visible_fraction)
    reason << "only " << result.visible_fraction << " of the keyframe points are visible (min "
           << options_.min_visible_fraction << ")";
  else if (result.inlier_fraction < options_.min_inlier_fraction)
    reason << "only " << result.inlier_fraction << " of the visible points are inliers (min "
           << options_.min_inlier_fraction << ")";
  else if (std::abs(state.a) > std::log(options_.max_affine_gain))
    reason << "contrast gain exp(a) = " << std::exp(state.a) << " outside [1/" << options_.max_affine_gain << ", "
           << options_.max_affine_gain << "]: the frame does not match the keyframe";
  else if (result.residual_rms > options_.max_residual_rms)
    reason << "inlier residual RMS " << result.residual_rms << " grey levels (max " << options_.max_residual_rms << ")";
  result.lost_reason = reason.str();
  result.ok = result.lost_reason.empty();
  if (result.ok && options_.camera_attached_min_votes > 0)
    VoteCameraAttached(state.frame_from_keyframe, state.a, state.b);
  return result;
}

}  // namespace prism
