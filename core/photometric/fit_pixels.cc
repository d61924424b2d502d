// EstimateNormals' inputs and fit pixels: the depth and colour chains, the candidate pixels, their
// prior normals (plane fits to the SLAM samples or the dense prior normals), and the subset used.
#include <algorithm>
#include <cmath>
#include <numeric>

#include <Eigen/Dense>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/photometric/photometric_internal.h"
#include "core/photometric/superpixels.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {
namespace {

// Reliable pixels: prior normal present near real samples, neither dark nor saturated, lit by all
// three lights (a band near zero is an attached or cast shadow).
// Candidates are taken on a grid of step fit_pixel_stride: the fit uses a random subset anyway.
// They are kept compact (shuffling ~1e5 full FitPixels cost ~10 ms); FitPixels are made for the
// ones used.
struct Candidate {
  int x, y;
};

// Window moments per column in a plane-fit row block.
constexpr int kMoments = 10;  // 1, x, y, xx, xy, yy, w, xw, yw, ww

// Adds (sign 1) or removes (sign -1) row y's SLAM samples to the column sums ([x][k]).
void AddRowMoments(const cv::Mat& inverse_depth, const PinholeCamera& camera, int w, int h, int y, double sign,
                   std::vector<double>& column) {
  if (y < 0 || y >= h) return;
  const float* id_row = inverse_depth.ptr<float>(y);
  const double py = (y - camera.cy) / camera.fy;
  for (int x = 0; x < w; ++x) {
    const double id = id_row[x];
    if (!(id > 0)) continue;
    const double px = (x - camera.cx) / camera.fx;
    const double v[kMoments] = {1, px, py, px * px, px * py, py * py, id, px * id, py * id, id * id};
    double* c = &column[static_cast<size_t>(x) * kMoments];
    for (int k = 0; k < kMoments; ++k) c[k] += sign * v[k];
  }
}

class FitPixelSelector {
 public:
  FitPixelSelector(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                   const PhotometricOptions& options, const Eigen::Matrix3d& demix, const ColourImage& image,
                   const PhotometricResult& result, ThreadPool* pool)
      : rgb_(rgb),
        prior_(prior),
        rig_(rig),
        options_(options),
        demix_(demix),
        image_(image),
        result_(result),
        pool_(pool),
        w_(rgb.cols),
        h_(rgb.rows),
        plane_priors_(options.prior_normals == PriorNormalSource::kPlaneFit) {}

  std::vector<FitPixel> Select(std::mt19937& rng);

 private:
  cv::Mat Support() const;
  std::vector<Candidate> FindCandidates(const cv::Mat& support) const;
  FitPixel MakeFitPixel(const Candidate& cand) const;
  void FitPlaneBlock(std::ptrdiff_t block, const std::vector<Candidate>& candidates,
                     const std::vector<size_t>& row_begin, std::vector<Eigen::Vector3f>& plane_normal,
                     std::vector<uint8_t>& accepted) const;
  std::vector<FitPixel> PlaneFitPixels(const std::vector<Candidate>& candidates, std::mt19937& rng) const;

  static constexpr int kRowsPerBlock = 32;

