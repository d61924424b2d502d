// EstimateNormals' per-pixel solve: labels, normals and confidence, row by row in float kernels.
#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Dense>
#include <opencv2/core.hpp>

#include "core/photometric/photometric_internal.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {
namespace {

// Row kernels of the per-pixel solve: plain float arrays, no branches, so that the compiler
// vectorises them.

// One row of S(p) for a point light: I v / |v|^3, v from the surface point ray * scale /
// inverse_depth to the light.
void PointLightRow(int w, float ray_x0, float ray_dx, float ray_y, float scale, float lx, float ly, float lz, float li,
                   const float* __restrict inverse_depth, float* __restrict sx, float* __restrict sy,
                   float* __restrict sz) {
  for (int x = 0; x < w; ++x) {
    const float depth = scale / inverse_depth[x];
    const float vx = lx - (ray_x0 + ray_dx * static_cast<float>(x)) * depth, vy = ly - ray_y * depth, vz = lz - depth;
    const float d2 = vx * vx + vy * vy + vz * vz;
    const float f = li / (d2 * std::sqrt(d2));
    sx[x] = f * vx;
    sy[x] = f * vy;
    sz[x] = f * vz;
  }
}

// n ~ S^-1 b up to a positive factor: adj(S) b sign(det S). s[3 * l + j] = S(l, j) per pixel.
void AdjugateSolveRow(int w, const float* const* s, const float* __restrict b0, const float* __restrict b1,
                      const float* __restrict b2, float* __restrict n0, float* __restrict n1, float* __restrict n2) {
  const float* __restrict s00 = s[0];
  const float* __restrict s01 = s[1];
  const float* __restrict s02 = s[2];
  const float* __restrict s10 = s[3];
  const float* __restrict s11 = s[4];
  const float* __restrict s12 = s[5];
  const float* __restrict s20 = s[6];
  const float* __restrict s21 = s[7];
  const float* __restrict s22 = s[8];
  for (int x = 0; x < w; ++x) {
    const float m00 = s00[x], m01 = s01[x], m02 = s02[x], m10 = s10[x], m11 = s11[x], m12 = s12[x], m20 = s20[x],
                m21 = s21[x], m22 = s22[x];
    const float c00 = m11 * m22 - m12 * m21, c01 = m12 * m20 - m10 * m22, c02 = m10 * m21 - m11 * m20;
    const float c10 = m02 * m21 - m01 * m22, c11 = m00 * m22 - m02 * m20, c12 = m01 * m20 - m00 * m21;
    const float c20 = m01 * m12 - m02 * m11, c21 = m02 * m10 - m00 * m12, c22 = m00 * m11 - m01 * m10;
    const float det = m00 * c00 + m01 * c01 + m02 * c02;
    const float sign = det < 0 ? -1.f : 1.f;
    n0[x] = sign * (c00 * b0[x] + c10 * b1[x] + c20 * b2[x]);
    n1[x] = sign * (c01 * b0[x] + c11 * b1[x] + c21 * b2[x]);
    n2[x] = sign * (c02 * b0[x] + c12 * b1[x] + c22 * b2[x]);
  }
}

// Albedo chromaticity (r, g of rho / sum rho, rho = q / max(0, S n0)) of each pixel under its prior
// normal, and the nearest of k centres to it; -1 where a band's predicted shading is <= 1e-4 or
// an albedo is not positive (as for no prior normal, n0 = 0).
void NearestChromaticityRow(int w, const float* const* s, const float* __restrict q0, const float* __restrict q1,
                            const float* __restrict q2, const float* __restrict p0, const float* __restrict p1,
                            const float* __restrict p2, int k, const float* centre_r, const float* centre_g,
                            float* __restrict cr, float* __restrict cg, float* __restrict best,
                            int* __restrict nearest) {
  const float* __restrict s00 = s[0];
  const float* __restrict s01 = s[1];
  const float* __restrict s02 = s[2];
  const float* __restrict s10 = s[3];
  const float* __restrict s11 = s[4];
  const float* __restrict s12 = s[5];
  const float* __restrict s20 = s[6];
  const float* __restrict s21 = s[7];
  const float* __restrict s22 = s[8];
  for (int x = 0; x < w; ++x) {
    const float a0 = std::max(0.f, s00[x] * p0[x] + s01[x] * p1[x] + s02[x] * p2[x]);
    const float a1 = std::max(0.f, s10[x] * p0[x] + s11[x] * p1[x] + s12[x] * p2[x]);
    const float a2 = std::max(0.f, s20[x] * p0[x] + s21[x] * p1[x] + s22[x] * p2[x]);
    const float lit = (a0 > 1e-4f ? 1.f : 0.f) * (a1 > 1e-4f ? 1.f : 0.f) * (a2 > 1e-4f ? 1.f : 0.f);
    const float r0 = q0[x] / (lit > 0 ? a0 : 1.f), r1 = q1[x] / (lit > 0 ? a1 : 1.f), r2 = q2[x] / (lit > 0 ? a2 : 1.f);
    const float positive = lit * (r0 > 0 ? 1.f : 0.f) * (r1 > 0 ? 1.f : 0.f) * (r2 > 0 ? 1.f : 0.f);
    const float sum = r0 + r1 + r2;
    cr[x] = r0 / (positive > 0 ? sum : 1.f);
    cg[x] = r1 / (positive > 0 ? sum : 1.f);
    best[x] = positive > 0 ? std::numeric_limits<float>::infinity() : -1.f;
    nearest[x] = -1;
  }
  for (int m = 0; m < k; ++m) {
    const float r = centre_r[m], g = centre_g[m];
    for (int x = 0; x < w; ++x) {
      const float dr = cr[x] - r, dg = cg[x] - g;
      const float d = dr * dr + dg * dg;
      const float old = best[x];
      const bool closer = d < old;
      best[x] = closer ? d : old;
      const int mask = -static_cast<int>(closer);
      nearest[x] = (m & mask) | (nearest[x] & ~mask);
    }
  }
}

// Normalises the solved normals n in place (zero where not solved or degenerate), flips them to
// face the camera, and computes their confidence. flags: 1 = solved, 2 = unlabelled (added).
void FinishRow(int w, float ray_x0, float ray_dx, float ray_y, bool calibrated, float saturation_level,
               float level_scale, float cos_max_prior_deviation, const float* __restrict level,
               const float* __restrict flags, const float* __restrict b0, const float* __restrict b1,
               const float* __restrict b2, const float* __restrict p0, const float* __restrict p1,
               const float* __restrict p2, float* __restrict n0, float* __restrict n1, float* __restrict n2,
               float* __restrict confidence) {
  const float shadow_test = calibrated ? 1.f : 0.f;
  for (int x = 0; x < w; ++x) {
    const float f = flags[x];
    const float solved = (f == 1.f ? 1.f : 0.f) + (f == 3.f ? 1.f : 0.f);
    const float unlabelled = f >= 2.f ? 1.f : 0.f;
    const float len2 = n0[x] * n0[x] + n1[x] * n1[x] + n2[x] * n2[x];
    // A normal is kept when solved, finite and not degenerate (len2 < inf also rejects NaN).
    const float keep = solved * (len2 > 0.f ? 1.f : 0.f) * (len2 < std::numeric_limits<float>::infinity() ? 1.f : 0.f);
    const float inv_len = 1.f / std::sqrt(keep > 0 ? len2 : 1.f);
    float nx = n0[x] * inv_len, ny = n1[x] * inv_len, nz = n2[x] * inv_len;
    float quality = 1.f;
    // A light that contributes (almost) nothing (attached or cast shadow) makes the 3-light solve
    // unreliable: compare each band with the others, relative to its irradiance (S n = b).
    const float bmin = std::min(std::min(b0[x], b1[x]), b2[x]), bmax = std::max(std::max(b0[x], b1[x]), b2[x]);
    quality *= shadow_test * (bmin < 0.1f * bmax ? 1.f : 0.f) > 0 ? 0.2f : 1.f;
    // Facing away: flip, and trust it less.
    const float rx = ray_x0 + ray_dx * static_cast<float>(x);
    const float away = nx * rx + ny * ray_y + nz;
    const float flip = away > 0 ? -1.f : 1.f;
    quality *= away > 0 ? 0.2f : 1.f;
    nx *= flip;
    ny *= flip;
    nz *= flip;
    quality *= level[x] >= saturation_level ? 0.2f : 1.f;
    quality *= unlabelled > 0 ? 0.5f : 1.f;
    quality *= std::min(1.f, level[x] * level_scale);
    // Far from the (coarse) prior normal: likely a shadow or a mislabelled albedo, not detail.
    const float prior2 = p0[x] * p0[x] + p1[x] * p1[x] + p2[x] * p2[x];
    const float cosine = nx * p0[x] + ny * p1[x] + nz * p2[x];
    quality *= (prior2 > 0 ? 1.f : 0.f) * (cosine < cos_max_prior_deviation ? 1.f : 0.f) > 0 ? 0.1f : 1.f;
    n0[x] = keep > 0 ? nx : 0.f;
    n1[x] = keep > 0 ? ny : 0.f;
    n2[x] = keep > 0 ? nz : 0.f;
    confidence[x] = keep > 0 ? std::min(1.f, std::max(0.f, quality)) : 0.f;
  }
}

// Per-row scratch arrays of the solve; one set per block of rows.
struct RowBuffers {
  std::vector<float> q[3], p[3], s[9], b[3], n[3], inverse_depth, cr, cg, best, level, flags, conf;
  std::vector<int> nearest;
  std::vector<uint8_t> solve;
};

// The per-pixel solve's inputs in float, set up once; SolveRow writes one row of the result.
class NormalSolver {
 public:
  NormalSolver(const cv::Mat& rgb, const RigCalibration& rig, const PhotometricOptions& options,
               const Eigen::Matrix3d& demix, const ColourImage& image, const ClusterModels& models,
               PhotometricResult* result);
  void SolveRow(std::ptrdiff_t row, RowBuffers& buf) const;

