#include "core/photometric/photometric_stereo.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <numeric>
#include <random>
#include <sstream>

#include <Eigen/Dense>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/photometric/superpixels.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// One pixel used for fitting.
struct FitPixel {
  int x, y;
  Eigen::Vector3d q;     // demixed colour (per light band), [0, 1] units
  Eigen::Vector3d n0;    // prior normal, camera frame
  Eigen::Vector3d ray;   // (u, v, 1) ray of the pixel
  double inverse_depth;  // dense prior
  double support = 1.0;
  int label = -1;
};

double Median(std::vector<double>& v) {
  if (v.empty()) return 0.0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// Per-band shading E_l * max(0, l_l . n) at the point `ray / inverse_depth * scale`.
// Light::Illuminate's arithmetic, inlined.
Eigen::Vector3d NearLightShading(const RigCalibration& rig, const Eigen::Vector3d& point, const Eigen::Vector3d& n) {
  Eigen::Vector3d a;
  for (int l = 0; l < 3; ++l) {
    const Light& light = rig.lights[l];
    if (light.type == LightType::kDirectional) {
      a[l] = light.intensity * std::max(0.0, light.direction_in_camera.normalized().dot(n));
      continue;
    }
    const Eigen::Vector3d d = light.position_in_camera - point;
    const double d2 = d.squaredNorm();
    const Eigen::Vector3d to_light = d / std::sqrt(d2);
    a[l] = (light.intensity / d2) * std::max(0.0, to_light.dot(n));
  }
  return a;
}

// S(p): rows E_l l_l^T. Light::Illuminate's arithmetic, inlined (it runs 20000 times per fit, 60
// fits per scale search).
Eigen::Matrix3d NearLightMatrix(const RigCalibration& rig, const Eigen::Vector3d& point) {
  Eigen::Matrix3d s;
  for (int l = 0; l < 3; ++l) {
    const Light& light = rig.lights[l];
    if (light.type == LightType::kDirectional) {
      s.row(l) = light.intensity * light.direction_in_camera.normalized().transpose();
      continue;
    }
    const Eigen::Vector3d d = light.position_in_camera - point;
    const double d2 = d.squaredNorm();
    const Eigen::Vector3d to_light = d / std::sqrt(d2);
    s.row(l) = (light.intensity / d2) * to_light.transpose();
  }
  return s;
}

// Per-band albedo estimate of a pixel under scale s (NaN components where a band is unlit).
Eigen::Vector3d AlbedoEstimate(const RigCalibration& rig, const FitPixel& p, double scale) {
  const Eigen::Vector3d a = NearLightShading(rig, p.ray * (scale / p.inverse_depth), p.n0);
  Eigen::Vector3d rho;
  for (int l = 0; l < 3; ++l) rho[l] = a[l] > 1e-4 ? p.q[l] / a[l] : std::nan("");
  return rho;
}

Eigen::Vector2d Chromaticity(const Eigen::Vector3d& v) {
  const double s = v.x() + v.y() + v.z();
  return Eigen::Vector2d(v.x() / s, v.y() / s);
}

// k-means with BIC model selection on 2D chromaticities; returns centres.
std::vector<Eigen::Vector2d> ClusterChromaticities(const std::vector<Eigen::Vector2d>& samples,
                                                   const std::vector<float>& weights, int max_clusters,
                                                   double min_sigma, uint32_t seed) {
  const int n = static_cast<int>(samples.size());
  if (n == 0) return {};
  cv::Mat data(n, 2, CV_32F);
  for (int i = 0; i < n; ++i) {
    data.at<float>(i, 0) = static_cast<float>(samples[i].x());
    data.at<float>(i, 1) = static_cast<float>(samples[i].y());
  }
  double total_w = 0;
  for (float w : weights) total_w += w;
  double best_bic = std::numeric_limits<double>::infinity();
  std::vector<Eigen::Vector2d> best;
  for (int k = 1; k <= std::min(max_clusters, n); ++k) {
    cv::Mat labels, centres;
    cv::theRNG().state = 0x1234567ull + seed;
    cv::kmeans(data, k, labels, cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-6), 3,
               cv::KMEANS_PP_CENTERS, centres);
    double sse = 0;
    for (int i = 0; i < n; ++i) {
      const int c = labels.at<int>(i);
      const double dx = data.at<float>(i, 0) - centres.at<float>(c, 0),
                   dy = data.at<float>(i, 1) - centres.at<float>(c, 1);
      sse += weights[i] * (dx * dx + dy * dy);
    }
    // Isotropic Gaussian per cluster, shared variance; parameters: k centres (2 each) + k-1 weights.
    // The variance floor stands for the chromaticity noise that the prior normals' errors cause:
    // spread below it is shading error, not albedo, and must not create clusters.
    const double var = std::max(sse / (2 * total_w), std::max(1e-10, min_sigma * min_sigma));
    const double bic = 2 * total_w * std::log(var) + (3.0 * k - 1) * std::log(total_w);
    if (bic < best_bic) {
      best_bic = bic;
      best.clear();
      for (int c = 0; c < k; ++c) best.emplace_back(centres.at<float>(c, 0), centres.at<float>(c, 1));
    }
  }
  return best;
}

int Nearest(const std::vector<Eigen::Vector2d>& centres, const Eigen::Vector2d& v) {
  int best = -1;
  double bd = std::numeric_limits<double>::infinity();
  for (size_t c = 0; c < centres.size(); ++c) {
    const double d = (centres[c] - v).squaredNorm();
    if (d < bd) {
      bd = d;
      best = static_cast<int>(c);
    }
  }
  return best;
}

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

}  // namespace

