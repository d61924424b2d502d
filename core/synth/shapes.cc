#include "core/synth/shapes.h"

#include <cmath>
#include <random>

namespace prism::synth {

TriangleMesh MakeTorus(double R, double r, int nu, int nv) {
  TriangleMesh m;
  for (int i = 0; i < nu; ++i) {
    const double u = 2 * M_PI * i / nu;
    for (int j = 0; j < nv; ++j) {
      const double v = 2 * M_PI * j / nv;
      const Eigen::Vector3d n(std::cos(v) * std::cos(u), std::cos(v) * std::sin(u), std::sin(v));
      const Eigen::Vector3d c(R * std::cos(u), R * std::sin(u), 0);
      m.vertices.push_back(c + r * n);
      m.vertex_normals.push_back(n);
    }
  }
  for (int i = 0; i < nu; ++i)
    for (int j = 0; j < nv; ++j) {
      const int a = i * nv + j, b = ((i + 1) % nu) * nv + j, c = ((i + 1) % nu) * nv + (j + 1) % nv,
                d = i * nv + (j + 1) % nv;
      m.faces.emplace_back(a, b, c);
      m.faces.emplace_back(a, c, d);
    }
  return m;
}

TriangleMesh MakeRelief(double half, double height, int bumps, int res, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> pos(-0.7 * half, 0.7 * half), amp(0.3, 1.0), width(0.12, 0.3);
  struct Bump {
    double x, y, a, s;
  };
  std::vector<Bump> bs;
  for (int i = 0; i < bumps; ++i) bs.push_back({pos(rng), pos(rng), height * amp(rng), half * width(rng)});
  // Height and gradient; a smooth window takes the relief to 0 at the border.
  auto eval = [&](double x, double y, double* h, double* hx, double* hy) {
    double f = 0, fx = 0, fy = 0;
    for (const Bump& b : bs) {
      const double dx = x - b.x, dy = y - b.y;
      const double g = b.a * std::exp(-(dx * dx + dy * dy) / (2 * b.s * b.s));
      f += g;
      fx += -g * dx / (b.s * b.s);
      fy += -g * dy / (b.s * b.s);
    }
    auto win = [&](double t, double* dw) {
      const double q = 1 - (t / half) * (t / half);
      *dw = -2 * t / (half * half) * 2 * q;
      return q * q;
    };
    double dwx, dwy;
    const double wx = win(x, &dwx), wy = win(y, &dwy);
    *h = f * wx * wy;
    *hx = fx * wx * wy + f * dwx * wy;
    *hy = fy * wx * wy + f * wx * dwy;
  };
  TriangleMesh m;
  const int n = res + 1;
  for (int j = 0; j < n; ++j)
    for (int i = 0; i < n; ++i) {
      const double x = -half + 2 * half * i / res, y = -half + 2 * half * j / res;
      double h, hx, hy;
      eval(x, y, &h, &hx, &hy);
      m.vertices.emplace_back(x, y, h);
      m.vertex_normals.push_back(Eigen::Vector3d(-hx, -hy, 1).normalized());
    }
  for (int j = 0; j < res; ++j)
    for (int i = 0; i < res; ++i) {
      const int a = j * n + i, b = a + 1, c = a + n + 1, d = a + n;
      m.faces.emplace_back(a, b, c);
      m.faces.emplace_back(a, c, d);
    }
  return m;
}

void NormaliseMesh(int up_axis, double up_sign, double size_m, TriangleMesh* mesh) {
  Eigen::Matrix3d r = Eigen::Matrix3d::Identity();
  // Map object axis `up_axis` (times up_sign) to +z with a proper rotation.
  Eigen::Vector3d up = Eigen::Vector3d::Zero();
  up[up_axis] = up_sign;
  r = Eigen::Quaterniond::FromTwoVectors(up, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  for (auto& v : mesh->vertices) v = r * v;
  for (auto& n : mesh->vertex_normals) n = r * n;
  Eigen::Vector3d lo, hi;
  if (!mesh->Bounds(&lo, &hi)) return;
  const double s = size_m / (hi - lo).maxCoeff();
  const Eigen::Vector3d shift(-0.5 * (lo.x() + hi.x()), -0.5 * (lo.y() + hi.y()), -lo.z());
  for (auto& v : mesh->vertices) v = (v + shift) * s;
}

}  // namespace prism::synth