 private:
  const cv::Mat& rgb_;
  const RigCalibration& rig_;
  const ColourImage& image_;
  const ClusterModels& models_;
  PhotometricResult& result_;
  const int w_;
  const bool calibrated_;
  const int k_;
  bool point_light_[3];
  Eigen::Vector3f light_row_[3];
  std::vector<Eigen::Vector3f> inverse_albedo_f_;
  std::vector<Eigen::Matrix3f> m_inv_f_;
  Eigen::Matrix3f global_m_f_;
  float cos_max_prior_deviation_, min_level_, saturation_level_, level_scale_, fscale_;
  float lx_[3], ly_[3], lz_[3], li_[3];
  std::vector<float> centre_r_, centre_g_;
  Eigen::Matrix3f demix_q_;
};

NormalSolver::NormalSolver(const cv::Mat& rgb, const RigCalibration& rig, const PhotometricOptions& options,
                           const Eigen::Matrix3d& demix, const ColourImage& image, const ClusterModels& models,
                           PhotometricResult* result)
    : rgb_(rgb),
      rig_(rig),
      image_(image),
      models_(models),
      result_(*result),
      w_(rgb.cols),
      calibrated_(options.mode == PhotometricMode::kCalibrated),
      k_(static_cast<int>(models.centres.size())) {
  const int k = k_;
  // Light geometry for the per-pixel solve, in float: point lights use position and intensity (S
  // row = I v / |v|^3), directional ones direction and intensity (the same as Light::Illuminate).
  Eigen::Vector3f light_position[3];
  float light_intensity[3];
  for (int l = 0; l < 3; ++l) {
    light_position[l] = rig.lights[l].position_in_camera.cast<float>();
    light_intensity[l] = static_cast<float>(rig.lights[l].intensity);
    light_row_[l] = (rig.lights[l].intensity * rig.lights[l].direction_in_camera.normalized()).cast<float>();
    point_light_[l] = rig.lights[l].type == LightType::kPoint;
  }
  inverse_albedo_f_.assign(k + 1, Eigen::Vector3f::Ones());
  m_inv_f_.resize(k + 1);
  for (int m = 0; m <= k; ++m) {
    if (calibrated_) inverse_albedo_f_[m] = models.inverse_albedo[m].cast<float>();
    m_inv_f_[m] = models.m_inv[m].cast<float>();
  }
  const Eigen::Matrix3f demix_solve = demix.cast<float>();
  global_m_f_ = models.global_m.cast<float>();
  std::vector<Eigen::Vector2f> centres_f;
  for (const Eigen::Vector2d& c : models.centres) centres_f.push_back(c.cast<float>());
  cos_max_prior_deviation_ = static_cast<float>(std::cos(options.max_prior_deviation_deg * M_PI / 180));
  min_level_ = static_cast<float>(options.min_level);
  saturation_level_ = static_cast<float>(options.saturation_level);
  level_scale_ = 1.f / static_cast<float>(3.0 * std::max(1.0, options.min_level));
  fscale_ = static_cast<float>(models.scale);
  for (int l = 0; l < 3; ++l) {
    lx_[l] = light_position[l].x();
    ly_[l] = light_position[l].y();
    lz_[l] = light_position[l].z();
    li_[l] = light_intensity[l];
  }
  // Per row: (1) labels and the right-hand sides, scalar; (2) for kCalibrated the 3x3 solves, in
  // float structure-of-arrays and branch-free so that the compiler vectorises them; (3) confidence.
  // n = S^-1 b is only needed up to scale: n ~ adj(S) b sign(det S). And S n = b, so the shading
  // test (each band's share of the light reaching the surface) is a test on b.
  centre_r_.resize(k);
  centre_g_.resize(k);
  for (int m = 0; m < k; ++m) {
    centre_r_[m] = centres_f[m].x();
    centre_g_[m] = centres_f[m].y();
  }
  demix_q_ = demix_solve;
}

void NormalSolver::SolveRow(std::ptrdiff_t row, RowBuffers& buf) const {
  const int w = w_, k = k_;
  const bool calibrated = calibrated_;
  const RigCalibration& rig = rig_;
  const int y = static_cast<int>(row);
  for (int i = 0; i < 3; ++i) {
    buf.q[i].resize(w);
    buf.p[i].resize(w);
    buf.b[i].assign(w, 0.f);
    buf.n[i].resize(w);
  }
  for (auto& v : buf.s) v.resize(w);
  buf.cr.resize(w);
  buf.cg.resize(w);
  buf.best.resize(w);
  buf.nearest.resize(w);
  buf.level.resize(w);
  buf.flags.resize(w);
  buf.conf.resize(w);
  buf.solve.assign(w, 0);
  buf.inverse_depth.resize(w);
  const cv::Vec3b* c = rgb_.ptr<cv::Vec3b>(y);
  const cv::Vec3f* col = image_.color.ptr<cv::Vec3f>(y);
  const float* inv = result_.dense_inverse_depth.ptr<float>(y);
  const cv::Vec3f* n0 = result_.prior_normals.empty() ? nullptr : result_.prior_normals.ptr<cv::Vec3f>(y);
  const int* sp_row = image_.num_sp > 0 ? image_.sp_labels.ptr<int>(y) : nullptr;
  int* lab = result_.labels.ptr<int>(y);
  cv::Vec3f* out = result_.normals.ptr<cv::Vec3f>(y);
  float* conf = result_.confidence.ptr<float>(y);
  const float ray_y = static_cast<float>((y - rig.camera.cy) / rig.camera.fy);
  const float inv_fx = static_cast<float>(1.0 / rig.camera.fx), cx = static_cast<float>(rig.camera.cx);
  // (0) Which pixels are solved, their demixed colour and prior normal as arrays.
  bool any_unlabelled = false;
  for (int x = 0; x < w; ++x) {
    lab[x] = -1;
    out[x] = cv::Vec3f(0, 0, 0);
    conf[x] = 0;
    const int mx = std::max({c[x][0], c[x][1], c[x][2]});
    const bool lit = !calibrated || inv[x] > 0;
    buf.solve[x] = mx >= min_level_ && lit;
    buf.inverse_depth[x] = buf.solve[x] ? inv[x] : 1.f;  // 1 where nothing is solved: keeps kernels finite
    const Eigen::Vector3f q = demix_q_ * Eigen::Vector3f(col[x][0], col[x][1], col[x][2]);
    for (int i = 0; i < 3; ++i) {
      buf.q[i][x] = q[i];
      buf.p[i][x] = n0 ? n0[x][i] : 0.f;
    }
    if (mx >= min_level_) {
      lab[x] = sp_row ? models_.sp_cluster[sp_row[x]] : -1;
      any_unlabelled |= lab[x] < 0 && buf.solve[x];
    }
  }
  // (1) S(p) rows: E_l l_l^T (point lights per pixel; directional lights constant), or for
  // kUncalibrated the global M (for the chromaticity of unlabelled pixels).
  float* s_rows[9];
  for (int i = 0; i < 9; ++i) s_rows[i] = buf.s[i].data();
  for (int l = 0; l < 3; ++l) {
    if (calibrated && point_light_[l]) {
      PointLightRow(w, -cx * inv_fx, inv_fx, ray_y, fscale_, lx_[l], ly_[l], lz_[l], li_[l], buf.inverse_depth.data(),
                    s_rows[3 * l], s_rows[3 * l + 1], s_rows[3 * l + 2]);
    } else {
      for (int j = 0; j < 3; ++j) {
        const float v = calibrated ? light_row_[l][j] : global_m_f_(l, j);
        std::fill(s_rows[3 * l + j], s_rows[3 * l + j] + w, v);
      }
    }
  }
  // (2) Pixels whose superpixel had no fit pixel (a third on the synthetic scenes) take the
  // centre nearest to their own albedo chromaticity under their prior normal.
  if (any_unlabelled && n0) {
    NearestChromaticityRow(w, s_rows, buf.q[0].data(), buf.q[1].data(), buf.q[2].data(), buf.p[0].data(),
                           buf.p[1].data(), buf.p[2].data(), k, centre_r_.data(), centre_g_.data(), buf.cr.data(),
                           buf.cg.data(), buf.best.data(), buf.nearest.data());
    for (int x = 0; x < w; ++x)
      if (buf.solve[x] && lab[x] < 0) lab[x] = buf.nearest[x];
  }
  // (3) Right-hand sides and solves.
  for (int x = 0; x < w; ++x) {
    if (!buf.solve[x]) continue;
    const int model = lab[x] >= 0 ? lab[x] : k;
    const Eigen::Vector3f q(buf.q[0][x], buf.q[1][x], buf.q[2][x]);
    if (calibrated) {
      const Eigen::Vector3f b = q.cwiseProduct(inverse_albedo_f_[model]);
      for (int i = 0; i < 3; ++i) buf.b[i][x] = b[i];
    } else {
      const Eigen::Vector3f n = m_inv_f_[model] * q;
      for (int i = 0; i < 3; ++i) buf.n[i][x] = n[i];
    }
  }
  if (calibrated)
    AdjugateSolveRow(w, s_rows, buf.b[0].data(), buf.b[1].data(), buf.b[2].data(), buf.n[0].data(), buf.n[1].data(),
                     buf.n[2].data());
  // (4) Unit normals facing the camera, and confidence.
  for (int x = 0; x < w; ++x) {
    buf.level[x] = std::max({c[x][0], c[x][1], c[x][2]});
    buf.flags[x] = (buf.solve[x] ? 1.f : 0.f) + (lab[x] < 0 ? 2.f : 0.f);
  }
  FinishRow(w, -cx * inv_fx, inv_fx, ray_y, calibrated, saturation_level_, level_scale_, cos_max_prior_deviation_,
            buf.level.data(), buf.flags.data(), buf.b[0].data(), buf.b[1].data(), buf.b[2].data(), buf.p[0].data(),
            buf.p[1].data(), buf.p[2].data(), buf.n[0].data(), buf.n[1].data(), buf.n[2].data(), buf.conf.data());
  for (int x = 0; x < w; ++x) {
    out[x] = cv::Vec3f(buf.n[0][x], buf.n[1][x], buf.n[2][x]);
    conf[x] = buf.conf[x];
  }
}

}  // namespace