Status PhotometricOptions::Check() const {
  PRISM_RETURN_IF_ERROR(densify.Check());
  PRISM_RETURN_IF_ERROR(prior.Check());
  std::ostringstream e;
  if (!(min_level >= 0 && min_level <= 255))
    e << "PhotometricOptions.min_level = " << min_level << "; violated: in [0, 255]";
  else if (!(saturation_level > min_level && saturation_level <= 255))
    e << "PhotometricOptions.saturation_level = " << saturation_level << "; violated: in (min_level, 255]";
  else if (!(image_smoothing_sigma_px >= 0 && image_smoothing_sigma_px <= 5))
    e << "PhotometricOptions.image_smoothing_sigma_px = " << image_smoothing_sigma_px << "; violated: in [0, 5]";
  else if (!(min_prior_support >= 0 && min_prior_support <= 1))
    e << "PhotometricOptions.min_prior_support = " << min_prior_support << "; violated: in [0, 1]";
  else if (!(min_band_fraction >= 0 && min_band_fraction < 1))
    e << "PhotometricOptions.min_band_fraction = " << min_band_fraction << "; violated: in [0, 1)";
  else if (reassignment_rounds < 0 || reassignment_rounds > 10)
    e << "PhotometricOptions.reassignment_rounds = " << reassignment_rounds << "; violated: in [0, 10]";
  else if (!(max_merge_chromaticity_distance >= 0 && max_merge_chromaticity_distance <= 1))
    e << "PhotometricOptions.max_merge_chromaticity_distance = " << max_merge_chromaticity_distance
      << "; violated: in [0, 1]";
  else if (!(min_albedo_edge >= 0 && min_albedo_edge <= 1))
    e << "PhotometricOptions.min_albedo_edge = " << min_albedo_edge << "; violated: in [0, 1]";
  else if (!(min_chromaticity_sigma >= 0 && min_chromaticity_sigma <= 0.5))
    e << "PhotometricOptions.min_chromaticity_sigma = " << min_chromaticity_sigma << "; violated: in [0, 0.5]";
  else if (plane_radius_px < 2 || plane_radius_px > 50)
    e << "PhotometricOptions.plane_radius_px = " << plane_radius_px << "; violated: in [2, 50]";
  else if (min_plane_samples < 3)
    e << "PhotometricOptions.min_plane_samples = " << min_plane_samples << "; violated: >= 3";
  else if (!(max_plane_residual > 0 && max_plane_residual <= 1))
    e << "PhotometricOptions.max_plane_residual = " << max_plane_residual << "; violated: in (0, 1]";
  else if (!(min_plane_spread >= 0 && min_plane_spread <= 1))
    e << "PhotometricOptions.min_plane_spread = " << min_plane_spread << "; violated: in [0, 1]";
  else if (!(max_prior_deviation_deg > 0 && max_prior_deviation_deg <= 180))
    e << "PhotometricOptions.max_prior_deviation_deg = " << max_prior_deviation_deg << "; violated: in (0, 180]";
  else if (fit_pixel_stride < 1 || fit_pixel_stride > 8)
    e << "PhotometricOptions.fit_pixel_stride = " << fit_pixel_stride << "; violated: in [1, 8]";
  else if (superpixel_downsample < 1 || superpixel_downsample > 4)
    e << "PhotometricOptions.superpixel_downsample = " << superpixel_downsample << "; violated: in [1, 4]";
  else if (max_clusters < 1 || max_clusters > 16)
    e << "PhotometricOptions.max_clusters = " << max_clusters << "; violated: in [1, 16]";
  else if (superpixel_size_px < 0 || superpixel_size_px > 100)
    e << "PhotometricOptions.superpixel_size_px = " << superpixel_size_px << "; violated: in [0, 100]";
  else if (max_fit_pixels < 100 || max_fit_pixels > 1000000)
    e << "PhotometricOptions.max_fit_pixels = " << max_fit_pixels << "; violated: in [100, 1e6]";
  else if (min_cluster_pixels < 10)
    e << "PhotometricOptions.min_cluster_pixels = " << min_cluster_pixels << "; violated: >= 10";
  else if (!(min_normal_spread >= 0 && min_normal_spread <= 1))
    e << "PhotometricOptions.min_normal_spread = " << min_normal_spread << "; violated: in [0, 1]";
  else if (!(depth_scale > 0)) e << "PhotometricOptions.depth_scale = " << depth_scale << "; violated: > 0";
  else if (!(depth_scale_search_factor > 1))
    e << "PhotometricOptions.depth_scale_search_factor = " << depth_scale_search_factor << "; violated: > 1";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

void SessionDepthScale::Add(double keyframe_estimate) {
  if (std::isfinite(keyframe_estimate) && keyframe_estimate > 0) estimates_.push_back(keyframe_estimate);
}

SessionDepthScale::SessionDepthScale(double agreement_factor) : agreement_factor_(agreement_factor) {
  PRISM_CHECK(agreement_factor >= 1.0) << "SessionDepthScale: agreement_factor must be >= 1, got " << agreement_factor;
}

std::pair<size_t, size_t> SessionDepthScale::Group(const std::vector<double>& sorted) const {
  std::pair<size_t, size_t> best(0, 0);
  for (size_t begin = 0, end = 0; begin < sorted.size(); ++begin) {
    end = std::max(end, begin);
    while (end < sorted.size() && sorted[end] <= sorted[begin] * agreement_factor_) ++end;
    // Largest group; among equal sizes the tightest (largest smallest/largest ratio).
    const size_t size = end - begin, best_size = best.second - best.first;
    if (size > best_size ||
        (size == best_size && sorted[begin] / sorted[end - 1] > sorted[best.first] / sorted[best.second - 1]))
      best = {begin, end};
  }
  return best;
}

int SessionDepthScale::agreeing() const {
  std::vector<double> v = estimates_;
  std::sort(v.begin(), v.end());
  const auto [begin, end] = Group(v);
  return static_cast<int>(end - begin);
}

double SessionDepthScale::value() const {
  PRISM_CHECK(!estimates_.empty()) << "SessionDepthScale::value() without estimates";
  std::vector<double> v = estimates_;
  std::sort(v.begin(), v.end());
  const auto [begin, end] = Group(v);
  std::vector<double> group(v.begin() + static_cast<std::ptrdiff_t>(begin),
                            v.begin() + static_cast<std::ptrdiff_t>(end));
  return Median(group);
}

bool FitLightingMatrix(const std::vector<Eigen::Vector3d>& colors, const std::vector<Eigen::Vector3d>& normals,
                       Eigen::Matrix3d* lighting) {
  const size_t n = colors.size();
  if (n < 6 || normals.size() != n) return false;
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const auto& nn : normals) scatter += nn * nn.transpose();
  scatter /= static_cast<double>(n);
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(scatter);
  if (eig.eigenvalues().minCoeff() < 1e-4) return false;
  Eigen::Matrix3d m = Eigen::Matrix3d::Zero();
  std::vector<double> w(n, 1.0);
  for (int iter = 0; iter < 6; ++iter) {
    for (int c = 0; c < 3; ++c) {
      Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
      Eigen::Vector3d b = Eigen::Vector3d::Zero();
      for (size_t i = 0; i < n; ++i) {
        a += w[i] * normals[i] * normals[i].transpose();
        b += w[i] * colors[i][c] * normals[i];
      }
      m.row(c) = a.ldlt().solve(b).transpose();
    }
    // Huber weights on the residual norm, threshold 1.345 x robust sigma (MAD).
    std::vector<double> r(n);
    for (size_t i = 0; i < n; ++i) r[i] = (colors[i] - m * normals[i]).norm();
    std::vector<double> rr = r;
    const double sigma = std::max(1e-6, 1.4826 * Median(rr));
    const double k = 1.345 * sigma;
    for (size_t i = 0; i < n; ++i) w[i] = r[i] <= k ? 1.0 : k / r[i];
  }
  *lighting = m;
  return true;
}

