#include "core/photometric/photometric_stereo.h"

#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <vector>

#include <Eigen/Dense>
#include <opencv2/core.hpp>

#include "core/photometric/photometric_internal.h"

namespace prism {
namespace {

double Median(std::vector<double>& v) {
  if (v.empty()) return 0.0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
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

  PhotometricResult result;
  internal::ColourImage image;
  internal::PrepareInputs(rgb, prior, rig, options, pool, &result, &image);
  const Eigen::Matrix3d demix = calibrated ? Eigen::Matrix3d(rig.crosstalk.inverse()) : Eigen::Matrix3d::Identity();

  std::mt19937 rng(options.seed);
  std::vector<internal::FitPixel> fit =
      internal::SelectFitPixels(rgb, prior, rig, options, demix, image, result, pool, rng);
  if (fit.size() < 50) return FailedPreconditionError("EstimateNormals: fewer than 50 pixels with a reliable prior");
  if (static_cast<int>(fit.size()) > options.max_fit_pixels) {
    std::shuffle(fit.begin(), fit.end(), rng);
    fit.resize(options.max_fit_pixels);
  }

  internal::ClusterModelFit cluster_fit(rgb, image, rig, options, pool, &fit);
  PRISM_ASSIGN_OR_RETURN(const internal::ClusterModels models, cluster_fit.Fit(&result));
  internal::SolveNormals(rgb, rig, options, demix, image, models, pool, &result);
  return result;
}

}  // namespace prism