  const cv::Mat& rgb_;
  const InverseDepthMap& prior_;
  const RigCalibration& rig_;
  const PhotometricOptions& options_;
  const Eigen::Matrix3d& demix_;
  const ColourImage& image_;
  const PhotometricResult& result_;
  ThreadPool* pool_;
  const int w_, h_;
  const bool plane_priors_;
};

// Support: the local density of real (semi-dense) samples. Far from samples the densified depth
// is an extrapolation and its normals are not a usable prior.
cv::Mat FitPixelSelector::Support() const {
  cv::Mat support;
  if (!plane_priors_) {
    cv::Mat samples;
    cv::Mat(prior_.inverse_depth > 0).convertTo(samples, CV_32F, 1.0 / 255.0);
    const double sigma = std::max(2.0, 2.0 * options_.prior.step_px);
    const int ksize = static_cast<int>(std::ceil(3 * sigma)) * 2 + 1;
    cv::GaussianBlur(samples, support, cv::Size(ksize, ksize), sigma);
  }
  return support;
}

std::vector<Candidate> FitPixelSelector::FindCandidates(const cv::Mat& support) const {
  const int w = w_, h = h_;
  const bool plane_priors = plane_priors_;
  const PhotometricOptions& options = options_;
  // Row blocks (on the pool when given), concatenated in raster order.
  const int stride = options.fit_pixel_stride;
  const Eigen::Matrix3f demix_f = demix_.cast<float>();
  constexpr int kCandidateRows = 32;
  const int candidate_blocks = (h + kCandidateRows - 1) / kCandidateRows;
  std::vector<std::vector<Candidate>> block_candidates(candidate_blocks);
  auto find_candidates = [&](std::ptrdiff_t block) {
    std::vector<Candidate>& out = block_candidates[block];
    const int y_end = std::min(h, static_cast<int>(block + 1) * kCandidateRows);
    for (int y = static_cast<int>(block) * kCandidateRows; y < y_end; ++y) {
      if (y % stride != 0) continue;
      const cv::Vec3b* c = rgb_.ptr<cv::Vec3b>(y);
      const cv::Vec3f* n0 = plane_priors ? nullptr : result_.prior_normals.ptr<cv::Vec3f>(y);
      const float* inv = result_.dense_inverse_depth.ptr<float>(y);
      const cv::Vec3f* col = image_.color.ptr<cv::Vec3f>(y);
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
  if (pool_) {
    pool_->ParallelFor(0, candidate_blocks, find_candidates, 1);
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
  return candidates;
}

FitPixel FitPixelSelector::MakeFitPixel(const Candidate& cand) const {
  FitPixel p;
  p.x = cand.x;
  p.y = cand.y;
  // Recomputed in double from the image (the float copy only served the candidate test).
  const cv::Vec3f cf = image_.color.at<cv::Vec3f>(cand.y, cand.x);
  p.q = demix_ * Eigen::Vector3d(cf[0], cf[1], cf[2]);
  if (!plane_priors_) {
    const cv::Vec3f n = result_.prior_normals.at<cv::Vec3f>(cand.y, cand.x);
    p.n0 = Eigen::Vector3d(n[0], n[1], n[2]);
  }
  p.ray = Eigen::Vector3d((cand.x - rig_.camera.cx) / rig_.camera.fx, (cand.y - rig_.camera.cy) / rig_.camera.fy, 1.0);
  p.inverse_depth = result_.dense_inverse_depth.at<float>(cand.y, cand.x);
  return p;
}

// Plane fits of the candidates in one block of kRowsPerBlock rows.
void FitPixelSelector::FitPlaneBlock(std::ptrdiff_t block, const std::vector<Candidate>& candidates,
                                     const std::vector<size_t>& row_begin, std::vector<Eigen::Vector3f>& plane_normal,
                                     std::vector<uint8_t>& accepted) const {
  const int w = w_, h = h_;
  const PhotometricOptions& options = options_;
  const RigCalibration& rig = rig_;
  const int r = options.plane_radius_px;
  const int y_begin = static_cast<int>(block) * kRowsPerBlock, y_end = std::min(h, y_begin + kRowsPerBlock);
  if (row_begin[y_begin] == row_begin[y_end]) return;
  std::vector<double> column(static_cast<size_t>(kMoments) * w, 0.0);        // [x][k]
  std::vector<double> prefix(static_cast<size_t>(kMoments) * (w + 1), 0.0);  // [x + 1][k]
  for (int y = y_begin - r; y < y_begin + r; ++y) AddRowMoments(prior_.inverse_depth, rig.camera, w, h, y, 1.0, column);
  for (int y = y_begin; y < y_end; ++y) {
    AddRowMoments(prior_.inverse_depth, rig.camera, w, h, y + r, 1.0, column);
    if (y > y_begin) AddRowMoments(prior_.inverse_depth, rig.camera, w, h, y - r - 1, -1.0, column);
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
}

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
std::vector<FitPixel> FitPixelSelector::PlaneFitPixels(const std::vector<Candidate>& candidates,
                                                       std::mt19937& rng) const {
  const int h = h_;
  std::vector<FitPixel> fit;
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
  const int num_blocks = (h + kRowsPerBlock - 1) / kRowsPerBlock;
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
      FitPlaneBlock(task - 1, candidates, row_begin, plane_normal, accepted);
    }
  };
  if (pool_) {
    pool_->ParallelFor(0, num_blocks + 1, shuffle_or_fit, 1);
  } else {
    for (int task = 0; task <= num_blocks; ++task) shuffle_or_fit(task);
  }
  std::vector<uint32_t> kept;
  for (uint32_t i : order) {
    if (!accepted[i]) continue;
    kept.push_back(i);
    if (static_cast<int>(kept.size()) >= options_.max_fit_pixels) break;
  }
  fit.resize(kept.size());
  auto make_fit_pixels = [&](std::ptrdiff_t j) {
    fit[j] = MakeFitPixel(candidates[kept[j]]);
    fit[j].n0 = plane_normal[kept[j]].cast<double>();
  };
  if (pool_) {
    pool_->ParallelFor(0, static_cast<std::ptrdiff_t>(kept.size()), make_fit_pixels, 1024);
  } else {
    for (size_t j = 0; j < kept.size(); ++j) make_fit_pixels(static_cast<std::ptrdiff_t>(j));
  }
  return fit;
}

std::vector<FitPixel> FitPixelSelector::Select(std::mt19937& rng) {
  std::vector<Candidate> candidates = FindCandidates(Support());
  if (plane_priors_) return PlaneFitPixels(candidates, rng);
  std::vector<FitPixel> fit;
  if (static_cast<int>(candidates.size()) > options_.max_fit_pixels) {
    std::shuffle(candidates.begin(), candidates.end(), rng);
    candidates.resize(options_.max_fit_pixels);
  }
  for (const Candidate& cand : candidates) fit.push_back(MakeFitPixel(cand));
  return fit;
}

}  // namespace

void PrepareInputs(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                   const PhotometricOptions& options, ThreadPool* pool, PhotometricResult* result, ColourImage* image) {
  const int w = rgb.cols, h = rgb.rows;
  const bool plane_priors = options.prior_normals == PriorNormalSource::kPlaneFit;
  auto depth_chain = [&](ThreadPool* chain_pool) {
    result->dense_inverse_depth = DensifyInverseDepth(prior, options.densify);
    // Dense prior normals: the fitting input in kDenseDepth mode; otherwise only an optional
    // output. When they are computed, the dense prior used from here on (fit pixels' depth, the
    // per-pixel S(p), the returned map) is the smoothed one they are differentiated from. Earlier
    // versions did this through an aliasing side effect of PriorNormals; the results (depth scale,
    // accuracy, fusion) were measured with it, so it is kept, now on purpose.
    if (!plane_priors || options.output_prior_normals)
      result->prior_normals = PriorNormals(result->dense_inverse_depth, rig.camera, options.prior, chain_pool,
                                           &result->dense_inverse_depth);
  };
  auto colour_chain = [&]() {
    rgb.convertTo(image->color, CV_32FC3, 1.0 / 255.0);
    if (options.image_smoothing_sigma_px > 0) {
      const int ksize = static_cast<int>(std::ceil(3 * options.image_smoothing_sigma_px)) * 2 + 1;
      cv::GaussianBlur(image->color, image->color, cv::Size(ksize, ksize), options.image_smoothing_sigma_px);
    }
    if (options.superpixel_size_px > 0) {
      // SLIC runs on an image downsampled by superpixel_downsample (~2 ms at 256x256); labels are
      // upsampled by nearest neighbour.
      const int f = options.superpixel_downsample;
      cv::Mat small = rgb;
      if (f > 1) cv::resize(rgb, small, cv::Size((w + f - 1) / f, (h + f - 1) / f), 0, 0, cv::INTER_AREA);
      cv::Mat lab;
      cv::cvtColor(small, lab, cv::COLOR_RGB2Lab);
      image->num_sp = SlicSuperpixels(lab, std::max(2, options.superpixel_size_px / f), 5, &image->sp_labels);
      if (f > 1) cv::resize(image->sp_labels, image->sp_labels, cv::Size(w, h), 0, 0, cv::INTER_NEAREST);
    }
  };
  if (pool && pool->num_threads() > 1) {
    pool->ParallelFor(
        0, 2, [&](std::ptrdiff_t chain) { chain == 0 ? depth_chain(nullptr) : colour_chain(); }, 1);
  } else {
    depth_chain(pool);
    colour_chain();
  }
}

std::vector<FitPixel> SelectFitPixels(const cv::Mat& rgb, const InverseDepthMap& prior, const RigCalibration& rig,
                                      const PhotometricOptions& options, const Eigen::Matrix3d& demix,
                                      const ColourImage& image, const PhotometricResult& result, ThreadPool* pool,
                                      std::mt19937& rng) {
  return FitPixelSelector(rgb, prior, rig, options, demix, image, result, pool).Select(rng);
}

}  // namespace internal
}  // namespace prism