StatusOr<PhotometricResult> EstimateNormals(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                                            const PhotometricOptions& options, ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (rgb.type() != CV_8UC3) return InvalidArgumentError("EstimateNormals: image must be 8-bit RGB (CV_8UC3)");
  if (prior.inverse_depth.type() != CV_32F || prior.variance.type() != CV_32F ||
      prior.inverse_depth.size() != rgb.size() || prior.variance.size() != rgb.size())
    return InvalidArgumentError("EstimateNormals: depth prior must be two CV_32F maps of the image's size");
  if (rig.camera.width != rgb.cols || rig.camera.height != rgb.rows)
    return InvalidArgumentError("EstimateNormals: camera size differs from the image size");
  const bool calibrated = options.mode == PhotometricMode::kCalibrated;
  if (calibrated) PRISM_RETURN_IF_ERROR(rig.Check());

  const int w = rgb.cols, h = rgb.rows;
  PhotometricResult result;
  const bool plane_priors = options.prior_normals == PriorNormalSource::kPlaneFit;
  // Two independent chains, run side by side when a pool is given: the depth prior (densified, and
  // the prior normals), and the colour image (smoothed) with its superpixels.
  auto depth_chain = [&](ThreadPool* chain_pool) {
    result.dense_inverse_depth = DensifyInverseDepth(prior, options.densify);
    // Dense prior normals: the fitting input in kDenseDepth mode; otherwise only an optional
    // output. When they are computed, the dense prior used from here on (fit pixels' depth, the
    // per-pixel S(p), the returned map) is the smoothed one they are differentiated from. Earlier
    // versions did this through an aliasing side effect of PriorNormals; the results (depth scale,
    // accuracy, fusion) were measured with it, so it is kept, now on purpose.
    if (!plane_priors || options.output_prior_normals)
      result.prior_normals =
          PriorNormals(result.dense_inverse_depth, rig.camera, options.prior, chain_pool, &result.dense_inverse_depth);
  };
  // Linear colour in [0, 1] (optionally smoothed), before demixing.
  cv::Mat color;
  // Superpixels (SLIC) give spatially coherent clusters.
  cv::Mat sp_labels;
  int num_sp = 0;
  auto colour_chain = [&]() {
    rgb.convertTo(color, CV_32FC3, 1.0 / 255.0);
    if (options.image_smoothing_sigma_px > 0) {
      const int ksize = static_cast<int>(std::ceil(3 * options.image_smoothing_sigma_px)) * 2 + 1;
      cv::GaussianBlur(color, color, cv::Size(ksize, ksize), options.image_smoothing_sigma_px);
    }
    if (options.superpixel_size_px > 0) {
      // SLIC runs on an image downsampled by superpixel_downsample (~2 ms at 256x256); labels are
      // upsampled by nearest neighbour.
      const int f = options.superpixel_downsample;
      cv::Mat small = rgb;
      if (f > 1) cv::resize(rgb, small, cv::Size((w + f - 1) / f, (h + f - 1) / f), 0, 0, cv::INTER_AREA);
      cv::Mat lab;
      cv::cvtColor(small, lab, cv::COLOR_RGB2Lab);
      num_sp = SlicSuperpixels(lab, std::max(2, options.superpixel_size_px / f), 5, &sp_labels);
      if (f > 1) cv::resize(sp_labels, sp_labels, cv::Size(w, h), 0, 0, cv::INTER_NEAREST);
    }
  };
  if (pool && pool->num_threads() > 1) {
    pool->ParallelFor(
        0, 2, [&](std::ptrdiff_t chain) { chain == 0 ? depth_chain(nullptr) : colour_chain(); }, 1);
  } else {
    depth_chain(pool);
    colour_chain();
  }
  const Eigen::Matrix3d demix = calibrated ? Eigen::Matrix3d(rig.crosstalk.inverse()) : Eigen::Matrix3d::Identity();

  // Support: the local density of real (semi-dense) samples. Far from samples the densified depth
  // is an extrapolation and its normals are not a usable prior.
  cv::Mat support;
  if (!plane_priors) {
    cv::Mat samples;
    cv::Mat(prior.inverse_depth > 0).convertTo(samples, CV_32F, 1.0 / 255.0);
    const double sigma = std::max(2.0, 2.0 * options.prior.step_px);
    const int ksize = static_cast<int>(std::ceil(3 * sigma)) * 2 + 1;
    cv::GaussianBlur(samples, support, cv::Size(ksize, ksize), sigma);
  }
  // Reliable pixels: prior normal present near real samples, neither dark nor saturated, lit by all
  // three lights (a band near zero is an attached or cast shadow).
  // Candidates are taken on a grid of step fit_pixel_stride: the fit uses a random subset anyway.
  // They are kept compact (shuffling ~1e5 full FitPixels cost ~10 ms); FitPixels are made for the
  // ones used.
  struct Candidate {
    int x, y;
  };
  // Row blocks (on the pool when given), concatenated in raster order.
  const int stride = options.fit_pixel_stride;
  const Eigen::Matrix3f demix_f = demix.cast<float>();
  constexpr int kCandidateRows = 32;
  const int candidate_blocks = (h + kCandidateRows - 1) / kCandidateRows;
  std::vector<std::vector<Candidate>> block_candidates(candidate_blocks);
  auto find_candidates = [&](std::ptrdiff_t block) {
    std::vector<Candidate>& out = block_candidates[block];
    const int y_end = std::min(h, static_cast<int>(block + 1) * kCandidateRows);
    for (int y = static_cast<int>(block) * kCandidateRows; y < y_end; ++y) {
      if (y % stride != 0) continue;
      const cv::Vec3b* c = rgb.ptr<cv::Vec3b>(y);
      const cv::Vec3f* n0 = plane_priors ? nullptr : result.prior_normals.ptr<cv::Vec3f>(y);
      const float* inv = result.dense_inverse_depth.ptr<float>(y);
      const cv::Vec3f* col = color.ptr<cv::Vec3f>(y);
      for (int x = 0; x < w; x += stride) {
        if (!plane_priors && n0[x][2] == 0 && n0[x][0] == 0) continue;
        if (!(inv[x] > 0)) continue;
        const int mx = std::max({c[x][0], c[x][1], c[x][2]});
        if (mx < options.min_level || mx >= options.saturation_level) continue;
        if (!plane_priors && support.at<float>(y, x) < options.min_prior_support) continue;
        const Eigen::Vector3f q = demix_f * Eigen::Vector3f(col[x][0], col[x][1], col[x][2]);
        if (q.minCoeff() < options.min_band_fraction * q.maxCoeff()) continue;
        out.push_back({x, y});
      }
    }
  };
  if (pool) {
    pool->ParallelFor(0, candidate_blocks, find_candidates, 1);
  } else {
    for (int b = 0; b < candidate_blocks; ++b) find_candidates(b);
  }
  std::vector<Candidate> candidates;
  {
    size_t total = 0;
    for (const auto& v : block_candidates) total += v.size();
    candidates.reserve(total);
    for (const auto& v : block_candidates) candidates.insert(candidates.end(), v.begin(), v.end());
  }
  auto make_fit_pixel = [&](const Candidate& cand) {
    FitPixel p;
    p.x = cand.x;
    p.y = cand.y;
    // Recomputed in double from the image (the float copy only served the candidate test).
    const cv::Vec3f cf = color.at<cv::Vec3f>(cand.y, cand.x);
    p.q = demix * Eigen::Vector3d(cf[0], cf[1], cf[2]);
    if (!plane_priors) {
      const cv::Vec3f n = result.prior_normals.at<cv::Vec3f>(cand.y, cand.x);
      p.n0 = Eigen::Vector3d(n[0], n[1], n[2]);
    }
    p.ray = Eigen::Vector3d((cand.x - rig.camera.cx) / rig.camera.fx, (cand.y - rig.camera.cy) / rig.camera.fy, 1.0);
    p.inverse_depth = result.dense_inverse_depth.at<float>(cand.y, cand.x);
    return p;
  };
  std::vector<FitPixel> fit;
  std::mt19937 rng(options.seed);
  if (plane_priors) {
    // Prior normals fitted as planes to the real SLAM samples in a window. A plane's inverse depth is
    // linear in the normalised image coordinates: 1/z = A x + B y + C with (A, B, C) parallel to its
    // normal, and SLAM's noise is in inverse depth, so a linear least-squares fit (windowed moments)
    // has the right noise model. With ~10% of pixels holding a sample, a +-8 px window averages ~30
    // samples, where finite differences of the interpolated depth see one or two. Windows whose
    // samples lie along one curve (semi-dense points follow edges) or whose residual is too large
    // for a plane (a depth edge) are rejected.
    // Most candidates are rejected (~85% on the synthetic scenes), so every candidate is tested, in
    // raster order: the window moments come from column sums slid down the image and a prefix sum
    // along the row, all in cache. Row blocks are independent (each starts its column sums afresh).
    std::vector<Eigen::Vector3f> plane_normal(candidates.size());
    std::vector<uint8_t> accepted(candidates.size(), 0);
    std::vector<size_t> row_begin(h + 1);
    {
      size_t i = 0;
      for (int y = 0; y <= h; ++y) {
        while (i < candidates.size() && candidates[i].y < y) ++i;
        row_begin[y] = i;
      }
    }
    constexpr int kRowsPerBlock = 32;
    const int num_blocks = (h + kRowsPerBlock - 1) / kRowsPerBlock;
    auto fit_block = [&](std::ptrdiff_t block) {
      const int r = options.plane_radius_px;
      const int y_begin = static_cast<int>(block) * kRowsPerBlock, y_end = std::min(h, y_begin + kRowsPerBlock);
      if (row_begin[y_begin] == row_begin[y_end]) return;
      constexpr int kMoments = 10;                                               // 1, x, y, xx, xy, yy, w, xw, yw, ww
      std::vector<double> column(static_cast<size_t>(kMoments) * w, 0.0);        // [x][k]
      std::vector<double> prefix(static_cast<size_t>(kMoments) * (w + 1), 0.0);  // [x + 1][k]
      auto add_row = [&](int y, double sign) {
        if (y < 0 || y >= h) return;
        const float* id_row = prior.inverse_depth.ptr<float>(y);
        const double py = (y - rig.camera.cy) / rig.camera.fy;
        for (int x = 0; x < w; ++x) {
          const double id = id_row[x];
          if (!(id > 0)) continue;
          const double px = (x - rig.camera.cx) / rig.camera.fx;
          const double v[kMoments] = {1, px, py, px * px, px * py, py * py, id, px * id, py * id, id * id};
          double* c = &column[static_cast<size_t>(x) * kMoments];
          for (int k = 0; k < kMoments; ++k) c[k] += sign * v[k];
        }
      };
      for (int y = y_begin - r; y < y_begin + r; ++y) add_row(y, 1.0);
      for (int y = y_begin; y < y_end; ++y) {
        add_row(y + r, 1.0);
        if (y > y_begin) add_row(y - r - 1, -1.0);
        if (row_begin[y] == row_begin[y + 1]) continue;
        for (int x = 0; x < w; ++x)
          for (int k = 0; k < kMoments; ++k)
            prefix[static_cast<size_t>(x + 1) * kMoments + k] =
                prefix[static_cast<size_t>(x) * kMoments + k] + column[static_cast<size_t>(x) * kMoments + k];
        for (size_t i = row_begin[y]; i < row_begin[y + 1]; ++i) {
          const int x = candidates[i].x;
          const double* hi = &prefix[static_cast<size_t>(std::min(w - 1, x + r) + 1) * kMoments];
          const double* lo = &prefix[static_cast<size_t>(std::max(0, x - r)) * kMoments];
          const double n = std::round(hi[0] - lo[0]);  // a count: exact up to the sliding sums' rounding
          if (n < options.min_plane_samples) continue;
          double m[kMoments];
          for (int k = 0; k < kMoments; ++k) m[k] = hi[k] - lo[k];
          // Spread of the samples in the image: both principal variances of (x, y) must be sizeable
          // (closed-form eigenvalues of the 2x2 covariance).
          const double mx = m[1] / n, my = m[2] / n;
          const double cxx = m[3] / n - mx * mx, cxy = m[4] / n - mx * my, cyy = m[5] / n - my * my;
          const double mean = 0.5 * (cxx + cyy), dev = std::sqrt(0.25 * (cxx - cyy) * (cxx - cyy) + cxy * cxy);
          if (!(mean - dev > options.min_plane_spread * (mean + dev))) continue;
          Eigen::Matrix3d ata;
          ata << m[3], m[4], m[1], m[4], m[5], m[2], m[1], m[2], n;
          const Eigen::Vector3d atb(m[7], m[8], m[6]);
          const Eigen::Vector3d abc = ata.ldlt().solve(atb);
          if (!abc.allFinite()) continue;
          // Residual: sum (w - A x - B y - C)^2 = sum w^2 - 2 abc.atb + abc' ata abc.
          const double sse = m[9] - 2 * abc.dot(atb) + abc.dot(ata * abc);
          const double mean_w = m[6] / n;
          if (!(mean_w > 0) || std::sqrt(std::max(0.0, sse) / n) > options.max_plane_residual * mean_w) continue;
          // (A, B, C) . (x, y, 1) = 1/z > 0 for visible points: the normal facing the camera is -(A, B, C).
          const Eigen::Vector3d normal = -abc.normalized();
          const Eigen::Vector3d ray((x - rig.camera.cx) / rig.camera.fx, (y - rig.camera.cy) / rig.camera.fy, 1.0);
          if (normal.dot(ray) > 0) continue;
          plane_normal[i] = normal.cast<float>();
          accepted[i] = 1;
        }
      }
    };
    // The first max_fit_pixels accepted candidates in a random order of all candidates (the same
    // subset and order as testing them one by one in that order). The subset matters more than one
    // would think: other random subsets of the same size move the pooled multi-coloured sphere error
    // between 3.6 and 4.0 deg. The shuffle (serial) runs beside the plane fits.
    std::vector<uint32_t> order(candidates.size());
    auto shuffle_or_fit = [&](std::ptrdiff_t task) {
      if (task == 0) {
        std::iota(order.begin(), order.end(), 0u);
        std::shuffle(order.begin(), order.end(), rng);
      } else {
        fit_block(task - 1);
      }
    };
    if (pool) {
      pool->ParallelFor(0, num_blocks + 1, shuffle_or_fit, 1);
    } else {
      for (int task = 0; task <= num_blocks; ++task) shuffle_or_fit(task);
    }
    std::vector<uint32_t> kept;
    for (uint32_t i : order) {
      if (!accepted[i]) continue;
      kept.push_back(i);
      if (static_cast<int>(kept.size()) >= options.max_fit_pixels) break;
    }
    fit.resize(kept.size());
    auto make_fit_pixels = [&](std::ptrdiff_t j) {
      fit[j] = make_fit_pixel(candidates[kept[j]]);
      fit[j].n0 = plane_normal[kept[j]].cast<double>();
    };
    if (pool) {
      pool->ParallelFor(0, static_cast<std::ptrdiff_t>(kept.size()), make_fit_pixels, 1024);
    } else {
      for (size_t j = 0; j < kept.size(); ++j) make_fit_pixels(static_cast<std::ptrdiff_t>(j));
    }
  } else {
    if (static_cast<int>(candidates.size()) > options.max_fit_pixels) {
      std::shuffle(candidates.begin(), candidates.end(), rng);
      candidates.resize(options.max_fit_pixels);
    }
    for (const Candidate& cand : candidates) fit.push_back(make_fit_pixel(cand));
  }
  if (fit.size() < 50) return FailedPreconditionError("EstimateNormals: fewer than 50 pixels with a reliable prior");
  if (static_cast<int>(fit.size()) > options.max_fit_pixels) {
    std::shuffle(fit.begin(), fit.end(), rng);
    fit.resize(options.max_fit_pixels);
  }

  // Chromaticity of each fit pixel (normal-independent albedo direction).
  double scale = options.depth_scale;
  Eigen::Matrix3d global_m = Eigen::Matrix3d::Identity();
  auto chroma_of = [&](const FitPixel& p, Eigen::Vector2d* out) {
    Eigen::Vector3d r;
    if (calibrated) {
      r = AlbedoEstimate(rig, p, scale);
    } else {
      const Eigen::Vector3d pred = global_m * p.n0;
      for (int l = 0; l < 3; ++l) r[l] = pred[l] > 1e-4 ? p.q[l] / pred[l] : std::nan("");
    }
    if (!r.allFinite() || r.minCoeff() <= 0) return false;
    *out = Chromaticity(r);
    return true;
  };
  if (!calibrated) {
    std::vector<Eigen::Vector3d> cs, ns;
    for (const FitPixel& p : fit) {
      cs.push_back(p.q);
      ns.push_back(p.n0);
    }
    if (!FitLightingMatrix(cs, ns, &global_m))
      return FailedPreconditionError("EstimateNormals: prior normals too uniform to fit the lighting");
  }

  // The fit pixels are processed in fixed chunks (on the pool when given) whose sums are added in
  // chunk order: the result does not depend on the number of threads.
  constexpr size_t kFitChunk = 1024;
  auto for_chunks = [&](size_t n, const std::function<void(size_t, size_t, size_t)>& fn) {
    const size_t chunks = (n + kFitChunk - 1) / kFitChunk;
    auto run = [&](std::ptrdiff_t c) {
      const size_t begin = static_cast<size_t>(c) * kFitChunk;
      fn(static_cast<size_t>(c), begin, std::min(n, begin + kFitChunk));
    };
    if (pool && chunks > 1) {
      pool->ParallelFor(0, static_cast<std::ptrdiff_t>(chunks), run, 1);
    } else {
      for (size_t c = 0; c < chunks; ++c) run(static_cast<std::ptrdiff_t>(c));
    }
    return chunks;
  };
  auto cluster = [&](double min_sigma) {
    std::vector<Eigen::Vector2d> samples;
    std::vector<float> weights;
    std::vector<Eigen::Vector2d> pixel_chroma(fit.size());
    std::vector<uint8_t> has(fit.size(), 0);
    for_chunks(fit.size(), [&](size_t, size_t begin, size_t end) {
      for (size_t i = begin; i < end; ++i) has[i] = chroma_of(fit[i], &pixel_chroma[i]);
    });
    if (num_sp > 0) {
      std::vector<Eigen::Vector2d> sum(num_sp, Eigen::Vector2d::Zero());
      std::vector<int> count(num_sp, 0);
      for (size_t i = 0; i < fit.size(); ++i) {
        if (!has[i]) continue;
        const int s = sp_labels.at<int>(fit[i].y, fit[i].x);
        sum[s] += pixel_chroma[i];
        count[s]++;
      }
      for (int s = 0; s < num_sp; ++s)
        if (count[s] > 0) {
          samples.push_back(sum[s] / count[s]);
          weights.push_back(static_cast<float>(count[s]));
        }
      const auto centres = ClusterChromaticities(samples, weights, options.max_clusters, min_sigma, options.seed);
      std::vector<int> sp_cluster(num_sp, -1);
      for (int s = 0; s < num_sp; ++s)
        if (count[s] > 0) sp_cluster[s] = Nearest(centres, sum[s] / count[s]);
      return std::make_pair(centres, sp_cluster);
    }
    for (size_t i = 0; i < fit.size(); ++i)
      if (has[i]) {
        samples.push_back(pixel_chroma[i]);
        weights.push_back(1.f);
      }
    return std::make_pair(ClusterChromaticities(samples, weights, options.max_clusters, min_sigma, options.seed),
                          std::vector<int>());
  };

  std::vector<Eigen::Vector2d> centres;
  std::vector<int> sp_cluster;
  auto label_fit_pixels = [&]() {
    for (FitPixel& p : fit) {
      if (num_sp > 0) {
        p.label = sp_cluster[sp_labels.at<int>(p.y, p.x)];
      } else {
        Eigen::Vector2d ch;
        p.label = chroma_of(p, &ch) ? Nearest(centres, ch) : -1;
      }
    }
  };

  // Calibrated fit of each cluster's relative albedo. Only the albedo's chromaticity matters for the
  // normal's direction (n = normalize(S^-1 diag(1/rho) q)), so brightness variation inside a
  // cluster (texture) is harmless. With u = 1/rho, the photometric normal A_i u (A_i = S_i^-1
  // diag(q_i)) should be parallel to the prior normal n0_i: (I - n0 n0^T) A_i u = 0 is linear in u,
  // and u is the smallest eigenvector of sum_i w_i A_i^T (I - n0 n0^T) A_i (IRLS with Cauchy weights
  // on the angle). This uses the noisy prior normals only through an average over many pixels.
  std::vector<Eigen::Vector3d> inverse_albedo;
  constexpr double kCauchyScale = 0.2;  // sine of the angle at which a prior normal counts half
  std::vector<Eigen::Matrix3d> a;       // A_i at the scale of the last fit_directions call
  std::vector<Eigen::Matrix3d> apa;     // A_i^T (I - n0 n0^T) A_i
  std::vector<uint8_t> usable;          // not vector<bool>: written from several threads
  // Uses the first `num_pixels` fit pixels (they are shuffled) and `iterations` IRLS rounds.
  struct ChunkSums {
    std::vector<Eigen::Matrix3d> h;
    std::vector<int> counts;
    double cost = 0, weight_sum = 0;
  };
  std::vector<ChunkSums> chunk_sums;
  auto fit_directions = [&](double s, size_t num_pixels, int iterations) {
    const int k = static_cast<int>(centres.size());
    const size_t n_fit = std::min(num_pixels, fit.size());
    a.resize(fit.size());
    apa.resize(fit.size());
    usable.assign(fit.size(), 0);
    for_chunks(n_fit, [&](size_t, size_t begin, size_t end) {
      for (size_t i = begin; i < end; ++i) {
        const Eigen::Matrix3d sm = NearLightMatrix(rig, fit[i].ray * (s / fit[i].inverse_depth));
        const double det = sm.determinant();
        if (!(std::abs(det) > 1e-12)) continue;
        a[i] = sm.inverse() * fit[i].q.asDiagonal();  // closed-form 3x3 inverse
        usable[i] = a[i].allFinite();
        // A^T (I - n0 n0^T) A is fixed across the IRLS rounds: only the weights change.
        const Eigen::Vector3d an0 = a[i].transpose() * fit[i].n0;
        apa[i] = a[i].transpose() * a[i] - an0 * an0.transpose();
      }
    });
    inverse_albedo.assign(k + 1, Eigen::Vector3d::Ones());
    double cost = 0;
    double weight_sum = 0;
    for (int iter = 0; iter < iterations; ++iter) {
      // Only the last round's cost is returned.
      const bool want_cost = iter + 1 == iterations;
      chunk_sums.resize((n_fit + kFitChunk - 1) / kFitChunk);
      const size_t chunks = for_chunks(n_fit, [&](size_t chunk, size_t begin, size_t end) {
        ChunkSums& sums = chunk_sums[chunk];
        sums.h.assign(k + 1, Eigen::Matrix3d::Zero());
        sums.counts.assign(k + 1, 0);
        sums.cost = sums.weight_sum = 0;
        for (size_t i = begin; i < end; ++i) {
          if (!usable[i]) continue;
          for (int m : {fit[i].label, k}) {
            if (m < 0) continue;
            const Eigen::Vector3d n = a[i] * inverse_albedo[m];
            const double len2 = n.squaredNorm();
            if (len2 < 1e-18) continue;
            // sin^2 of the angle to n0: |(I - n0 n0^T) n|^2 / |n|^2 = 1 - (n0 . n)^2 / |n|^2.
            const double c = fit[i].n0.dot(n);
            const double r2 = std::max(0.0, 1.0 - c * c / len2) / (kCauchyScale * kCauchyScale);
            const double w = 1.0 / (1.0 + r2);
            sums.h[m] += (w / len2) * apa[i];
            sums.counts[m]++;
            if (want_cost && m == (fit[i].label >= 0 ? fit[i].label : k)) {
              sums.cost += std::log1p(r2);
              sums.weight_sum += 1;
            }
          }
        }
      });
      std::vector<Eigen::Matrix3d> h(k + 1, Eigen::Matrix3d::Zero());
      std::vector<int> counts(k + 1, 0);
      cost = 0;
      weight_sum = 0;
      for (size_t c = 0; c < chunks; ++c) {
        for (int m = 0; m <= k; ++m) {
          h[m] += chunk_sums[c].h[m];
          counts[m] += chunk_sums[c].counts[m];
        }
        cost += chunk_sums[c].cost;
        weight_sum += chunk_sums[c].weight_sum;
      }
      for (int m = k; m >= 0; --m) {
        const bool own = counts[m] >= options.min_cluster_pixels || m == k;
        if (!own || counts[m] < 3) {
          inverse_albedo[m] = inverse_albedo[k];
          continue;
        }
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(h[m]);
        Eigen::Vector3d u = eig.eigenvectors().col(0);
        if (u.sum() < 0) u = -u;
        if (u.minCoeff() <= 0 || !u.allFinite()) {
          inverse_albedo[m] = inverse_albedo[k];
          continue;
        }
        inverse_albedo[m] = u / u.sum() * 3.0;
      }
    }
    return weight_sum > 0 ? cost / weight_sum : std::numeric_limits<double>::infinity();
  };
  // The scale search runs on a subsample with fewer IRLS rounds; the final fit uses every fit pixel.
  auto scale_cost = [&](double s) { return fit_directions(s, options.scale_search_pixels, 4); };
  // Reassigns each superpixel to the cluster whose albedo explains its prior normals best: the
  // chromaticity clusters come from noisy per-pixel estimates and can mix similar colours (an
  // off-white object on a beige floor); the model fit separates them.
  auto reassign_superpixels = [&]() {
    const int k = static_cast<int>(centres.size());
    if (num_sp == 0 || k < 2) return;
    std::vector<double> cost(static_cast<size_t>(num_sp) * k, 0.0);
    std::vector<int> count(num_sp, 0);
    for (size_t i = 0; i < fit.size(); ++i) {
      if (!usable[i]) continue;
      const int sp = sp_labels.at<int>(fit[i].y, fit[i].x);
      count[sp]++;
      const Eigen::Matrix3d proj = Eigen::Matrix3d::Identity() - fit[i].n0 * fit[i].n0.transpose();
      for (int m = 0; m < k; ++m) {
        const Eigen::Vector3d n = a[i] * inverse_albedo[m];
        const double len = n.norm();
        const double r = len > 1e-9 ? (proj * n).norm() / len : 1.0;
        cost[static_cast<size_t>(sp) * k + m] += std::log1p((r / kCauchyScale) * (r / kCauchyScale));
      }
    }
    for (int sp = 0; sp < num_sp; ++sp) {
      if (count[sp] == 0) continue;
      const double* c = &cost[static_cast<size_t>(sp) * k];
      sp_cluster[sp] = static_cast<int>(std::min_element(c, c + k) - c);
    }
    label_fit_pixels();
  };

  // Chromaticity edges validate cluster splits: albedo boundaries are sharp steps of the image
  // chromaticity, while the errors of the prior normals (which can also split a cluster) vary
  // smoothly. Two clusters whose shared superpixel boundaries show no step are merged.
  // Only needed on the boundaries between clusters: computed there, from the smoothed colour.
  auto chroma_at = [&](int x, int y) {
    const cv::Vec3f c = color.at<cv::Vec3f>(y, x);
    const float sum = std::max(1e-4f, c[0] + c[1] + c[2]);
    return cv::Vec2f(c[0] / sum, c[1] / sum);
  };
  auto chroma_gradient_at = [&](int x, int y) {
    if (x <= 0 || y <= 0 || x >= w - 1 || y >= h - 1) return 0.f;
    const cv::Vec2f dx = 0.5f * (chroma_at(x + 1, y) - chroma_at(x - 1, y));
    const cv::Vec2f dy = 0.5f * (chroma_at(x, y + 1) - chroma_at(x, y - 1));
    return std::sqrt(dx.dot(dx) + dy.dot(dy));
  };
  auto merge_by_edges = [&]() {
    const int k = static_cast<int>(centres.size());
    if (num_sp == 0 || k < 2) return;
    // Per cluster pair: gradient samples on boundaries between their superpixels (dark pixels,
    // whose chromaticity is noise, are skipped).
    std::vector<std::vector<float>> steps(static_cast<size_t>(k) * k);
    for (int y = 1; y < h - 1; ++y) {
      const int* sp_row = sp_labels.ptr<int>(y);
      const int* sp_down = sp_labels.ptr<int>(y + 1);
      const cv::Vec3b* c = rgb.ptr<cv::Vec3b>(y);
      for (int x = 1; x < w - 1; ++x) {
        const int ca = sp_cluster[sp_row[x]];
        if (ca < 0) continue;
        // Only where a neighbour (right, below) is in another cluster.
        const int cr = sp_cluster[sp_row[x + 1]], cd = sp_cluster[sp_down[x]];
        if ((cr < 0 || cr == ca) && (cd < 0 || cd == ca)) continue;
        if (std::max({c[x][0], c[x][1], c[x][2]}) < options.min_level) continue;
        const float g = chroma_gradient_at(x, y);
        if (cr >= 0 && cr != ca)
          steps[static_cast<size_t>(std::min(ca, cr)) * k + std::max(ca, cr)].push_back(
              std::max(g, chroma_gradient_at(x + 1, y)));
        if (cd >= 0 && cd != ca)
          steps[static_cast<size_t>(std::min(ca, cd)) * k + std::max(ca, cd)].push_back(
              std::max(g, chroma_gradient_at(x, y + 1)));
      }
    }
    std::vector<int> parent(k);
    std::iota(parent.begin(), parent.end(), 0);
    std::function<int(int)> find = [&](int i) { return parent[i] == i ? i : parent[i] = find(parent[i]); };
    for (int a = 0; a < k; ++a)
      for (int b = a + 1; b < k; ++b) {
        auto& v = steps[static_cast<size_t>(a) * k + b];
        if (v.size() < 20) continue;  // not neighbours (or barely): leave them apart
        // A real albedo edge is a step along most of the shared boundary: use the median.
        std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
        // Only clusters of similar chromaticity can be one albedo split by prior-normal errors.
        const bool similar = (centres[a] - centres[b]).norm() < options.max_merge_chromaticity_distance;
        if (similar && v[v.size() / 2] < options.min_albedo_edge) parent[find(a)] = find(b);
      }
    std::vector<int> new_index(k, -1);
    std::vector<Eigen::Vector2d> merged;
    std::vector<double> weight;
    for (int c = 0; c < k; ++c) {
      const int r = find(c);
      if (new_index[r] < 0) {
        new_index[r] = static_cast<int>(merged.size());
        merged.push_back(Eigen::Vector2d::Zero());
        weight.push_back(0);
      }
    }
    std::vector<int> count(k, 0);
    for (int sp = 0; sp < num_sp; ++sp)
      if (sp_cluster[sp] >= 0) count[sp_cluster[sp]]++;
    for (int c = 0; c < k; ++c) {
      const int m = new_index[find(c)];
      merged[m] += (count[c] + 1e-9) * centres[c];
      weight[m] += count[c] + 1e-9;
    }
    for (size_t m = 0; m < merged.size(); ++m) merged[m] /= weight[m];
    for (int sp = 0; sp < num_sp; ++sp)
      if (sp_cluster[sp] >= 0) sp_cluster[sp] = new_index[find(sp_cluster[sp])];
    centres = merged;
    label_fit_pixels();
  };

  auto clustered = cluster(options.min_chromaticity_sigma);
  centres = clustered.first;
  sp_cluster = clustered.second;
  label_fit_pixels();
  merge_by_edges();
  if (calibrated && options.estimate_depth_scale) {
    // Log-grid search, then golden-section refinement; re-cluster once at the found scale and
    // search again. Where the shading constrains the scale poorly the cost is flat and a single
    // keyframe's estimate can be far off: sessions should use SessionDepthScale.
    for (int pass = 0; pass < 2; ++pass) {
      const double lo = std::log(options.depth_scale / options.depth_scale_search_factor);
      const double hi = std::log(options.depth_scale * options.depth_scale_search_factor);
      const int steps = 16;
      std::vector<double> grid_cost(steps + 1);
      for (int i = 0; i <= steps; ++i) grid_cost[i] = scale_cost(std::exp(lo + (hi - lo) * i / steps));
      // Prefer the lowest interior local minimum: towards very small scales the points approach the
      // lights and the model can bend to fit anything, so a minimum at the range's end is suspect.
      int best_i = static_cast<int>(std::min_element(grid_cost.begin(), grid_cost.end()) - grid_cost.begin());
      double best_interior = std::numeric_limits<double>::infinity();
      for (int i = 1; i < steps; ++i)
        if (grid_cost[i] < grid_cost[i - 1] && grid_cost[i] <= grid_cost[i + 1] && grid_cost[i] < best_interior) {
          best_interior = grid_cost[i];
          best_i = i;
        }
      const double best_t = lo + (hi - lo) * best_i / steps;
      double a = best_t - (hi - lo) / steps, b = best_t + (hi - lo) / steps;
      const double g = 0.5 * (std::sqrt(5.0) - 1);
      double x1 = b - g * (b - a), x2 = a + g * (b - a);
      double f1 = scale_cost(std::exp(x1)), f2 = scale_cost(std::exp(x2));
      for (int i = 0; i < 12; ++i) {
        if (f1 < f2) {
          b = x2;
          x2 = x1;
          f2 = f1;
          x1 = b - g * (b - a);
          f1 = scale_cost(std::exp(x1));
        } else {
          a = x1;
          x1 = x2;
          f1 = f2;
          x2 = a + g * (b - a);
          f2 = scale_cost(std::exp(x2));
        }
      }
      scale = std::exp(0.5 * (a + b));
      if (pass == 0) {
        clustered = cluster(options.min_chromaticity_sigma);
        centres = clustered.first;
        sp_cluster = clustered.second;
        label_fit_pixels();
        merge_by_edges();
      }
    }
  }
  const int k = static_cast<int>(centres.size());
  result.num_clusters = k;
  result.depth_scale = scale;

  // Per-cluster models.
  std::vector<Eigen::Matrix3d> m_inv(k + 1, Eigen::Matrix3d::Identity());
  if (calibrated) {
    fit_directions(scale, fit.size(), 6);
    for (int round = 0; round < options.reassignment_rounds; ++round) {
      reassign_superpixels();
      fit_directions(scale, fit.size(), 6);
    }
    for (int c = 0; c < k; ++c) {
      const Eigen::Vector3d rho = inverse_albedo[c].cwiseInverse();
      result.cluster_albedo.push_back(rho / rho.sum());
    }
  } else {
    std::vector<std::vector<Eigen::Vector3d>> cs(k), ns(k);
    for (const FitPixel& p : fit)
      if (p.label >= 0) {
        cs[p.label].push_back(p.q);
        ns[p.label].push_back(p.n0);
      }
    result.cluster_lighting.assign(k, global_m);
    for (int c = 0; c < k; ++c) {
      Eigen::Matrix3d m;
      bool ok = static_cast<int>(cs[c].size()) >= options.min_cluster_pixels;
      if (ok) {
        Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
        for (const auto& n : ns[c]) scatter += n * n.transpose();
        scatter /= static_cast<double>(ns[c].size());
        ok = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvalues().minCoeff() * 3 >=
             options.min_normal_spread;
      }
      if (ok && FitLightingMatrix(cs[c], ns[c], &m) && std::abs(m.determinant()) > 1e-12)
        result.cluster_lighting[c] = m;
      m_inv[c] = result.cluster_lighting[c].inverse();
    }
    m_inv[k] = global_m.inverse();
  }

  // Label every pixel: its superpixel's cluster, or the nearest centre by its own chromaticity.
  // The outputs are written in full by the per-pixel loop (no separate initialisation pass).
  result.labels.create(h, w, CV_32S);
  result.normals.create(h, w, CV_32FC3);
  result.confidence.create(h, w, CV_32F);
  // Light geometry for the per-pixel solve, in float: point lights use position and intensity (S
  // row = I v / |v|^3), directional ones direction and intensity (the same as Light::Illuminate).
  bool point_light[3];
  Eigen::Vector3f light_position[3], light_row[3];
  float light_intensity[3];
  for (int l = 0; l < 3; ++l) {
    light_position[l] = rig.lights[l].position_in_camera.cast<float>();
    light_intensity[l] = static_cast<float>(rig.lights[l].intensity);
    light_row[l] = (rig.lights[l].intensity * rig.lights[l].direction_in_camera.normalized()).cast<float>();
    point_light[l] = rig.lights[l].type == LightType::kPoint;
  }
  std::vector<Eigen::Vector3f> inverse_albedo_f(k + 1, Eigen::Vector3f::Ones());
  std::vector<Eigen::Matrix3f> m_inv_f(k + 1);
  for (int m = 0; m <= k; ++m) {
    if (calibrated) inverse_albedo_f[m] = inverse_albedo[m].cast<float>();
    m_inv_f[m] = m_inv[m].cast<float>();
  }
  const Eigen::Matrix3f demix_solve = demix.cast<float>();
  const Eigen::Matrix3f global_m_f = global_m.cast<float>();
  std::vector<Eigen::Vector2f> centres_f;
  for (const Eigen::Vector2d& c : centres) centres_f.push_back(c.cast<float>());
  const float cos_max_prior_deviation = static_cast<float>(std::cos(options.max_prior_deviation_deg * M_PI / 180));
  const float min_level = static_cast<float>(options.min_level),
              saturation_level = static_cast<float>(options.saturation_level);
  const float level_scale = 1.f / static_cast<float>(3.0 * std::max(1.0, options.min_level));
  const float fscale = static_cast<float>(scale);
  float lx[3], ly[3], lz[3], li[3];
  for (int l = 0; l < 3; ++l) {
    lx[l] = light_position[l].x();
    ly[l] = light_position[l].y();
    lz[l] = light_position[l].z();
    li[l] = light_intensity[l];
  }
  // Per row: (1) labels and the right-hand sides, scalar; (2) for kCalibrated the 3x3 solves, in
  // float structure-of-arrays and branch-free so that the compiler vectorises them; (3) confidence.
  // n = S^-1 b is only needed up to scale: n ~ adj(S) b sign(det S). And S n = b, so the shading
  // test (each band's share of the light reaching the surface) is a test on b.
  std::vector<float> centre_r(k), centre_g(k);
  for (int m = 0; m < k; ++m) {
    centre_r[m] = centres_f[m].x();
    centre_g[m] = centres_f[m].y();
  }
  const Eigen::Matrix3f demix_q = demix_solve;
  struct RowBuffers {
    std::vector<float> q[3], p[3], s[9], b[3], n[3], inverse_depth, cr, cg, best, level, flags, conf;
    std::vector<int> nearest;
    std::vector<uint8_t> solve;
  };
  auto solve_row = [&](std::ptrdiff_t row, RowBuffers& buf) {
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
    const cv::Vec3b* c = rgb.ptr<cv::Vec3b>(y);
    const cv::Vec3f* col = color.ptr<cv::Vec3f>(y);
    const float* inv = result.dense_inverse_depth.ptr<float>(y);
    const cv::Vec3f* n0 = result.prior_normals.empty() ? nullptr : result.prior_normals.ptr<cv::Vec3f>(y);
    const int* sp_row = num_sp > 0 ? sp_labels.ptr<int>(y) : nullptr;
    int* lab = result.labels.ptr<int>(y);
    cv::Vec3f* out = result.normals.ptr<cv::Vec3f>(y);
    float* conf = result.confidence.ptr<float>(y);
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
      buf.solve[x] = mx >= min_level && lit;
      buf.inverse_depth[x] = buf.solve[x] ? inv[x] : 1.f;  // 1 where nothing is solved: keeps kernels finite
      const Eigen::Vector3f q = demix_q * Eigen::Vector3f(col[x][0], col[x][1], col[x][2]);
      for (int i = 0; i < 3; ++i) {
        buf.q[i][x] = q[i];
        buf.p[i][x] = n0 ? n0[x][i] : 0.f;
      }
      if (mx >= min_level) {
        lab[x] = sp_row ? sp_cluster[sp_row[x]] : -1;
        any_unlabelled |= lab[x] < 0 && buf.solve[x];
      }
    }
    // (1) S(p) rows: E_l l_l^T (point lights per pixel; directional lights constant), or for
    // kUncalibrated the global M (for the chromaticity of unlabelled pixels).
    float* s_rows[9];
    for (int i = 0; i < 9; ++i) s_rows[i] = buf.s[i].data();
    for (int l = 0; l < 3; ++l) {
      if (calibrated && point_light[l]) {
        PointLightRow(w, -cx * inv_fx, inv_fx, ray_y, fscale, lx[l], ly[l], lz[l], li[l], buf.inverse_depth.data(),
                      s_rows[3 * l], s_rows[3 * l + 1], s_rows[3 * l + 2]);
      } else {
        for (int j = 0; j < 3; ++j) {
          const float v = calibrated ? light_row[l][j] : global_m_f(l, j);
          std::fill(s_rows[3 * l + j], s_rows[3 * l + j] + w, v);
        }
      }
    }
    // (2) Pixels whose superpixel had no fit pixel (a third on the synthetic scenes) take the
    // centre nearest to their own albedo chromaticity under their prior normal.
    if (any_unlabelled && n0) {
      NearestChromaticityRow(w, s_rows, buf.q[0].data(), buf.q[1].data(), buf.q[2].data(), buf.p[0].data(),
                             buf.p[1].data(), buf.p[2].data(), k, centre_r.data(), centre_g.data(), buf.cr.data(),
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
        const Eigen::Vector3f b = q.cwiseProduct(inverse_albedo_f[model]);
        for (int i = 0; i < 3; ++i) buf.b[i][x] = b[i];
      } else {
        const Eigen::Vector3f n = m_inv_f[model] * q;
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
    FinishRow(w, -cx * inv_fx, inv_fx, ray_y, calibrated, saturation_level, level_scale, cos_max_prior_deviation,
              buf.level.data(), buf.flags.data(), buf.b[0].data(), buf.b[1].data(), buf.b[2].data(), buf.p[0].data(),
              buf.p[1].data(), buf.p[2].data(), buf.n[0].data(), buf.n[1].data(), buf.n[2].data(), buf.conf.data());
    for (int x = 0; x < w; ++x) {
      out[x] = cv::Vec3f(buf.n[0][x], buf.n[1][x], buf.n[2][x]);
      conf[x] = buf.conf[x];
    }
  };
  // Rows in blocks, each block with its own buffers.
  constexpr int kSolveRows = 16;
  auto solve_block = [&](std::ptrdiff_t block) {
    RowBuffers buf;
    for (int y = static_cast<int>(block) * kSolveRows; y < std::min(h, static_cast<int>(block + 1) * kSolveRows); ++y)
      solve_row(y, buf);
  };
  const int solve_blocks = (h + kSolveRows - 1) / kSolveRows;
  if (pool) {
    pool->ParallelFor(0, solve_blocks, solve_block, 1);
  } else {
    for (int b = 0; b < solve_blocks; ++b) solve_block(b);
  }
  return result;
}

}  // namespace prism
