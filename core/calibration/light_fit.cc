#include "core/calibration/light_fit.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include <Eigen/Cholesky>
#include <Eigen/LU>

namespace prism::calibration {

Status LightFitOptions::Check() const {
  std::ostringstream e;
  if (!(max_iterations >= 1 && max_iterations <= 1000))
    e << "LightFitOptions.max_iterations = " << max_iterations << "; violated: in [1, 1000]";
  else if (!(search_radius_m > 0 && search_radius_m <= 2))
    e << "LightFitOptions.search_radius_m = " << search_radius_m << "; violated: in (0, 2]";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

constexpr int kParams = 21;
using Params = Eigen::Matrix<double, kParams, 1>;
using Normal = Eigen::Matrix<double, kParams, kParams>;

int GainIndex(int c, int l) { return 9 + 3 * l + c; }
int AmbientIndex(int c) { return 18 + c; }

// Near-light shading max(0, n . v) / |v|^3 with v = light - point, and its gradient in the light position.
double Shading(const Eigen::Vector3d& light, const LightSample& s, Eigen::Vector3d* gradient) {
  const Eigen::Vector3d v = light - s.point_in_camera;
  const double d2 = v.squaredNorm(), d = std::sqrt(d2), nv = s.normal_in_camera.dot(v);
  if (nv <= 0 || d2 <= 0) {
    if (gradient) gradient->setZero();
    return 0;
  }
  const double inv_d3 = 1.0 / (d2 * d);
  if (gradient) *gradient = s.normal_in_camera * inv_d3 - 3 * nv * inv_d3 / d2 * v;
  return nv * inv_d3;
}

// Cost (sum of squared residuals) and, when asked, the normal equations at `theta`.
double Evaluate(const std::vector<LightSample>& samples, const Params& theta, bool fit_ambient, Normal* h, Params* g) {
  if (h) h->setZero();
  if (g) g->setZero();
  double cost = 0;
  Eigen::Matrix<double, kParams, 1> row;
  for (const LightSample& s : samples) {
    double shade[3];
    Eigen::Vector3d grad[3];
    for (int l = 0; l < 3; ++l)
      shade[l] = (s.lit >> l) & 1 ? Shading(theta.segment<3>(3 * l), s, h ? &grad[l] : nullptr) : 0.0;
    for (int c = 0; c < 3; ++c) {
      double pred = theta[AmbientIndex(c)];
      for (int l = 0; l < 3; ++l) pred += theta[GainIndex(c, l)] * shade[l];
      const double r = pred - s.rgb[c];
      cost += r * r;
      if (!h) continue;
      row.setZero();
      if (fit_ambient) row[AmbientIndex(c)] = 1;
      for (int l = 0; l < 3; ++l) {
        if (!((s.lit >> l) & 1)) continue;
        row.segment<3>(3 * l) = theta[GainIndex(c, l)] * grad[l];
        row[GainIndex(c, l)] = shade[l];
      }
      h->selfadjointView<Eigen::Lower>().rankUpdate(row);
      *g += r * row;
    }
  }
  if (h) {
    *h = h->selfadjointView<Eigen::Lower>();
    if (!fit_ambient) h->diagonal().tail<3>().setOnes();  // b stays 0: no gradient, unit curvature
  }
  return cost;
}

// Grid search for one light over the samples it lit alone; the gains are solved in closed form.
Eigen::Vector3d StartPosition(const std::vector<const LightSample*>& samples, double radius) {
  Eigen::Vector3d best = Eigen::Vector3d::Zero();
  double best_cost = std::numeric_limits<double>::infinity();
  const int n = 12;
  for (int iz = -n / 4; iz <= n / 4; ++iz) {
    for (int iy = -n; iy <= n; ++iy) {
      for (int ix = -n; ix <= n; ++ix) {
        const Eigen::Vector3d p(radius * ix / n, radius * iy / n, radius * iz / n);
        double ss = 0, yy = 0;
        Eigen::Vector3d sy = Eigen::Vector3d::Zero();
        for (const LightSample* s : samples) {
          const double sh = Shading(p, *s, nullptr);
          ss += sh * sh;
          sy += sh * s->rgb;
          yy += s->rgb.squaredNorm();
        }
        if (ss <= 0) continue;
        const double cost = yy - sy.squaredNorm() / ss;
        if (cost < best_cost) {
          best_cost = cost;
          best = p;
        }
      }
    }
  }
  return best;
}

}  // namespace

StatusOr<LightFitResult> FitLights(const std::vector<LightSample>& samples, const LightFitOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  static const char* kNames[3] = {"red", "green", "blue"};
  Params theta = Params::Zero();
  for (int l = 0; l < 3; ++l) {
    std::vector<const LightSample*> alone;
    for (const LightSample& s : samples)
      if (s.lit == (1 << l)) alone.push_back(&s);
    if (alone.empty())
      return FailedPreconditionError(std::string("no board sample lit by the ") + kNames[l] + " light alone");
    // Every k-th sample is enough for the start.
    std::vector<const LightSample*> few;
    const size_t step = std::max<size_t>(1, alone.size() / 2000);
    for (size_t i = 0; i < alone.size(); i += step) few.push_back(alone[i]);
    const Eigen::Vector3d p = StartPosition(few, options.search_radius_m);
    theta.segment<3>(3 * l) = p;
    double ss = 0;
    Eigen::Vector3d sy = Eigen::Vector3d::Zero();
    for (const LightSample* s : alone) {
      const double sh = Shading(p, *s, nullptr);
      ss += sh * sh;
      sy += sh * s->rgb;
    }
    for (int c = 0; c < 3; ++c) theta[GainIndex(c, l)] = ss > 0 ? sy[c] / ss : 0;
  }

  LightFitResult result;
  Normal h;
  Params g;
  double cost = Evaluate(samples, theta, options.fit_ambient, &h, &g);
  double lambda = 1e-4;
  for (int it = 0; it < options.max_iterations; ++it) {
    result.iterations = it + 1;
    Normal damped = h;
    damped.diagonal() += lambda * h.diagonal().cwiseMax(1e-12);
    const Params delta = -damped.ldlt().solve(g);
    if (!delta.allFinite()) return FailedPreconditionError("light fit: singular normal equations");
    const Params candidate = theta + delta;
    const double candidate_cost = Evaluate(samples, candidate, options.fit_ambient, nullptr, nullptr);
    if (candidate_cost < cost) {
      const double decrease = (cost - candidate_cost) / std::max(cost, 1e-300);
      theta = candidate;
      cost = Evaluate(samples, theta, options.fit_ambient, &h, &g);
      lambda = std::max(lambda / 3, 1e-12);
      if (decrease < 1e-12 || delta.head<9>().norm() < 1e-9) {
        result.converged = true;
        break;
      }
    } else {
      lambda *= 4;
      if (lambda > 1e12) {
        result.converged = true;  // no step lowers the cost: at the minimum to machine precision
        break;
      }
    }
  }

  const int m = 3 * static_cast<int>(samples.size());
  result.residuals = m;
  result.rms = std::sqrt(cost / std::max(1, m));
  const double sigma2 = cost / std::max(1, m - (options.fit_ambient ? kParams : kParams - 3));
  Eigen::FullPivLU<Normal> lu(h);
  if (!lu.isInvertible()) return FailedPreconditionError("light fit: the board poses do not constrain the lights");
  result.covariance = sigma2 * lu.inverse();
  for (int l = 0; l < 3; ++l) {
    result.position_in_camera[l] = theta.segment<3>(3 * l);
    result.position_std[l] = result.covariance.diagonal().segment<3>(3 * l).cwiseMax(0).cwiseSqrt();
    for (int c = 0; c < 3; ++c) {
      result.gain(c, l) = theta[GainIndex(c, l)];
      result.gain_std(c, l) = std::sqrt(std::max(0.0, result.covariance(GainIndex(c, l), GainIndex(c, l))));
    }
  }
  for (int c = 0; c < 3; ++c) {
    result.ambient[c] = theta[AmbientIndex(c)];
    result.ambient_std[c] =
        options.fit_ambient ? std::sqrt(std::max(0.0, result.covariance(AmbientIndex(c), AmbientIndex(c)))) : 0.0;
  }
  return result;
}

}  // namespace prism::calibration
