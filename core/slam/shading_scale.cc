#include "core/slam/shading_scale.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>

#include <Eigen/Dense>

#include "core/slam/keyframe_ba.h"

namespace prism {

Status ShadingScaleOptions::Check() const {
  std::ostringstream e;
  if (!(cell_px >= 1 && cell_px <= 64)) e << "ShadingScaleOptions.cell_px = " << cell_px << "; violated: in [1, 64]";
  else if (!(min_gradient >= 0)) e << "ShadingScaleOptions.min_gradient = " << min_gradient << "; violated: >= 0";
  else if (!(min_level >= 0 && min_level <= 255))
    e << "ShadingScaleOptions.min_level = " << min_level << "; violated: in [0, 255]";
  else if (!(saturation_level > 0 && saturation_level <= 255))
    e << "ShadingScaleOptions.saturation_level = " << saturation_level << "; violated: in (0, 255]";
  else if (!(min_band_fraction >= 0 && min_band_fraction < 1))
    e << "ShadingScaleOptions.min_band_fraction = " << min_band_fraction << "; violated: in [0, 1)";
  else if (!(min_view_cosine >= -1 && min_view_cosine < 1))
    e << "ShadingScaleOptions.min_view_cosine = " << min_view_cosine << "; violated: in [-1, 1)";
  else if (!(scan_steps >= 1)) e << "ShadingScaleOptions.scan_steps = " << scan_steps << "; violated: >= 1";
  else if (!(scan_factor > 1)) e << "ShadingScaleOptions.scan_factor = " << scan_factor << "; violated: > 1";
  else if (!(initial_metres_per_unit > 0) || !std::isfinite(initial_metres_per_unit))
    e << "ShadingScaleOptions.initial_metres_per_unit = " << initial_metres_per_unit << "; violated: > 0";
  else if (!(max_iterations >= 1 && max_iterations <= 200))
    e << "ShadingScaleOptions.max_iterations = " << max_iterations << "; violated: in [1, 200]";
  else if (!(huber_sigmas > 0)) e << "ShadingScaleOptions.huber_sigmas = " << huber_sigmas << "; violated: > 0";
  else if (!(outlier_sigmas > huber_sigmas))
    e << "ShadingScaleOptions.outlier_sigmas = " << outlier_sigmas << "; violated: > huber_sigmas";
  else if (!(border_px >= 2)) e << "ShadingScaleOptions.border_px = " << border_px << "; violated: >= 2";
  else if (!(min_points >= 10)) e << "ShadingScaleOptions.min_points = " << min_points << "; violated: >= 10";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

using Vector6d = Eigen::Matrix<double, 6, 1>;

struct ScalePoint {
  Eigen::Vector3d x = Eigen::Vector3d::Zero();       // in the keyframe, depth units
  Eigen::Vector3d bands = Eigen::Vector3d::Zero();   // demixed keyframe colour X^-1 c, grey levels
  Eigen::Vector3d m = Eigen::Vector3d::Zero();       // rho n at the current k (keyframe frame)
  Eigen::Vector3d m_plus = Eigen::Vector3d::Zero();  // ... at k * exp(+h), k * exp(-h): d / d log k
  Eigen::Vector3d m_minus = Eigen::Vector3d::Zero();
};

// S(p): rows E_l(p) L_l(p)^T.
Eigen::Matrix3d LightingMatrix(const RigCalibration& rig, const Eigen::Vector3d& p) {
  Eigen::Matrix3d s;
  for (int l = 0; l < 3; ++l) {
    Eigen::Vector3d to_light;
    double irradiance;
    rig.lights[l].Illuminate(p, &to_light, &irradiance);
    s.row(l) = irradiance * to_light.transpose();
  }
  return s;
}

// rho n from the demixed bands at metric point p (one-pixel photometric stereo, grey albedo).
Eigen::Vector3d ImpliedNormal(const RigCalibration& rig, const Eigen::Vector3d& p, const Eigen::Vector3d& bands) {
  return LightingMatrix(rig, p).inverse() * bands;
}

// Predicted grey level of the frame for a keyframe point with rho n = m (keyframe frame), seen at
// q = R x + t (depth units) with k metres per unit.
double PredictGrey(const RigCalibration& rig, const Eigen::Vector3d& q, const Eigen::Vector3d& m_in_frame, double k) {
  const Eigen::Vector3d p = k * q;
  Eigen::Vector3d s;
  for (int l = 0; l < 3; ++l) {
    Eigen::Vector3d to_light;
    double irradiance;
    rig.lights[l].Illuminate(p, &to_light, &irradiance);
    s[l] = irradiance * std::max(0.0, m_in_frame.dot(to_light));
  }
  return (rig.crosstalk * s).mean();
}

float Bilinear(const cv::Mat& m, double x, double y) {
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const float ax = static_cast<float>(x - x0), ay = static_cast<float>(y - y0);
  const float* r0 = m.ptr<float>(y0);
  const float* r1 = m.ptr<float>(y0 + 1);
  return (1 - ay) * ((1 - ax) * r0[x0] + ax * r0[x0 + 1]) + ay * ((1 - ax) * r1[x0] + ax * r1[x0 + 1]);
}

struct FrameImages {
  cv::Mat grey, grad_x, grad_y;  // CV_32F
};

FrameImages MakeFrameImages(const cv::Mat& rgb) {
  FrameImages f;
  f.grey = MeanOfChannels(rgb);
  f.grad_x = cv::Mat::zeros(f.grey.size(), CV_32F);
  f.grad_y = cv::Mat::zeros(f.grey.size(), CV_32F);
  for (int y = 1; y + 1 < f.grey.rows; ++y) {
    const float* r = f.grey.ptr<float>(y);
    const float* up = f.grey.ptr<float>(y - 1);
    const float* down = f.grey.ptr<float>(y + 1);
    float* gx = f.grad_x.ptr<float>(y);
    float* gy = f.grad_y.ptr<float>(y);
    for (int x = 1; x + 1 < f.grey.cols; ++x) {
      gx[x] = 0.5f * (r[x + 1] - r[x - 1]);
      gy[x] = 0.5f * (down[x] - up[x]);
    }
  }
  return f;
}

Rigid3d ApplyLeft(const Vector6d& delta, const Rigid3d& pose) {
  return Rigid3d(ExpSo3(delta.tail<3>()), delta.head<3>()) * pose;
}

}  // namespace

StatusOr<ShadingScaleResult> EstimateShadingScale(const RigCalibration& rig, const cv::Mat& keyframe_rgb,
                                                  const cv::Mat& keyframe_inverse_depth,
                                                  const std::vector<ShadingScaleFrame>& frames,
                                                  const ShadingScaleOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(rig.Check());
  const PinholeCamera& cam = rig.camera;
  if (cam.HasDistortion()) return InvalidArgumentError("EstimateShadingScale: the camera has distortion");
  if (keyframe_rgb.type() != CV_8UC3 || keyframe_rgb.cols != cam.width || keyframe_rgb.rows != cam.height)
    return InvalidArgumentError("EstimateShadingScale: keyframe_rgb must be CV_8UC3 of the camera's size");
  if (keyframe_inverse_depth.type() != CV_32F || keyframe_inverse_depth.size() != keyframe_rgb.size())
    return InvalidArgumentError("EstimateShadingScale: keyframe_inverse_depth must be CV_32F of the image's size");
  if (frames.empty()) return InvalidArgumentError("EstimateShadingScale: no frames");
  for (const ShadingScaleFrame& f : frames) {
    if (f.rgb.type() != CV_8UC3 || f.rgb.size() != keyframe_rgb.size())
      return InvalidArgumentError("EstimateShadingScale: every frame must be CV_8UC3 of the keyframe's size");
  }
  const Eigen::Matrix3d demix = rig.crosstalk.inverse();

  // Points: per cell the strongest grey gradient among pixels with a depth, unsaturated, bright enough,
  // lit by all three lights.
  const cv::Mat kf_grey = MeanOfChannels(keyframe_rgb);
  std::vector<ScalePoint> points;
  int candidates = 0, facing = 0;
  const double k0 = options.initial_metres_per_unit;
  const int b = options.border_px;
  for (int cy = b; cy < cam.height - b; cy += options.cell_px) {
    for (int cx = b; cx < cam.width - b; cx += options.cell_px) {
      int bx = -1, by = -1;
      double best = options.min_gradient * options.min_gradient;
      for (int y = cy; y < std::min(cy + options.cell_px, cam.height - b); ++y) {
        const float* id = keyframe_inverse_depth.ptr<float>(y);
        const cv::Vec3b* c = keyframe_rgb.ptr<cv::Vec3b>(y);
        for (int x = cx; x < std::min(cx + options.cell_px, cam.width - b); ++x) {
          if (!(id[x] > 0) || !std::isfinite(id[x])) continue;
          if (kf_grey.at<float>(y, x) < options.min_level) continue;
          if (std::max({c[x][0], c[x][1], c[x][2]}) >= options.saturation_level) continue;
          const double gx = 0.5 * (kf_grey.at<float>(y, x + 1) - kf_grey.at<float>(y, x - 1));
          const double gy = 0.5 * (kf_grey.at<float>(y + 1, x) - kf_grey.at<float>(y - 1, x));
          const double g2 = gx * gx + gy * gy;
          if (g2 >= best) best = g2, bx = x, by = y;
        }
      }
      if (bx < 0) continue;
      const cv::Vec3b c = keyframe_rgb.at<cv::Vec3b>(by, bx);
      ScalePoint p;
      p.bands = demix * Eigen::Vector3d(c[0], c[1], c[2]);
      const double strongest = p.bands.maxCoeff();
      if (!(strongest > 0) || p.bands.minCoeff() < options.min_band_fraction * strongest) continue;
      const Eigen::Vector3d ray = cam.Unproject(Eigen::Vector2d(bx, by));
      p.x = ray / ray.z() / keyframe_inverse_depth.at<float>(by, bx);
      ++candidates;
      const Eigen::Vector3d m = ImpliedNormal(rig, k0 * p.x, p.bands);
      if (m.dot(-p.x.normalized()) < options.min_view_cosine * m.norm()) continue;
      ++facing;
      points.push_back(p);
    }
  }
  ShadingScaleResult result;
  result.grey_albedo_fraction = candidates > 0 ? static_cast<double>(facing) / candidates : 0.0;
  if (static_cast<int>(points.size()) < options.min_points) {
    std::ostringstream e;
    e << "EstimateShadingScale: " << points.size() << " usable points (" << candidates << " lit in all bands), need "
      << options.min_points;
    return FailedPreconditionError(e.str());
  }

  std::vector<FrameImages> images;
  images.reserve(frames.size());
  for (const ShadingScaleFrame& f : frames) images.push_back(MakeFrameImages(f.rgb));
  std::vector<Rigid3d> poses;
  for (const ShadingScaleFrame& f : frames) poses.push_back(f.frame_from_keyframe);

  const double h = 1e-4;  // log k step for the numerical derivative
  // Each point's m at k (what the residuals read); m at k exp(+-h) only where the derivative is taken
  // (set_scale_derivative, once per linearisation: the scan and the trial steps do not need it).
  auto set_scale = [&](double k) {
    for (ScalePoint& p : points) p.m = ImpliedNormal(rig, k * p.x, p.bands);
  };
  auto set_scale_derivative = [&](double k) {
    for (ScalePoint& p : points) {
      p.m_plus = ImpliedNormal(rig, k * std::exp(h) * p.x, p.bands);
      p.m_minus = ImpliedNormal(rig, k * std::exp(-h) * p.x, p.bands);
    }
  };
  auto inside = [&](const Eigen::Vector2d& uv) {
    return uv.x() >= b && uv.y() >= b && uv.x() < cam.width - 1 - b && uv.y() < cam.height - 1 - b;
  };
  // Residuals at (k, poses) with the model's m cached for k; appends |r| to `abs_res` when given.
  auto residuals = [&](double k, const std::vector<Rigid3d>& ps, std::vector<double>* abs_res) {
    for (size_t f = 0; f < ps.size(); ++f) {
      const Eigen::Matrix3d r = ps[f].RotationMatrix();
      for (const ScalePoint& p : points) {
        const Eigen::Vector3d q = r * p.x + ps[f].translation;
        if (q.z() <= 0) continue;
        const Eigen::Vector2d uv = cam.Project(q);
        if (!inside(uv)) continue;
        abs_res->push_back(std::abs(Bilinear(images[f].grey, uv.x(), uv.y()) - PredictGrey(rig, q, r * p.m, k)));
      }
    }
  };
  auto robust_cost = [&](const std::vector<double>& abs_res, double huber, double cut) {
    double cost = 0;
    for (double a : abs_res) {
      const double e = std::min(a, cut);
      cost += e <= huber ? 0.5 * e * e : huber * (e - 0.5 * huber);
    }
    return cost;
  };

  // Coarse scan of k at the given poses: the cost is the robust one with a sigma from the median
  // absolute residual at each k (a wrong k inflates every residual).
  double k = k0;
  if (options.scan_steps > 1) {
    double best_cost = std::numeric_limits<double>::infinity();
    for (int i = 0; i < options.scan_steps; ++i) {
      const double kk = k0 * std::exp(std::log(options.scan_factor) * (2.0 * i / (options.scan_steps - 1) - 1.0));
      set_scale(kk);
      std::vector<double> a;
      residuals(kk, poses, &a);
      if (a.size() < static_cast<size_t>(options.min_points)) continue;
      std::nth_element(a.begin(), a.begin() + a.size() / 2, a.end());
      const double med = a[a.size() / 2];
      if (med < best_cost) best_cost = med, k = kk;
    }
  }
  set_scale(k);
  std::vector<double> start;
  residuals(k, poses, &start);
  if (start.size() < static_cast<size_t>(options.min_points))
    return FailedPreconditionError("EstimateShadingScale: too few points project into the frames");
  std::nth_element(start.begin(), start.begin() + start.size() / 2, start.end());
  const double sigma = std::max(0.5, 1.4826 * start[start.size() / 2]);
  const double huber = options.huber_sigmas * sigma, cut = options.outlier_sigmas * sigma;
  result.residual_sigma = sigma;

  const int nf = static_cast<int>(frames.size());
  const int dim = 6 * nf + 1;
  auto evaluate = [&](double kk, const std::vector<Rigid3d>& ps) {
    std::vector<double> a;
    residuals(kk, ps, &a);
    return robust_cost(a, huber, cut);
  };
  double cost = evaluate(k, poses);
  double lambda = 1e-3;
  // The prediction's numerical pose derivative perturbs every residual by the same six small motions
  // (translation steps, then rotations about the axes): made once here.
  const double e = 1e-6;
  std::array<Eigen::Matrix3d, 6> perturb_rotation;
  std::array<Eigen::Vector3d, 6> perturb_translation;
  for (int j = 0; j < 6; ++j) {
    Vector6d d = Vector6d::Zero();
    d[j] = e;
    perturb_rotation[j] = ExpSo3(d.tail<3>()).toRotationMatrix();
    perturb_translation[j] = d.head<3>();
  }
  const double exp_h = std::exp(h), exp_minus_h = std::exp(-h);
  Eigen::MatrixXd hessian(dim, dim);
  Eigen::VectorXd gradient(dim);
  int iterations = 0;
  for (; iterations < options.max_iterations; ++iterations) {
    hessian.setZero();
    gradient.setZero();
    set_scale_derivative(k);
    for (int f = 0; f < nf; ++f) {
      const Eigen::Matrix3d r = poses[f].RotationMatrix();
      for (const ScalePoint& p : points) {
        const Eigen::Vector3d q = r * p.x + poses[f].translation;
        if (q.z() <= 0) continue;
        const Eigen::Vector2d uv = cam.Project(q);
        if (!inside(uv)) continue;
        const Eigen::Vector3d m_frame = r * p.m;
        const double pred = PredictGrey(rig, q, m_frame, k);
        const double res = Bilinear(images[f].grey, uv.x(), uv.y()) - pred;
        const double a = std::abs(res);
        if (a > cut) continue;
        const double w = a <= huber ? 1.0 : huber / a;
        Eigen::Matrix<double, 1, 7> jac;
        // Image term: d grey / d q, with d q / d delta = [I, -[q]x] (left perturbation).
        const double iz = 1.0 / q.z();
        const double gu = Bilinear(images[f].grad_x, uv.x(), uv.y()) * cam.fx;
        const double gv = Bilinear(images[f].grad_y, uv.x(), uv.y()) * cam.fy;
        const Eigen::Vector3d dimg_dq(gu * iz, gv * iz, -(gu * q.x() + gv * q.y()) * iz * iz);
        jac.head<3>() = dimg_dq.transpose();
        jac.segment<3>(3) = q.cross(dimg_dq).transpose();
        // Prediction term (numerical): q and m move with the pose, k with log k.
        if (options.refine_poses) {
          for (int j = 0; j < 6; ++j) {
            const Eigen::Matrix3d& rp = perturb_rotation[j];
            const Eigen::Matrix3d rm = rp.transpose();
            const Eigen::Vector3d qp = rp * q + perturb_translation[j], qm = rm * q - perturb_translation[j];
            jac[j] -= (PredictGrey(rig, qp, rp * m_frame, k) - PredictGrey(rig, qm, rm * m_frame, k)) / (2 * e);
          }
        }
        jac[6] = -(PredictGrey(rig, q, r * p.m_plus, k * exp_h) - PredictGrey(rig, q, r * p.m_minus, k * exp_minus_h)) /
                 (2 * h);
        // Scatter into the frame's pose block and the shared log k.
        const int o = 6 * f;
        Eigen::Matrix<double, 7, 7> jtj = w * jac.transpose() * jac;
        Eigen::Matrix<double, 7, 1> jtr = w * jac.transpose() * res;
        hessian.block<6, 6>(o, o) += jtj.topLeftCorner<6, 6>();
        hessian.block<6, 1>(o, dim - 1) += jtj.topRightCorner<6, 1>();
        hessian.block<1, 6>(dim - 1, o) += jtj.bottomLeftCorner<1, 6>();
        hessian(dim - 1, dim - 1) += jtj(6, 6);
        gradient.segment<6>(o) += jtr.head<6>();
        gradient[dim - 1] += jtr[6];
      }
    }
    if (!options.refine_poses) {
      for (int i = 0; i < 6 * nf; ++i) {
        hessian.row(i).setZero();
        hessian.col(i).setZero();
        hessian(i, i) = 1;
        gradient[i] = 0;
      }
    }
    bool improved = false;
    for (int attempt = 0; attempt < 8 && !improved; ++attempt) {
      Eigen::MatrixXd damped = hessian;
      for (int i = 0; i < dim; ++i) damped(i, i) *= 1 + lambda;
      const Eigen::VectorXd step = -damped.ldlt().solve(gradient);
      if (!step.allFinite()) break;
      std::vector<Rigid3d> trial = poses;
      for (int f = 0; f < nf; ++f) trial[f] = ApplyLeft(step.segment<6>(6 * f), poses[f]);
      const double k_trial = k * std::exp(std::clamp(step[dim - 1], -0.3, 0.3));
      set_scale(k_trial);
      const double trial_cost = evaluate(k_trial, trial);
      if (trial_cost < cost) {
        const bool converged = (cost - trial_cost) < 1e-9 * cost || step.norm() < 1e-9;
        poses = trial;
        k = k_trial;
        cost = trial_cost;
        lambda = std::max(1e-7, lambda / 10);
        improved = true;
        if (converged) iterations = options.max_iterations;
      } else {
        set_scale(k);
        lambda *= 10;
      }
    }
    if (!improved) break;
  }
  set_scale(k);

  // Final statistics and the log k uncertainty from the normal equations.
  int inliers = 0;
  double sse = 0;
  for (int f = 0; f < nf; ++f) {
    const Eigen::Matrix3d r = poses[f].RotationMatrix();
    for (const ScalePoint& p : points) {
      const Eigen::Vector3d q = r * p.x + poses[f].translation;
      if (q.z() <= 0) continue;
      const Eigen::Vector2d uv = cam.Project(q);
      if (!inside(uv)) continue;
      const double res = Bilinear(images[f].grey, uv.x(), uv.y()) - PredictGrey(rig, q, r * p.m, k);
      if (std::abs(res) > cut) continue;
      ++inliers;
      sse += res * res;
    }
  }
  if (inliers == 0) return FailedPreconditionError("EstimateShadingScale: no inlier residuals");
  result.metres_per_unit = k;
  result.frame_from_keyframe = poses;
  result.points = static_cast<int>(points.size());
  result.residuals = inliers;
  result.final_rms = std::sqrt(sse / inliers);
  result.iterations = std::min(iterations, options.max_iterations);
  // The last iteration's normal equations (at most one step from the end): the marginal variance of log k.
  const Eigen::MatrixXd covariance = hessian.ldlt().solve(Eigen::MatrixXd::Identity(dim, dim));
  const double var = covariance(dim - 1, dim - 1);
  result.log_sigma =
      var > 0 && std::isfinite(var) ? result.final_rms * std::sqrt(var) : std::numeric_limits<double>::infinity();
  return result;
}

}  // namespace prism
