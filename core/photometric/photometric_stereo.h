// Multispectral (colour) photometric stereo from one RGB keyframe (paper §3.3; Anderson, Stenger,
// Cipolla, ICCV 2011), with the SLAM depth prior standing in for the calibration object.
//
// Per pixel, camera colour c = X diag(rho) S(p) n: X the crosstalk, rho the albedo per light band,
// S(p) rows = E_l(p) l_l(p)^T (irradiance times direction of light l at the surface point).
//   kCalibrated:   X, the light positions and intensities come from the rig calibration; S(p) is
//                  evaluated per pixel from the densified depth (near point lights), the unknown
//                  SLAM depth scale is estimated, and rho per chromaticity cluster.
//   kUncalibrated: the paper's model c = M_k n with one 3x3 M_k per chromaticity cluster (distant
//                  lights), fitted by robust least squares to the prior normals.
#pragma once

#include <utility>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/io/calibration_io.h"
#include "core/photometric/depth_prior.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

enum class PhotometricMode { kCalibrated, kUncalibrated };

// Where the prior normals that calibrate the model come from.
enum class PriorNormalSource {
  kPlaneFit,    // planes fitted to the real SLAM points around each pixel (robust to sparse depth)
  kDenseDepth,  // finite differences of the densified depth (PriorNormals)
};

struct PhotometricOptions {
  PhotometricMode mode = PhotometricMode::kCalibrated;
  DensifyOptions densify;
  PriorNormalOptions prior;
  // Pixels darker than this (max channel, 8-bit levels) are not used for fitting and get low
  // confidence, in [0, 255].
  double min_level = 12.0;
  // Pixels with a channel at or above this (8-bit levels) are saturated, in [0, 255].
  double saturation_level = 250.0;
  PriorNormalSource prior_normals = PriorNormalSource::kPlaneFit;
  // kPlaneFit: half-width of the window, pixels, in [2, 50]; minimum SLAM samples in it, >= 3;
  // minimum ratio of the smaller to the larger principal variance of their image positions (spread
  // in two directions, not along one edge curve), in [0, 1]; maximum RMS residual of the plane fit
  // relative to the mean inverse depth (rejects depth edges; SLAM noise is ~1%), in (0, 1].
  int plane_radius_px = 8;
  int min_plane_samples = 15;
  double min_plane_spread = 0.2;
  double max_plane_residual = 0.02;
  // Gaussian smoothing of the colour image before solving, pixels (0 = none), in [0, 5]. Single-shot
  // photometric stereo inherits the sensor noise directly (2.4 deg median at 8 bits with prism-synth's
  // default noise, even with perfect albedo and depth); a sigma of 1 averages about 6 pixels.
  double image_smoothing_sigma_px = 1.0;
  // Minimum local density of real depth samples (Gaussian-weighted fraction of pixels within about
  // two stencil widths) for a pixel's prior normal to be used in fitting, in [0, 1].
  double min_prior_support = 0.05;
  // Pixels whose weakest demixed band is below this fraction of the strongest are treated as
  // shadowed in one light and not used in fitting, in [0, 1).
  double min_band_fraction = 0.1;
  // Rounds of reassigning superpixels to the cluster whose model fits them best, then refitting,
  // in [0, 10].
  int reassignment_rounds = 0;
  // Maximum number of chromaticity clusters (model selection by BIC picks 1..max), in [1, 16].
  int max_clusters = 8;
  // Chromaticity spread (standard deviation, in chromaticity units r/(r+g+b)) that the model
  // selection attributes to noise: clusters closer than this are not split, in [0, 0.5].
  double min_chromaticity_sigma = 0.02;
  // Median chromaticity gradient (per pixel, after image smoothing) along the boundary between two
  // clusters below which they are merged: albedo edges are steps, prior-normal errors are smooth.
  // In chromaticity units per pixel, in [0, 1]; 0 disables merging.
  double min_albedo_edge = 0.01;
  // ... and only when their chromaticity centres are closer than this (chromaticity units), [0, 1].
  double max_merge_chromaticity_distance = 0.1;
  // SLIC superpixel size in pixels (0 = cluster pixels directly), in [0, 100].
  int superpixel_size_px = 20;
  // SLIC runs on the image downsampled by this factor, in [1, 4].
  int superpixel_downsample = 2;
  // Pixels sampled per fit (robust least squares, scale search), in [100, 1e6].
  int max_fit_pixels = 20000;
  // A normal further than this from the dense prior normal gets a tenth of its confidence
  // (degrees, in (0, 180]): the prior is coarse (~11 deg) but a shadowed or mislabelled pixel is
  // usually much further off.
  double max_prior_deviation_deg = 35.0;
  // Fit candidates are taken every fit_pixel_stride pixels in x and y, in [1, 8]. 2 saves little
  // since the plane fits run in raster order, and costs accuracy on multi-coloured surfaces (3.96 ->
  // 4.85 deg pooled in the tests, measured before that change).
  int fit_pixel_stride = 1;
  // kPlaneFit: also compute the dense prior normals (PriorNormals, ~2.5 ms at 512x512, beside the
  // superpixels when there is a pool). They label pixels whose superpixel had no fit pixel, and are
  // returned in PhotometricResult; the dense prior used and returned is then their smoothed one.
  bool output_prior_normals = true;
  // Minimum pixels with reliable priors for a cluster's own model; else the global model is used.
  int min_cluster_pixels = 200;
  // Minimum smallest eigenvalue of the prior normals' scatter (x3) for a cluster's own M
  // (kUncalibrated): the normals must be varied enough, in [0, 1].
  double min_normal_spread = 0.05;
  // kCalibrated: estimate the scale between SLAM depth units and metres (else it is `depth_scale`).
  bool estimate_depth_scale = true;
  // Metres per SLAM depth unit when not estimated, or the centre of the search, > 0.
  double depth_scale = 1.0;
  // Fit pixels used by the scale search (the final fit uses max_fit_pixels), in [100, 1e6]. The scale
  // is a per-session quantity: a pipeline estimates it on its first keyframes and then passes it
  // with estimate_depth_scale = false, which is much cheaper.
  int scale_search_pixels = 20000;
  // Search range of the scale around depth_scale (factor), > 1.
  double depth_scale_search_factor = 4.0;
  uint32_t seed = 1;

