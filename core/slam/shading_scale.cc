#include "core/slam/shading_scale.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>

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

constexpr double kLogScaleStep = 1e-4;  // log k step for the numerical derivative
constexpr double kPoseStep = 1e-6;      // pose step (translation, rotation) for the numerical derivative

Status CheckInputs(const RigCalibration& rig, const cv::Mat& keyframe_rgb, const cv::Mat& keyframe_inverse_depth,
                   const std::vector<ShadingScaleFrame>& frames, const ShadingScaleOptions& options) {
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
  return Status::Ok();
}

// Points: per cell the strongest grey gradient among pixels with a depth, unsaturated, bright enough,
// lit by all three lights, whose implied normal (at the initial k) faces the camera. `candidates` counts
// the cells' points lit by all three lights, `facing` those kept.
std::vector<ScalePoint> SelectPoints(const RigCalibration& rig, const cv::Mat& keyframe_rgb,
                                     const cv::Mat& keyframe_inverse_depth, const ShadingScaleOptions& options,
                                     int* candidates, int* facing) {
  const PinholeCamera& cam = rig.camera;
  const Eigen::Matrix3d demix = rig.crosstalk.inverse();
  const cv::Mat kf_grey = MeanOfChannels(keyframe_rgb);
  std::vector<ScalePoint> points;
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
      ++*candidates;
      const Eigen::Vector3d m = ImpliedNormal(rig, k0 * p.x, p.bands);
      if (m.dot(-p.x.normalized()) < options.min_view_cosine * m.norm()) continue;
      ++*facing;
      points.push_back(p);
    }
  }
  return points;
}

// The grey residuals of the points in the frames: each point's m is cached for the current k (SetScale;
// m at k exp(+-h) by SetScaleDerivative, only where the derivative is taken: once per linearisation,
// the scan and the trial steps do not need it).
class ShadingResiduals {
 public:
  ShadingResiduals(const RigCalibration& rig, const ShadingScaleOptions& options, std::vector<ScalePoint> points,
                   std::vector<FrameImages> images);

  int num_points() const { return static_cast<int>(points_.size()); }
  void SetScale(double k) {
    for (ScalePoint& p : points_) p.m = ImpliedNormal(rig_, k * p.x, p.bands);
  }
  void SetScaleDerivative(double k) {
    const double h = kLogScaleStep;
    for (ScalePoint& p : points_) {
      p.m_plus = ImpliedNormal(rig_, k * std::exp(h) * p.x, p.bands);
      p.m_minus = ImpliedNormal(rig_, k * std::exp(-h) * p.x, p.bands);
    }
  }
  // Residuals at (k, poses) with the model's m cached for k: appends |r| to `abs_res`.
  void AbsResiduals(double k, const std::vector<Rigid3d>& ps, std::vector<double>* abs_res) const;
  // The robust cost at (k, poses): Huber beyond `huber`, residuals cut at `cut`.
  double Cost(double k, const std::vector<Rigid3d>& ps, double huber, double cut) const;
  // The Gauss-Newton normal equations at (k, poses) over the inlier residuals (Huber weights), unknowns
  // each frame's pose (left perturbation) then log k; m at k and at k exp(+-h) must be set. Without
  // options.refine_poses the pose blocks are identity and their gradient zero.
  void NormalEquations(double k, const std::vector<Rigid3d>& poses, double huber, double cut, Eigen::MatrixXd* hessian,
                       Eigen::VectorXd* gradient) const;
  // The inlier residuals' count and sum of squares at (k, poses).
  void InlierStatistics(double k, const std::vector<Rigid3d>& poses, double cut, int* inliers, double* sse) const;

