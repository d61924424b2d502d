// EstimateNormals' model fit: chromaticity clusters of the fit pixels (k-means with BIC model
// selection, over superpixels), their merging along weak albedo edges, the depth scale search and
// the per-cluster models (ClusterModelFit in photometric_internal.h).
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include <Eigen/Dense>
#include <opencv2/core.hpp>

#include "core/photometric/photometric_internal.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {
namespace {

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

// The fit pixels are processed in fixed chunks (on the pool when given) whose sums are added in
// chunk order: the result does not depend on the number of threads.
constexpr size_t kFitChunk = 1024;

constexpr double kCauchyScale = 0.2;  // sine of the angle at which a prior normal counts half

}  // namespace

ClusterModelFit::ClusterModelFit(const cv::Mat& rgb, const ColourImage& image, const RigCalibration& rig,
                                 const PhotometricOptions& options, ThreadPool* pool, std::vector<FitPixel>* fit)
    : rgb_(rgb),
      image_(image),
      rig_(rig),
      options_(options),
      pool_(pool),
      fit_(*fit),
      calibrated_(options.mode == PhotometricMode::kCalibrated),
      w_(rgb.cols),
      h_(rgb.rows) {
  models_.scale = options.depth_scale;
}

// Chromaticity of a fit pixel (normal-independent albedo direction).
bool ClusterModelFit::ChromaOf(const FitPixel& p, Eigen::Vector2d* out) const {
  Eigen::Vector3d r;
  if (calibrated_) {
    r = AlbedoEstimate(rig_, p, models_.scale);
  } else {
    const Eigen::Vector3d pred = models_.global_m * p.n0;
    for (int l = 0; l < 3; ++l) r[l] = pred[l] > 1e-4 ? p.q[l] / pred[l] : std::nan("");
  }
  if (!r.allFinite() || r.minCoeff() <= 0) return false;
  *out = Chromaticity(r);
  return true;
}

size_t ClusterModelFit::ForChunks(size_t n, const std::function<void(size_t, size_t, size_t)>& fn) const {
  const size_t chunks = (n + kFitChunk - 1) / kFitChunk;
  auto run = [&](std::ptrdiff_t c) {
    const size_t begin = static_cast<size_t>(c) * kFitChunk;
    fn(static_cast<size_t>(c), begin, std::min(n, begin + kFitChunk));
  };
  if (pool_ && chunks > 1) {
    pool_->ParallelFor(0, static_cast<std::ptrdiff_t>(chunks), run, 1);
  } else {
    for (size_t c = 0; c < chunks; ++c) run(static_cast<std::ptrdiff_t>(c));
  }
  return chunks;
}