  Status Check() const;
};

struct PhotometricResult {
  cv::Mat normals;              // CV_32FC3, camera frame, facing the camera; (0,0,0) = none
  cv::Mat confidence;           // CV_32F in [0, 1]
  cv::Mat labels;               // CV_32S chromaticity cluster per pixel, -1 = none
  cv::Mat dense_inverse_depth;  // CV_32F, the densified prior
  cv::Mat prior_normals;        // CV_32FC3, from the densified prior (empty unless computed)
  int num_clusters = 0;
  double depth_scale = 1.0;                       // metres per depth unit used (kCalibrated)
  std::vector<Eigen::Vector3d> cluster_albedo;    // kCalibrated, per cluster
  std::vector<Eigen::Matrix3d> cluster_lighting;  // kUncalibrated, M_k per cluster
};

// rgb: CV_8UC3 (RGB order). The prior must have the image's size. rig: camera and, in
// kCalibrated mode, the lights and crosstalk. With a `pool`, the depth-prior and colour/superpixel
// stages run side by side and the per-pixel and per-fit-pixel loops are spread over it; the result
// is the same bit for bit with or without it (fixed chunks, sums in a fixed order).
StatusOr<PhotometricResult> EstimateNormals(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                                            const PhotometricOptions& options, ThreadPool* pool = nullptr);

// The depth scale (metres per SLAM depth unit) of a session from per-keyframe estimates
// (PhotometricResult::depth_scale with estimate_depth_scale = true). A single keyframe whose shading
// or depth constrains the scale poorly can be far off: on SLAM depth the first two keyframes, whose
// depth comes from the monocular initialisation, gave 3.3 and 2.8 m/unit where the later ones gave
// 0.44-0.68 (true 0.566). So the value is the median of the largest group of estimates that agree
// with each other (largest / smallest <= agreement_factor), and a pipeline keeps estimating until
// that group has enough members (agreeing()). Once settled, it passes the value as
// PhotometricOptions::depth_scale with estimate_depth_scale = false, which is also several times
// cheaper. Not thread-safe.
// Largest ratio between two depth-scale estimates that agree.
constexpr double kDepthScaleAgreement = 1.25;

class SessionDepthScale {
 public:
  // agreement_factor >= 1 (checked).
  explicit SessionDepthScale(double agreement_factor = kDepthScaleAgreement);
  void Add(double keyframe_estimate);  // ignores non-finite or non-positive values
  bool has_value() const { return !estimates_.empty(); }
  int count() const { return static_cast<int>(estimates_.size()); }
  // Size of the largest group of estimates within agreement_factor of each other (0 when empty).
  int agreeing() const;
  double value() const;  // median of that group (the tightest one on ties); requires has_value()

 private:
  // [begin, end) of the largest agreeing group in the sorted estimates.
  std::pair<size_t, size_t> Group(const std::vector<double>& sorted) const;
  double agreement_factor_;
  std::vector<double> estimates_;
};

// Robust (Huber IRLS) least-squares fit of M in c = M n over corresponding colours and unit
// normals; false when the normals do not span 3D well enough.
bool FitLightingMatrix(const std::vector<Eigen::Vector3d>& colors, const std::vector<Eigen::Vector3d>& normals,
                       Eigen::Matrix3d* lighting);

}  // namespace prism
