// The stages of EstimateNormals (photometric_stereo.h), in the order it runs them: the inputs (depth
// prior and colour image), the fit pixels, the chromaticity clusters with their models, and the
// per-pixel solve. Internal to prism_photometric; tests and callers use EstimateNormals.
#pragma once

#include <cstdint>
#include <functional>
#include <random>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/io/calibration_io.h"
#include "core/photometric/depth_prior.h"
#include "core/photometric/photometric_stereo.h"
#include "core/util/status.h"

namespace prism {

class ThreadPool;

namespace internal {

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

// The colour chain's output.
struct ColourImage {
  // Linear colour in [0, 1] (optionally smoothed), before demixing.
  cv::Mat color;
  // Superpixels (SLIC) give spatially coherent clusters.
  cv::Mat sp_labels;
  int num_sp = 0;
};

// Two independent chains, run side by side when a pool is given: the depth prior (densified, and
// the prior normals, into result->dense_inverse_depth and result->prior_normals), and the colour
// image (smoothed) with its superpixels.
void PrepareInputs(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                   const PhotometricOptions& options, ThreadPool* pool, PhotometricResult* result, ColourImage* image);

// The pixels the models are fitted to (at most max_fit_pixels when their prior normals are plane
// fits; otherwise the caller subsamples), drawing on `rng`.
std::vector<FitPixel> SelectFitPixels(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                                      const PhotometricOptions& options, const Eigen::Matrix3d& demix,
                                      const ColourImage& image, const PhotometricResult& result, ThreadPool* pool,
                                      std::mt19937& rng);

// What the per-pixel solve needs from the fit. Index k (the number of clusters) is the global model.
struct ClusterModels {
  double scale = 1.0;                                      // metres per depth unit (kCalibrated)
  Eigen::Matrix3d global_m = Eigen::Matrix3d::Identity();  // kUncalibrated: M over all fit pixels
  std::vector<Eigen::Vector2d> centres;                    // chromaticity centre per cluster
  std::vector<int> sp_cluster;                             // cluster per superpixel, -1 = none
  std::vector<Eigen::Vector3d> inverse_albedo;             // kCalibrated: 1 / rho per cluster and global
  std::vector<Eigen::Matrix3d> m_inv;                      // kUncalibrated: M_k^-1 per cluster and global
};

// Clusters the fit pixels by chromaticity (over superpixels when there are any), merges clusters
// that no albedo edge separates, estimates the depth scale (kCalibrated, when asked), and fits each
// cluster's model to the prior normals: relative albedo (kCalibrated) or M_k (kUncalibrated).
class ClusterModelFit {
 public:
  // All arguments must outlive the object; `fit` gets its labels.
  ClusterModelFit(const cv::Mat& rgb, const ColourImage& image, const RigCalibration& rig,
                  const PhotometricOptions& options, ThreadPool* pool, std::vector<FitPixel>* fit);

  // Fills result->num_clusters, depth_scale and cluster_albedo or cluster_lighting. FAILED_PRECONDITION
  // when kUncalibrated and the prior normals are too uniform to fit the global M.
  StatusOr<ClusterModels> Fit(PhotometricResult* result);

 private:
  // Sums of one chunk of fit pixels in FitDirections.
  struct ChunkSums {
    std::vector<Eigen::Matrix3d> h;
    std::vector<int> counts;
    double cost = 0, weight_sum = 0;
  };

  bool ChromaOf(const FitPixel& p, Eigen::Vector2d* out) const;
  size_t ForChunks(size_t n, const std::function<void(size_t, size_t, size_t)>& fn) const;
  std::pair<std::vector<Eigen::Vector2d>, std::vector<int>> Cluster(double min_sigma);
  void LabelFitPixels();
  void ClusterAndMerge();
  double FitDirections(double s, size_t num_pixels, int iterations);
  double ScaleCost(double s);
  void SearchDepthScale();
  void ReassignSuperpixels();
  cv::Vec2f ChromaAt(int x, int y) const;
  float ChromaGradientAt(int x, int y) const;
  void MergeByEdges();
  void FitClusterModels(PhotometricResult* result);

  const cv::Mat& rgb_;
  const ColourImage& image_;
  const RigCalibration& rig_;
  const PhotometricOptions& options_;
  ThreadPool* pool_;
  std::vector<FitPixel>& fit_;
  const bool calibrated_;
  const int w_, h_;
  ClusterModels models_;
  std::vector<Eigen::Matrix3d> a_;    // A_i at the scale of the last FitDirections call
  std::vector<Eigen::Matrix3d> apa_;  // A_i^T (I - n0 n0^T) A_i
  std::vector<uint8_t> usable_;       // not vector<bool>: written from several threads
  std::vector<ChunkSums> chunk_sums_;
};

// The per-pixel solve: result->labels, normals and confidence.
void SolveNormals(const cv::Mat& rgb, const RigCalibration& rig, const PhotometricOptions& options,
                  const Eigen::Matrix3d& demix, const ColourImage& image, const ClusterModels& models, ThreadPool* pool,
                  PhotometricResult* result);

}  // namespace internal
}  // namespace prism