void SolveNormals(const cv::Mat& rgb, const RigCalibration& rig, const PhotometricOptions& options,
                  const Eigen::Matrix3d& demix, const ColourImage& image, const ClusterModels& models, ThreadPool* pool,
                  PhotometricResult* result) {
  const int w = rgb.cols, h = rgb.rows;
  // Label every pixel: its superpixel's cluster, or the nearest centre by its own chromaticity.
  // The outputs are written in full by the per-pixel loop (no separate initialisation pass).
  result->labels.create(h, w, CV_32S);
  result->normals.create(h, w, CV_32FC3);
  result->confidence.create(h, w, CV_32F);
  const NormalSolver solver(rgb, rig, options, demix, image, models, result);
  // Rows in blocks, each block with its own buffers.
  constexpr int kSolveRows = 16;
  auto solve_block = [&](std::ptrdiff_t block) {
    RowBuffers buf;
    for (int y = static_cast<int>(block) * kSolveRows; y < std::min(h, static_cast<int>(block + 1) * kSolveRows); ++y)
      solver.SolveRow(y, buf);
  };
  const int solve_blocks = (h + kSolveRows - 1) / kSolveRows;
  if (pool) {
    pool->ParallelFor(0, solve_blocks, solve_block, 1);
  } else {
    for (int b = 0; b < solve_blocks; ++b) solve_block(b);
  }
}

}  // namespace internal
}  // namespace prism