 private:
  // Calls visit(f, p, q, r, uv) for each point p in front of frame f's camera (q = its position in the
  // camera, r the frame's rotation) and inside its image at uv, frame by frame in point order.
  template <typename Visit>
  void ForEachVisible(const std::vector<Rigid3d>& poses, Visit&& visit) const {
    for (size_t f = 0; f < poses.size(); ++f) {
      const Eigen::Matrix3d r = poses[f].RotationMatrix();
      for (const ScalePoint& p : points_) {
        const Eigen::Vector3d q = r * p.x + poses[f].translation;
        if (q.z() <= 0) continue;
        const Eigen::Vector2d uv = rig_.camera.Project(q);
        if (!Inside(uv)) continue;
        visit(f, p, q, r, uv);
      }
    }
  }
  bool Inside(const Eigen::Vector2d& uv) const {
    const PinholeCamera& cam = rig_.camera;
    const int b = options_.border_px;
    return uv.x() >= b && uv.y() >= b && uv.x() < cam.width - 1 - b && uv.y() < cam.height - 1 - b;
  }
  // One residual's derivative: the image term d grey / d (pose), the prediction's pose term (numerical,
  // with refine_poses) and d / d log k (numerical).
  Eigen::Matrix<double, 1, 7> Jacobian(const FrameImages& image, const Eigen::Matrix3d& r, const ScalePoint& p,
                                       const Eigen::Vector3d& q, const Eigen::Vector3d& m_frame,
                                       const Eigen::Vector2d& uv, double k) const;

  const RigCalibration& rig_;
  const ShadingScaleOptions& options_;
  std::vector<ScalePoint> points_;
  std::vector<FrameImages> images_;
  // The prediction's numerical pose derivative perturbs every residual by the same six small motions
  // (translation steps, then rotations about the axes): made once here.
  std::array<Eigen::Matrix3d, 6> perturb_rotation_;
  std::array<Eigen::Vector3d, 6> perturb_translation_;
};

ShadingResiduals::ShadingResiduals(const RigCalibration& rig, const ShadingScaleOptions& options,
                                   std::vector<ScalePoint> points, std::vector<FrameImages> images)
    : rig_(rig), options_(options), points_(std::move(points)), images_(std::move(images)) {
  const double e = kPoseStep;
  for (int j = 0; j < 6; ++j) {
    Vector6d d = Vector6d::Zero();
    d[j] = e;
    perturb_rotation_[j] = ExpSo3(d.tail<3>()).toRotationMatrix();
    perturb_translation_[j] = d.head<3>();
  }
}

void ShadingResiduals::AbsResiduals(double k, const std::vector<Rigid3d>& ps, std::vector<double>* abs_res) const {
  ForEachVisible(ps, [&](size_t f, const ScalePoint& p, const Eigen::Vector3d& q, const Eigen::Matrix3d& r,
                         const Eigen::Vector2d& uv) {
    abs_res->push_back(std::abs(Bilinear(images_[f].grey, uv.x(), uv.y()) - PredictGrey(rig_, q, r * p.m, k)));
  });
}

double ShadingResiduals::Cost(double k, const std::vector<Rigid3d>& ps, double huber, double cut) const {
  std::vector<double> abs_res;
  AbsResiduals(k, ps, &abs_res);
  double cost = 0;
  for (double a : abs_res) {
    const double e = std::min(a, cut);
    cost += e <= huber ? 0.5 * e * e : huber * (e - 0.5 * huber);
  }
  return cost;
}

void ShadingResiduals::NormalEquations(double k, const std::vector<Rigid3d>& poses, double huber, double cut,
                                       Eigen::MatrixXd* hessian_out, Eigen::VectorXd* gradient_out) const {
  Eigen::MatrixXd& hessian = *hessian_out;
  Eigen::VectorXd& gradient = *gradient_out;
  const int nf = static_cast<int>(poses.size());
  const int dim = 6 * nf + 1;
  hessian.setZero();
  gradient.setZero();
  ForEachVisible(poses, [&](size_t f, const ScalePoint& p, const Eigen::Vector3d& q, const Eigen::Matrix3d& r,
                            const Eigen::Vector2d& uv) {
    const Eigen::Vector3d m_frame = r * p.m;
    const double pred = PredictGrey(rig_, q, m_frame, k);
    const double res = Bilinear(images_[f].grey, uv.x(), uv.y()) - pred;
    const double a = std::abs(res);
    if (a > cut) return;
    const double w = a <= huber ? 1.0 : huber / a;
    const Eigen::Matrix<double, 1, 7> jac = Jacobian(images_[f], r, p, q, m_frame, uv, k);
    // Scatter into the frame's pose block and the shared log k.
    const int o = 6 * static_cast<int>(f);
    Eigen::Matrix<double, 7, 7> jtj = w * jac.transpose() * jac;
    Eigen::Matrix<double, 7, 1> jtr = w * jac.transpose() * res;
    hessian.block<6, 6>(o, o) += jtj.topLeftCorner<6, 6>();
    hessian.block<6, 1>(o, dim - 1) += jtj.topRightCorner<6, 1>();
    hessian.block<1, 6>(dim - 1, o) += jtj.bottomLeftCorner<1, 6>();
    hessian(dim - 1, dim - 1) += jtj(6, 6);
    gradient.segment<6>(o) += jtr.head<6>();
    gradient[dim - 1] += jtr[6];
  });
  if (!options_.refine_poses) {
    for (int i = 0; i < 6 * nf; ++i) {
      hessian.row(i).setZero();
      hessian.col(i).setZero();
      hessian(i, i) = 1;
      gradient[i] = 0;
    }
  }
}