// Chromaticity centres, and the cluster of each superpixel (empty without superpixels).
std::pair<std::vector<Eigen::Vector2d>, std::vector<int>> ClusterModelFit::Cluster(double min_sigma) {
  const std::vector<FitPixel>& fit = fit_;
  const int num_sp = image_.num_sp;
  std::vector<Eigen::Vector2d> samples;
  std::vector<float> weights;
  std::vector<Eigen::Vector2d> pixel_chroma(fit.size());
  std::vector<uint8_t> has(fit.size(), 0);
  ForChunks(fit.size(), [&](size_t, size_t begin, size_t end) {
    for (size_t i = begin; i < end; ++i) has[i] = ChromaOf(fit[i], &pixel_chroma[i]);
  });
  if (num_sp > 0) {
    std::vector<Eigen::Vector2d> sum(num_sp, Eigen::Vector2d::Zero());
    std::vector<int> count(num_sp, 0);
    for (size_t i = 0; i < fit.size(); ++i) {
      if (!has[i]) continue;
      const int s = image_.sp_labels.at<int>(fit[i].y, fit[i].x);
      sum[s] += pixel_chroma[i];
      count[s]++;
    }
    for (int s = 0; s < num_sp; ++s)
      if (count[s] > 0) {
        samples.push_back(sum[s] / count[s]);
        weights.push_back(static_cast<float>(count[s]));
      }
    const auto centres = ClusterChromaticities(samples, weights, options_.max_clusters, min_sigma, options_.seed);
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
  return std::make_pair(ClusterChromaticities(samples, weights, options_.max_clusters, min_sigma, options_.seed),
                        std::vector<int>());
}

void ClusterModelFit::LabelFitPixels() {
  for (FitPixel& p : fit_) {
    if (image_.num_sp > 0) {
      p.label = models_.sp_cluster[image_.sp_labels.at<int>(p.y, p.x)];
    } else {
      Eigen::Vector2d ch;
      p.label = ChromaOf(p, &ch) ? Nearest(models_.centres, ch) : -1;
    }
  }
}

void ClusterModelFit::ClusterAndMerge() {
  auto clustered = Cluster(options_.min_chromaticity_sigma);
  models_.centres = clustered.first;
  models_.sp_cluster = clustered.second;
  LabelFitPixels();
  MergeByEdges();
}

// Calibrated fit of each cluster's relative albedo. Only the albedo's chromaticity matters for the
// normal's direction (n = normalize(S^-1 diag(1/rho) q)), so brightness variation inside a
// cluster (texture) is harmless. With u = 1/rho, the photometric normal A_i u (A_i = S_i^-1
// diag(q_i)) should be parallel to the prior normal n0_i: (I - n0 n0^T) A_i u = 0 is linear in u,
// and u is the smallest eigenvector of sum_i w_i A_i^T (I - n0 n0^T) A_i (IRLS with Cauchy weights
// on the angle). This uses the noisy prior normals only through an average over many pixels.
// Uses the first `num_pixels` fit pixels (they are shuffled) and `iterations` IRLS rounds.
double ClusterModelFit::FitDirections(double s, size_t num_pixels, int iterations) {
  const std::vector<FitPixel>& fit = fit_;
  std::vector<Eigen::Vector3d>& inverse_albedo = models_.inverse_albedo;
  const int k = static_cast<int>(models_.centres.size());
  const size_t n_fit = std::min(num_pixels, fit.size());
  a_.resize(fit.size());
  apa_.resize(fit.size());
  usable_.assign(fit.size(), 0);
  ForChunks(n_fit, [&](size_t, size_t begin, size_t end) {
    for (size_t i = begin; i < end; ++i) {
      const Eigen::Matrix3d sm = NearLightMatrix(rig_, fit[i].ray * (s / fit[i].inverse_depth));
      const double det = sm.determinant();
      if (!(std::abs(det) > 1e-12)) continue;
      a_[i] = sm.inverse() * fit[i].q.asDiagonal();  // closed-form 3x3 inverse
      usable_[i] = a_[i].allFinite();
      // A^T (I - n0 n0^T) A is fixed across the IRLS rounds: only the weights change.
      const Eigen::Vector3d an0 = a_[i].transpose() * fit[i].n0;
      apa_[i] = a_[i].transpose() * a_[i] - an0 * an0.transpose();
    }
  });
  inverse_albedo.assign(k + 1, Eigen::Vector3d::Ones());
  double cost = 0;
  double weight_sum = 0;
  for (int iter = 0; iter < iterations; ++iter) {
    // Only the last round's cost is returned.
    const bool want_cost = iter + 1 == iterations;
    chunk_sums_.resize((n_fit + kFitChunk - 1) / kFitChunk);
    const size_t chunks = ForChunks(n_fit, [&](size_t chunk, size_t begin, size_t end) {
      ChunkSums& sums = chunk_sums_[chunk];
      sums.h.assign(k + 1, Eigen::Matrix3d::Zero());
      sums.counts.assign(k + 1, 0);
      sums.cost = sums.weight_sum = 0;
      for (size_t i = begin; i < end; ++i) {
        if (!usable_[i]) continue;
        for (int m : {fit[i].label, k}) {
          if (m < 0) continue;
          const Eigen::Vector3d n = a_[i] * inverse_albedo[m];
          const double len2 = n.squaredNorm();
          if (len2 < 1e-18) continue;
          // sin^2 of the angle to n0: |(I - n0 n0^T) n|^2 / |n|^2 = 1 - (n0 . n)^2 / |n|^2.
          const double c = fit[i].n0.dot(n);
          const double r2 = std::max(0.0, 1.0 - c * c / len2) / (kCauchyScale * kCauchyScale);
          const double w = 1.0 / (1.0 + r2);
          sums.h[m] += (w / len2) * apa_[i];
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
        h[m] += chunk_sums_[c].h[m];
        counts[m] += chunk_sums_[c].counts[m];
      }
      cost += chunk_sums_[c].cost;
      weight_sum += chunk_sums_[c].weight_sum;
    }
    for (int m = k; m >= 0; --m) {
      const bool own = counts[m] >= options_.min_cluster_pixels || m == k;
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
}

// The scale search runs on a subsample with fewer IRLS rounds; the final fit uses every fit pixel.
double ClusterModelFit::ScaleCost(double s) { return FitDirections(s, options_.scale_search_pixels, 4); }

// Log-grid search, then golden-section refinement; re-cluster once at the found scale and
// search again. Where the shading constrains the scale poorly the cost is flat and a single
// keyframe's estimate can be far off: sessions should use SessionDepthScale.
void ClusterModelFit::SearchDepthScale() {
  const PhotometricOptions& options = options_;
  for (int pass = 0; pass < 2; ++pass) {
    const double lo = std::log(options.depth_scale / options.depth_scale_search_factor);
    const double hi = std::log(options.depth_scale * options.depth_scale_search_factor);
    const int steps = 16;
    std::vector<double> grid_cost(steps + 1);
    for (int i = 0; i <= steps; ++i) grid_cost[i] = ScaleCost(std::exp(lo + (hi - lo) * i / steps));
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
    double f1 = ScaleCost(std::exp(x1)), f2 = ScaleCost(std::exp(x2));
    for (int i = 0; i < 12; ++i) {
      if (f1 < f2) {
        b = x2;
        x2 = x1;
        f2 = f1;
        x1 = b - g * (b - a);
        f1 = ScaleCost(std::exp(x1));
      } else {
        a = x1;
        x1 = x2;
        f1 = f2;
        x2 = a + g * (b - a);
        f2 = ScaleCost(std::exp(x2));
      }
    }
    models_.scale = std::exp(0.5 * (a + b));
    if (pass == 0) ClusterAndMerge();
  }
}

// Reassigns each superpixel to the cluster whose albedo explains its prior normals best: the
// chromaticity clusters come from noisy per-pixel estimates and can mix similar colours (an
// off-white object on a beige floor); the model fit separates them.
void ClusterModelFit::ReassignSuperpixels() {
  const std::vector<FitPixel>& fit = fit_;
  const int num_sp = image_.num_sp;
  const int k = static_cast<int>(models_.centres.size());
  if (num_sp == 0 || k < 2) return;
  std::vector<double> cost(static_cast<size_t>(num_sp) * k, 0.0);
  std::vector<int> count(num_sp, 0);
  for (size_t i = 0; i < fit.size(); ++i) {
    if (!usable_[i]) continue;
    const int sp = image_.sp_labels.at<int>(fit[i].y, fit[i].x);
    count[sp]++;
    const Eigen::Matrix3d proj = Eigen::Matrix3d::Identity() - fit[i].n0 * fit[i].n0.transpose();
    for (int m = 0; m < k; ++m) {
      const Eigen::Vector3d n = a_[i] * models_.inverse_albedo[m];
      const double len = n.norm();
      const double r = len > 1e-9 ? (proj * n).norm() / len : 1.0;
      cost[static_cast<size_t>(sp) * k + m] += std::log1p((r / kCauchyScale) * (r / kCauchyScale));
    }
  }
  for (int sp = 0; sp < num_sp; ++sp) {
    if (count[sp] == 0) continue;
    const double* c = &cost[static_cast<size_t>(sp) * k];
    models_.sp_cluster[sp] = static_cast<int>(std::min_element(c, c + k) - c);
  }
  LabelFitPixels();
}

// Chromaticity edges validate cluster splits: albedo boundaries are sharp steps of the image
// chromaticity, while the errors of the prior normals (which can also split a cluster) vary
// smoothly. Two clusters whose shared superpixel boundaries show no step are merged.
// Only needed on the boundaries between clusters: computed there, from the smoothed colour.
cv::Vec2f ClusterModelFit::ChromaAt(int x, int y) const {
  const cv::Vec3f c = image_.color.at<cv::Vec3f>(y, x);
  const float sum = std::max(1e-4f, c[0] + c[1] + c[2]);
  return cv::Vec2f(c[0] / sum, c[1] / sum);
}

float ClusterModelFit::ChromaGradientAt(int x, int y) const {
  if (x <= 0 || y <= 0 || x >= w_ - 1 || y >= h_ - 1) return 0.f;
  const cv::Vec2f dx = 0.5f * (ChromaAt(x + 1, y) - ChromaAt(x - 1, y));
  const cv::Vec2f dy = 0.5f * (ChromaAt(x, y + 1) - ChromaAt(x, y - 1));
  return std::sqrt(dx.dot(dx) + dy.dot(dy));
}

void ClusterModelFit::MergeByEdges() {
  const int w = w_, h = h_;
  const int num_sp = image_.num_sp;
  std::vector<Eigen::Vector2d>& centres = models_.centres;
  std::vector<int>& sp_cluster = models_.sp_cluster;
  const int k = static_cast<int>(centres.size());
  if (num_sp == 0 || k < 2) return;
  // Per cluster pair: gradient samples on boundaries between their superpixels (dark pixels,
  // whose chromaticity is noise, are skipped).
  std::vector<std::vector<float>> steps(static_cast<size_t>(k) * k);
  for (int y = 1; y < h - 1; ++y) {
    const int* sp_row = image_.sp_labels.ptr<int>(y);
    const int* sp_down = image_.sp_labels.ptr<int>(y + 1);
    const cv::Vec3b* c = rgb_.ptr<cv::Vec3b>(y);
    for (int x = 1; x < w - 1; ++x) {
      const int ca = sp_cluster[sp_row[x]];
      if (ca < 0) continue;
      // Only where a neighbour (right, below) is in another cluster.
      const int cr = sp_cluster[sp_row[x + 1]], cd = sp_cluster[sp_down[x]];
      if ((cr < 0 || cr == ca) && (cd < 0 || cd == ca)) continue;
      if (std::max({c[x][0], c[x][1], c[x][2]}) < options_.min_level) continue;
      const float g = ChromaGradientAt(x, y);
      if (cr >= 0 && cr != ca)
        steps[static_cast<size_t>(std::min(ca, cr)) * k + std::max(ca, cr)].push_back(
            std::max(g, ChromaGradientAt(x + 1, y)));
      if (cd >= 0 && cd != ca)
        steps[static_cast<size_t>(std::min(ca, cd)) * k + std::max(ca, cd)].push_back(
            std::max(g, ChromaGradientAt(x, y + 1)));
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
      const bool similar = (centres[a] - centres[b]).norm() < options_.max_merge_chromaticity_distance;
      if (similar && v[v.size() / 2] < options_.min_albedo_edge) parent[find(a)] = find(b);
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
  LabelFitPixels();
}

// Per-cluster models.
void ClusterModelFit::FitClusterModels(PhotometricResult* result) {
  const int k = static_cast<int>(models_.centres.size());
  const Eigen::Matrix3d& global_m = models_.global_m;
  std::vector<Eigen::Matrix3d>& m_inv = models_.m_inv;
  m_inv.assign(k + 1, Eigen::Matrix3d::Identity());
  if (calibrated_) {
    FitDirections(models_.scale, fit_.size(), 6);
    for (int round = 0; round < options_.reassignment_rounds; ++round) {
      ReassignSuperpixels();
      FitDirections(models_.scale, fit_.size(), 6);
    }
    for (int c = 0; c < k; ++c) {
      const Eigen::Vector3d rho = models_.inverse_albedo[c].cwiseInverse();
      result->cluster_albedo.push_back(rho / rho.sum());
    }
  } else {
    std::vector<std::vector<Eigen::Vector3d>> cs(k), ns(k);
    for (const FitPixel& p : fit_)
      if (p.label >= 0) {
        cs[p.label].push_back(p.q);
        ns[p.label].push_back(p.n0);
      }
    result->cluster_lighting.assign(k, global_m);
    for (int c = 0; c < k; ++c) {
      Eigen::Matrix3d m;
      bool ok = static_cast<int>(cs[c].size()) >= options_.min_cluster_pixels;
      if (ok) {
        Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
        for (const auto& n : ns[c]) scatter += n * n.transpose();
        scatter /= static_cast<double>(ns[c].size());
        ok = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvalues().minCoeff() * 3 >=
             options_.min_normal_spread;
      }
      if (ok && FitLightingMatrix(cs[c], ns[c], &m) && std::abs(m.determinant()) > 1e-12)
        result->cluster_lighting[c] = m;
      m_inv[c] = result->cluster_lighting[c].inverse();
    }
    m_inv[k] = global_m.inverse();
  }
}

StatusOr<ClusterModels> ClusterModelFit::Fit(PhotometricResult* result) {
  if (!calibrated_) {
    std::vector<Eigen::Vector3d> cs, ns;
    for (const FitPixel& p : fit_) {
      cs.push_back(p.q);
      ns.push_back(p.n0);
    }
    if (!FitLightingMatrix(cs, ns, &models_.global_m))
      return FailedPreconditionError("EstimateNormals: prior normals too uniform to fit the lighting");
  }
  ClusterAndMerge();
  if (calibrated_ && options_.estimate_depth_scale) SearchDepthScale();
  const int k = static_cast<int>(models_.centres.size());
  result->num_clusters = k;
  result->depth_scale = models_.scale;
  FitClusterModels(result);
  return models_;
}

}  // namespace internal
}  // namespace prism