Eigen::Matrix<double, 1, 7> ShadingResiduals::Jacobian(const FrameImages& image, const Eigen::Matrix3d& r,
                                                       const ScalePoint& p, const Eigen::Vector3d& q,
                                                       const Eigen::Vector3d& m_frame, const Eigen::Vector2d& uv,
                                                       double k) const {
  const PinholeCamera& cam = rig_.camera;
  const double h = kLogScaleStep, e = kPoseStep;
  const double exp_h = std::exp(h), exp_minus_h = std::exp(-h);
  Eigen::Matrix<double, 1, 7> jac;
  // Image term: d grey / d q, with d q / d delta = [I, -[q]x] (left perturbation).
  const double iz = 1.0 / q.z();
  const double gu = Bilinear(image.grad_x, uv.x(), uv.y()) * cam.fx;
  const double gv = Bilinear(image.grad_y, uv.x(), uv.y()) * cam.fy;
  const Eigen::Vector3d dimg_dq(gu * iz, gv * iz, -(gu * q.x() + gv * q.y()) * iz * iz);
  jac.head<3>() = dimg_dq.transpose();
  jac.segment<3>(3) = q.cross(dimg_dq).transpose();
  // Prediction term (numerical): q and m move with the pose, k with log k.
  if (options_.refine_poses) {
    for (int j = 0; j < 6; ++j) {
      const Eigen::Matrix3d& rp = perturb_rotation_[j];
      const Eigen::Matrix3d rm = rp.transpose();
      const Eigen::Vector3d qp = rp * q + perturb_translation_[j], qm = rm * q - perturb_translation_[j];
      jac[j] -= (PredictGrey(rig_, qp, rp * m_frame, k) - PredictGrey(rig_, qm, rm * m_frame, k)) / (2 * e);
    }
  }
  jac[6] =
      -(PredictGrey(rig_, q, r * p.m_plus, k * exp_h) - PredictGrey(rig_, q, r * p.m_minus, k * exp_minus_h)) / (2 * h);
  return jac;
}

void ShadingResiduals::InlierStatistics(double k, const std::vector<Rigid3d>& poses, double cut, int* inliers,
                                        double* sse) const {
  ForEachVisible(poses, [&](size_t f, const ScalePoint& p, const Eigen::Vector3d& q, const Eigen::Matrix3d& r,
                            const Eigen::Vector2d& uv) {
    const double res = Bilinear(images_[f].grey, uv.x(), uv.y()) - PredictGrey(rig_, q, r * p.m, k);
    if (std::abs(res) > cut) return;
    ++*inliers;
    *sse += res * res;
  });
}

// Coarse scan of k at the given poses: the cost is the robust one with a sigma from the median absolute
// residual at each k (a wrong k inflates every residual). Returns the best k (k0 when there is no scan).
double ScanScale(const std::vector<Rigid3d>& poses, const ShadingScaleOptions& options, ShadingResiduals* model) {
  const double k0 = options.initial_metres_per_unit;
  double k = k0;
  if (options.scan_steps > 1) {
    double best_cost = std::numeric_limits<double>::infinity();
    for (int i = 0; i < options.scan_steps; ++i) {
      const double kk = k0 * std::exp(std::log(options.scan_factor) * (2.0 * i / (options.scan_steps - 1) - 1.0));
      model->SetScale(kk);
      std::vector<double> a;
      model->AbsResiduals(kk, poses, &a);
      if (a.size() < static_cast<size_t>(options.min_points)) continue;
      std::nth_element(a.begin(), a.begin() + a.size() / 2, a.end());
      const double med = a[a.size() / 2];
      if (med < best_cost) best_cost = med, k = kk;
    }
  }
  return k;
}

// The Levenberg-Marquardt state: each frame's pose, k (m set for it), the robust cost there and the damping.
struct Refinement {
  std::vector<Rigid3d> poses;
  double k = 0;
  double cost = 0;
  double lambda = 1e-3;
};

// One Levenberg-Marquardt step from the normal equations: up to 8 dampings until the cost falls. Returns
// whether it fell; `converged` when the fall or the step was negligible.
bool LevenbergMarquardtStep(const Eigen::MatrixXd& hessian, const Eigen::VectorXd& gradient, double huber, double cut,
                            ShadingResiduals* model, Refinement* state, bool* converged) {
  const int nf = static_cast<int>(state->poses.size());
  const int dim = 6 * nf + 1;
  bool improved = false;
  for (int attempt = 0; attempt < 8 && !improved; ++attempt) {
    Eigen::MatrixXd damped = hessian;
    for (int i = 0; i < dim; ++i) damped(i, i) *= 1 + state->lambda;
    const Eigen::VectorXd step = -damped.ldlt().solve(gradient);
    if (!step.allFinite()) break;
    std::vector<Rigid3d> trial = state->poses;
    for (int f = 0; f < nf; ++f) trial[f] = ApplyLeft(step.segment<6>(6 * f), state->poses[f]);
    const double k_trial = state->k * std::exp(std::clamp(step[dim - 1], -0.3, 0.3));
    model->SetScale(k_trial);
    const double trial_cost = model->Cost(k_trial, trial, huber, cut);
    if (trial_cost < state->cost) {
      *converged = (state->cost - trial_cost) < 1e-9 * state->cost || step.norm() < 1e-9;
      state->poses = trial;
      state->k = k_trial;
      state->cost = trial_cost;
      state->lambda = std::max(1e-7, state->lambda / 10);
      improved = true;
    } else {
      model->SetScale(state->k);
      state->lambda *= 10;
    }
  }
  return improved;
}

}  // namespace

StatusOr<ShadingScaleResult> EstimateShadingScale(const RigCalibration& rig, const cv::Mat& keyframe_rgb,
                                                  const cv::Mat& keyframe_inverse_depth,
                                                  const std::vector<ShadingScaleFrame>& frames,
                                                  const ShadingScaleOptions& options) {
  PRISM_RETURN_IF_ERROR(CheckInputs(rig, keyframe_rgb, keyframe_inverse_depth, frames, options));
  int candidates = 0, facing = 0;
  std::vector<ScalePoint> points =
      SelectPoints(rig, keyframe_rgb, keyframe_inverse_depth, options, &candidates, &facing);
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
  Refinement state;
  for (const ShadingScaleFrame& f : frames) state.poses.push_back(f.frame_from_keyframe);
  ShadingResiduals model(rig, options, std::move(points), std::move(images));

  state.k = ScanScale(state.poses, options, &model);
  model.SetScale(state.k);
  std::vector<double> start;
  model.AbsResiduals(state.k, state.poses, &start);
  if (start.size() < static_cast<size_t>(options.min_points))
    return FailedPreconditionError("EstimateShadingScale: too few points project into the frames");
  std::nth_element(start.begin(), start.begin() + start.size() / 2, start.end());
  const double sigma = std::max(0.5, 1.4826 * start[start.size() / 2]);
  const double huber = options.huber_sigmas * sigma, cut = options.outlier_sigmas * sigma;
  result.residual_sigma = sigma;

  const int dim = 6 * static_cast<int>(frames.size()) + 1;
  state.cost = model.Cost(state.k, state.poses, huber, cut);
  Eigen::MatrixXd hessian(dim, dim);
  Eigen::VectorXd gradient(dim);
  int iterations = 0;
  for (; iterations < options.max_iterations; ++iterations) {
    model.SetScaleDerivative(state.k);
    model.NormalEquations(state.k, state.poses, huber, cut, &hessian, &gradient);
    bool converged = false;
    if (!LevenbergMarquardtStep(hessian, gradient, huber, cut, &model, &state, &converged)) break;
    if (converged) iterations = options.max_iterations;
  }
  model.SetScale(state.k);

  // Final statistics and the log k uncertainty from the normal equations.
  int inliers = 0;
  double sse = 0;
  model.InlierStatistics(state.k, state.poses, cut, &inliers, &sse);
  if (inliers == 0) return FailedPreconditionError("EstimateShadingScale: no inlier residuals");
  result.metres_per_unit = state.k;
  result.frame_from_keyframe = state.poses;
  result.points = model.num_points();
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
