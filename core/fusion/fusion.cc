#include "core/fusion/fusion.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <sstream>

#include <Eigen/Cholesky>
#include <opencv2/imgproc.hpp>

#include "core/util/check.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace {

// Rows per block of the parallel loops (even: see the multigrid restriction). Blocks, not threads,
// own the partial sums of reductions, so results do not depend on the number of threads.
constexpr int kRowsPerBlock = 8;
// Largest weight of a SLAM sample relative to a median-variance one.
constexpr float kMaxRelativeInverseVariance = 10.f;
// A normal counts as present when its length is at least this (inputs are unit vectors or 0).
constexpr float kMinNormalLength = 0.5f;

// Runs fn(y_begin, y_end, block) over the row blocks of an image of `rows` rows, on up to
// `num_threads` threads of the pool (blocks handed out dynamically).
class RowBlocks {
 public:
  RowBlocks(int rows, int num_threads, ThreadPool* pool)
      : rows_(rows), blocks_((rows + kRowsPerBlock - 1) / kRowsPerBlock), pool_(pool) {
    threads_ =
        pool == nullptr ? 1 : (num_threads <= 0 ? pool->num_threads() : std::min(num_threads, pool->num_threads()));
    threads_ = std::max(1, std::min(threads_, blocks_));
  }
  int blocks() const { return blocks_; }

  template <typename Fn>
  void Run(const Fn& fn) const {
    if (threads_ == 1) {
      for (int b = 0; b < blocks_; ++b) fn(b * kRowsPerBlock, std::min(rows_, (b + 1) * kRowsPerBlock), b);
      return;
    }
    std::atomic<int> next{0};
    pool_->ParallelFor(0, threads_, [&](std::ptrdiff_t) {
      for (int b = next.fetch_add(1); b < blocks_; b = next.fetch_add(1))
        fn(b * kRowsPerBlock, std::min(rows_, (b + 1) * kRowsPerBlock), b);
    });
  }

 private:
  int rows_;
  int blocks_;
  int threads_ = 1;
  ThreadPool* pool_;
};

double Sum(const std::vector<double>& v) {
  double t = 0;
  for (double e : v) t += e;  // fixed order
  return t;
}

// sum a[i] * b[i] over [0, n): eight float lanes (vectorised without -ffast-math), summed in double.
double Dot(const float* a, const float* b, size_t n) {
  float acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  size_t i = 0;
  for (; i + 8 <= n; i += 8)
    for (int k = 0; k < 8; ++k) acc[k] += a[i + k] * b[i + k];
  double sum = 0;
  for (int k = 0; k < 8; ++k) sum += acc[k];
  for (; i < n; ++i) sum += static_cast<double>(a[i]) * b[i];
  return sum;
}

bool NormalPresent(const cv::Vec3f& n) {
  const float len2 = n.dot(n);
  return std::isfinite(len2) && len2 >= kMinNormalLength * kMinNormalLength;
}

Status CheckImage(const cv::Mat& m, const char* name, int type, const PinholeCamera& camera, bool may_be_empty) {
  if (m.empty()) {
    if (may_be_empty) return Status::Ok();
    return InvalidArgumentError(std::string("FusionInput.") + name + " is empty");
  }
  if (m.type() != type || m.cols != camera.width || m.rows != camera.height || m.dims != 2) {
    std::ostringstream e;
    e << "FusionInput." << name << ": " << m.cols << "x" << m.rows << " of type " << m.type() << "; expected "
      << camera.width << "x" << camera.height << " of type " << type;
    return InvalidArgumentError(e.str());
  }
  return Status::Ok();
}

// Per-pixel rays at z = 1 (x and y components) and their inverse lengths.
struct Rays {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::array<double, 5> distortion{};
  std::vector<float> x, y, inv_norm;

  void Update(const PinholeCamera& c) {
    if (c.width == width && c.height == height && c.fx == fx && c.fy == fy && c.cx == cx && c.cy == cy &&
        c.distortion == distortion)
      return;
    width = c.width;
    height = c.height;
    fx = c.fx;
    fy = c.fy;
    cx = c.cx;
    cy = c.cy;
    distortion = c.distortion;
    const size_t n = static_cast<size_t>(width) * height;
    x.resize(n);
    y.resize(n);
    inv_norm.resize(n);
    for (int v = 0; v < height; ++v)
      for (int u = 0; u < width; ++u) {
        const size_t i = static_cast<size_t>(v) * width + u;
        const Eigen::Vector3d r = c.Unproject(Eigen::Vector2d(u, v));
        x[i] = static_cast<float>(r.x());
        y[i] = static_cast<float>(r.y());
        inv_norm[i] = static_cast<float>(1.0 / r.norm());
      }
  }
};

// ---------------------------------------------------------------------------------------------------
// Stencil assembly.

// Per-pixel and per-pair buffers of the assembly, kept between calls.
struct StencilScratch {
  std::vector<float> rel_var, inv_zp, conf, cos_slant, sin_slant;
  std::vector<cv::Vec3f> unit;
  std::vector<float> ar, br, ad, bd;  // pair rows: a * Z_i + b * Z_j (right and down neighbour)
  std::vector<int> parent, region_size;
  std::vector<uint8_t> supported;
  std::vector<int> block_a, block_b;
};

struct StencilCounts {
  int unknowns = 0;
  int samples = 0;
  int tangent_rows = 0;
  int dropped = 0;
};

// Builds the stencil of one pass into *s. previous / previous_depth (may be null): the stencil and
// solution of the previous pass.
void BuildStencil(const FusionInput& input, const cv::Mat& normals, const cv::Mat& prior_depth, const Rays& rays,
                  const FusionOptions& options, const RowBlocks& blocks, const internal::FusionStencil* previous,
                  const std::vector<float>* previous_depth, StencilScratch* scratch, internal::FusionStencil* s,
                  StencilCounts* counts) {
  const int w = input.camera.width, h = input.camera.height;
  const size_t n = static_cast<size_t>(w) * h;
  PRISM_CHECK(normals.type() == CV_32FC3 && normals.cols == w && normals.rows == h);
  PRISM_CHECK(prior_depth.type() == CV_32F && prior_depth.cols == w && prior_depth.rows == h);
  PRISM_CHECK(rays.width == w && rays.height == h);
  PRISM_CHECK(previous_depth == nullptr || previous_depth->size() == n);
  PRISM_CHECK(previous == nullptr || previous->diag.size() == n);
  s->width = w;
  s->height = h;
  s->diag.assign(n, 1.f);
  s->right.assign(n, 0.f);
  s->down.assign(n, 0.f);
  s->rhs.assign(n, 0.f);
  s->unknown.assign(n, 0);
  StencilScratch& t = *scratch;
  t.rel_var.assign(n, 0.f);
  t.inv_zp.assign(n, 0.f);
  t.conf.assign(n, 0.f);
  t.cos_slant.assign(n, 0.f);
  t.sin_slant.assign(n, 0.f);
  t.unit.assign(n, cv::Vec3f(0, 0, 0));
  t.ar.assign(n, 0.f);
  t.br.assign(n, 0.f);
  t.ad.assign(n, 0.f);
  t.bd.assign(n, 0.f);
  t.block_a.assign(blocks.blocks(), 0);
  t.block_b.assign(blocks.blocks(), 0);
  const bool has_confidence = !input.confidence.empty();
  const bool has_mask = !input.valid_mask.empty();
  const cv::Mat& sd = input.semi_dense.inverse_depth;
  const cv::Mat& sd_var = input.semi_dense.variance;

  // Per pixel: unknown or not, SLAM sample (relative variance var_rho / rho^2), unit normal
  // (confidence 0 = none), cosine and sine of its slant against the pixel's ray.
  blocks.Run([&](int y0, int y1, int block) {
    for (int y = y0; y < y1; ++y) {
      const float* zp = prior_depth.ptr<float>(y);
      const float* rho = sd.ptr<float>(y);
      const float* var = sd_var.ptr<float>(y);
      const cv::Vec3f* nr = normals.ptr<cv::Vec3f>(y);
      const uint8_t* mask = has_mask ? input.valid_mask.ptr<uint8_t>(y) : nullptr;
      const float* cf = has_confidence ? input.confidence.ptr<float>(y) : nullptr;
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        if (mask != nullptr && mask[x] == 0) continue;
        if (!(zp[x] > 0) || !std::isfinite(zp[x])) continue;
        const bool sample = rho[x] > 0 && std::isfinite(rho[x]) && var[x] > 0 && std::isfinite(var[x]);
        const bool has_normal = NormalPresent(nr[x]) && (cf == nullptr || cf[x] > 0);
        if (!sample && !has_normal) continue;
        s->unknown[i] = 1;
        ++t.block_a[block];
        t.inv_zp[i] = 1.f / zp[x];
        if (sample) {
          t.rel_var[i] = var[x] / (rho[x] * rho[x]);
          ++t.block_b[block];
        }
        if (has_normal) {
          const cv::Vec3f u = nr[x] / std::sqrt(nr[x].dot(nr[x]));
          t.unit[i] = u;
          t.conf[i] = cf == nullptr ? 1.f : std::min(1.f, cf[x]);
          const float c = -(u[0] * rays.x[i] + u[1] * rays.y[i] + u[2]) * rays.inv_norm[i];
          t.cos_slant[i] = c;
          t.sin_slant[i] = std::sqrt(std::max(0.f, 1.f - c * c));
        }
      }
    }
  });
  int unknowns = 0, samples = 0;
  for (int u : t.block_a) unknowns += u;
  for (int u : t.block_b) samples += u;
  float median_var = 1.f;
  if (samples > 0) {
    std::vector<float> v;
    v.reserve(samples);
    for (size_t i = 0; i < n; ++i)
      if (t.rel_var[i] > 0) v.push_back(t.rel_var[i]);
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    median_var = v[v.size() / 2];
  }
  const double density = unknowns > 0 ? static_cast<double>(samples) / unknowns : 1.0;
  // Passes that solve with corrected normals get the positions' low frequencies through them too.
  const double pass_scale =
      previous != nullptr && options.normal_correction ? options.corrected_pass_position_scale : 1.0;
  const float position_weight = static_cast<float>(pass_scale * options.position_weight / std::max(density, 1e-6));
  const float prior_weight = static_cast<float>(options.prior_weight);
  // Test (a): |log(A) - log(B)| > max_depth_jump <=> A / B outside [1 / e^t, e^t].
  const float max_ratio = static_cast<float>(std::exp(options.max_depth_jump));
  const float min_ratio = 1.f / max_ratio;
  const float cos_crease = static_cast<float>(std::cos(options.max_normal_angle_deg * M_PI / 180.0));
  const float cos_contour = static_cast<float>(std::cos(options.contour_slant_deg * M_PI / 180.0));
  const float cos_drop = static_cast<float>(std::cos(options.contour_slant_drop_deg * M_PI / 180.0));
  const float sin_drop = static_cast<float>(std::sin(options.contour_slant_drop_deg * M_PI / 180.0));
  const float cos_max_slant = static_cast<float>(std::cos(options.max_slant_deg * M_PI / 180.0));
  const float* prev_depth = previous_depth != nullptr && previous != nullptr ? previous_depth->data() : nullptr;

  // Pair rows, pre-multiplied by sqrt(weight).
  t.block_a.assign(blocks.blocks(), 0);
  blocks.Run([&](int y0, int y1, int block) {
    for (int y = y0; y < y1; ++y) {
      const float* rho_row = sd.ptr<float>(y);
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        if (!s->unknown[i]) continue;
        for (int dir = 0; dir < 2; ++dir) {
          if (dir == 0 ? x + 1 >= w : y + 1 >= h) continue;
          const size_t j = dir == 0 ? i + 1 : i + w;
          if (!s->unknown[j]) continue;
          if (previous != nullptr && (dir == 0 ? previous->right[i] : previous->down[i]) == 0.f) continue;
          const cv::Vec3f& ni = t.unit[i];
          const cv::Vec3f& nj = t.unit[j];
          const bool pi = t.conf[i] > 0, pj = t.conf[j] > 0;
          if (!pi && !pj) continue;
          bool cut = false;
          if (pi && pj) {
            // (b) crease.
            if (ni.dot(nj) < cos_crease) cut = true;
            // (c) occluding contour: slant_j < slant_i - drop <=> cos slant_j > cos(slant_i - drop).
            // The image direction from i to j is +x (dir 0) or +y (dir 1); a normal points towards
            // the other pixel when its image-plane component along that direction has that sign.
            const float ci = t.cos_slant[i], cj = t.cos_slant[j];
            if (ci < cos_contour && ni[dir] > 0 && cj > ci * cos_drop + t.sin_slant[i] * sin_drop) cut = true;
            if (cj < cos_contour && nj[dir] < 0 && ci > cj * cos_drop + t.sin_slant[j] * sin_drop) cut = true;
          }
          cv::Vec3f nm = ni + nj;  // a missing normal is 0
          const float len = std::sqrt(nm.dot(nm));
          if (cut || !(len > 1e-6f)) {
            ++t.block_a[block];
            continue;
          }
          nm /= len;
          const float di = nm[0] * rays.x[i] + nm[1] * rays.y[i] + nm[2];
          const float dj = nm[0] * rays.x[j] + nm[1] * rays.y[j] + nm[2];
          // (d) too grazing (also a normal facing away): cos(slant) = -n . r / |r|.
          const float cos_i = -di * rays.inv_norm[i];
          const float cos_j = -dj * rays.inv_norm[j];
          if (!(cos_i > cos_max_slant && cos_j > cos_max_slant)) cut = true;
          // (a) The depth step against the step the normal predicts, Z_j / Z_i = di / dj: of the SLAM
          // depth (Z = 1 / rho) and of the previous pass's solution.
          const float predicted = di / dj;
          if (!cut && t.rel_var[i] > 0 && t.rel_var[j] > 0) {
            const float rho_j = dir == 0 ? rho_row[x + 1] : sd.ptr<float>(y + 1)[x];
            const float ratio = rho_row[x] / rho_j / predicted;
            if (!(ratio < max_ratio && ratio > min_ratio)) cut = true;
          }
          if (!cut && prev_depth != nullptr && prev_depth[i] > 0 && prev_depth[j] > 0) {
            const float ratio = prev_depth[j] / prev_depth[i] / predicted;
            if (!(ratio < max_ratio && ratio > min_ratio)) cut = true;
          }
          if (cut) {
            ++t.block_a[block];
            continue;
          }
          const float c = (pi && pj) ? 0.5f * (t.conf[i] + t.conf[j]) : (pi ? t.conf[i] : t.conf[j]);
          // Relative residual (divided by the pair's prior depth), times the cosine of the slant.
          const float scale = std::sqrt(c) * 0.5f * (t.inv_zp[i] + t.inv_zp[j]) * cos_i;
          (dir == 0 ? t.ar : t.ad)[i] = -scale * di;
          (dir == 0 ? t.br : t.bd)[i] = scale * dj;
        }
      }
    }
  });
  counts->dropped = 0;
  for (int d : t.block_a) counts->dropped += d;

  // Connected regions over the rows kept (union-find). Regions without SLAM depth are singular but
  // for the prior tie: small ones (slivers along depth edges, where the blurred prior is wrong) are
  // dropped; large ones follow the prior at low frequencies.
  t.parent.resize(n);
  for (size_t i = 0; i < n; ++i) t.parent[i] = static_cast<int>(i);
  auto find = [&](int a) {
    while (t.parent[a] != a) a = t.parent[a] = t.parent[t.parent[a]];
    return a;
  };
  auto unite = [&](int a, int b) {
    a = find(a);
    b = find(b);
    if (a != b) t.parent[std::max(a, b)] = std::min(a, b);
  };
  for (size_t i = 0; i < n; ++i) {
    if (t.ar[i] != 0.f) unite(static_cast<int>(i), static_cast<int>(i + 1));
    if (t.ad[i] != 0.f) unite(static_cast<int>(i), static_cast<int>(i + w));
  }
  t.region_size.assign(n, 0);
  t.supported.assign(n, 0);
  for (size_t i = 0; i < n; ++i) {
    if (!s->unknown[i]) continue;
    const int root = find(static_cast<int>(i));
    ++t.region_size[root];
    if (t.rel_var[i] > 0) t.supported[root] = 1;
  }
  for (size_t i = 0; i < n; ++i) {
    if (!s->unknown[i]) continue;
    const int root = find(static_cast<int>(i));
    if (t.supported[root] || t.region_size[root] >= options.min_unsupported_region_px) continue;
    s->unknown[i] = 0;
    --unknowns;
    t.ar[i] = t.br[i] = t.ad[i] = t.bd[i] = 0.f;
  }

  // The normal equations, gathered per pixel.
  t.block_a.assign(blocks.blocks(), 0);
  blocks.Run([&](int y0, int y1, int block) {
    for (int y = y0; y < y1; ++y) {
      const float* rho = sd.ptr<float>(y);
      const float* zp = prior_depth.ptr<float>(y);
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        if (!s->unknown[i]) continue;
        float d = t.ar[i] * t.ar[i] + t.ad[i] * t.ad[i];
        if (x > 0) d += t.br[i - 1] * t.br[i - 1];
        if (y > 0) d += t.bd[i - w] * t.bd[i - w];
        const float inv_zp2 = t.inv_zp[i] * t.inv_zp[i];
        float b = 0.f;
        if (t.rel_var[i] > 0) {
          const float wp = position_weight * std::min(kMaxRelativeInverseVariance, median_var / t.rel_var[i]) * inv_zp2;
          d += wp;
          b += wp / rho[x];  // Zm = 1 / rho
        }
        d += prior_weight * inv_zp2;
        b += prior_weight * inv_zp2 * zp[x];
        s->diag[i] = d;
        s->rhs[i] = b;
        s->right[i] = t.ar[i] * t.br[i];
        s->down[i] = t.ad[i] * t.bd[i];
        t.block_a[block] += (t.ar[i] != 0.f) + (t.ad[i] != 0.f);
      }
    }
  });
  counts->tangent_rows = 0;
  for (int r : t.block_a) counts->tangent_rows += r;
  counts->unknowns = unknowns;
  counts->samples = samples;
}

// ---------------------------------------------------------------------------------------------------
// Solver.

// out = A v on rows [y0, y1) of a 5-point stencil (diag, right = A(i, i+1), down = A(i, i+w)).
void ApplyStencil(const float* diag, const float* right, const float* down, int w, int h, const float* v, float* out,
                  int y0, int y1) {
  for (int y = y0; y < y1; ++y) {
    const size_t row = static_cast<size_t>(y) * w;
    const float* vc = v + row;
    const float* dg = diag + row;
    const float* rt = right + row;
    const float* dn = down + row;
    float* o = out + row;
    for (int x = 0; x < w; ++x) o[x] = dg[x] * vc[x];
    for (int x = 0; x + 1 < w; ++x) o[x] += rt[x] * vc[x + 1];
    for (int x = 1; x < w; ++x) o[x] += rt[x - 1] * vc[x - 1];
    if (y + 1 < h)
      for (int x = 0; x < w; ++x) o[x] += dn[x] * vc[x + w];
    if (y > 0) {
      const float* up = dn - w;
      for (int x = 0; x < w; ++x) o[x] += up[x] * vc[x - w];
    }
  }
}

// One grid of the multigrid hierarchy.
struct GridLevel {
  int w = 0;
  int h = 0;
  std::vector<float> diag, right, down, inv_diag;
  std::vector<uint8_t> unknown;    // 0: an identity row (diag 1, no coupling)
  std::vector<float> x, b, r;      // solution, right-hand side, residual
  std::vector<float> row_scratch;  // kRowsPerBlock-row blocks x w, for the smoother
};

// Symmetric V-cycle preconditioner for the fusion stencil: Galerkin coarse grids of 2x2
// piecewise-constant aggregates (which keeps the 5-point structure and respects the cut pairs and
// holes exactly), red-black Gauss-Seidel (red-black before, black-red after the coarse correction)
// and a dense Cholesky solve on the coarsest grid: a fixed symmetric positive definite operator, so
// it can precondition conjugate gradients.
class MultigridPreconditioner {
 public:
  void Setup(const internal::FusionStencil& s, int num_threads, ThreadPool* pool) {
    num_threads_ = num_threads;
    pool_ = pool;
    levels_.resize(1);
    GridLevel& fine = levels_[0];
    fine.w = s.width;
    fine.h = s.height;
    fine.diag = s.diag;
    fine.right = s.right;
    fine.down = s.down;
    fine.unknown = s.unknown;
    size_t l = 0;
    while (std::max(levels_[l].w, levels_[l].h) > kCoarsestSize) {
      if (levels_.size() == l + 1) levels_.emplace_back();
      Coarsen(levels_[l], &levels_[l + 1]);
      ++l;
    }
    levels_.resize(l + 1);
    for (GridLevel& g : levels_) {
      const size_t n = static_cast<size_t>(g.w) * g.h;
      g.inv_diag.resize(n);
      for (size_t i = 0; i < n; ++i) g.inv_diag[i] = 1.f / g.diag[i];
      g.x.assign(n, 0.f);
      g.b.assign(n, 0.f);
      g.r.assign(n, 0.f);
      g.row_scratch.assign(static_cast<size_t>(RowBlocks(g.h, 1, nullptr).blocks()) * g.w, 0.f);
    }
    const GridLevel& c = levels_.back();
    const int n = c.w * c.h;
    Eigen::MatrixXd a = Eigen::MatrixXd::Zero(n, n);
    for (int i = 0; i < n; ++i) {
      a(i, i) = c.diag[i];
      if ((i % c.w) + 1 < c.w) a(i, i + 1) = a(i + 1, i) = c.right[i];
      if (i + c.w < n) a(i, i + c.w) = a(i + c.w, i) = c.down[i];
    }
    coarsest_.compute(a);
    PRISM_CHECK(coarsest_.info() == Eigen::Success) << "coarsest multigrid operator is not positive definite";
  }

  // z = M^-1 r; returns r . z (summed per row block in a fixed order). r is borrowed as the finest
  // right-hand side during the cycle (no copy) and handed back unchanged.
  double Apply(std::vector<float>* r, std::vector<float>* z) {
    GridLevel& f = levels_[0];
    f.b.swap(*r);
    Cycle(0);
    f.b.swap(*r);
    z->swap(f.x);
    f.x.resize(r->size());
    return Sum(dots_);
  }

 private:
  static constexpr int kCoarsestSize = 8;
  // Piecewise-constant aggregation makes the coarse Laplacian too stiff; a slightly scaled coarse
  // correction makes up for part of it (measured: 1.2 needs the fewest iterations on the presets).
  static constexpr float kCoarseCorrectionScale = 1.2f;
  // Grids smaller than this (pixels) run on the calling thread only: below it a parallel region
  // costs about as much as it saves, and it is more exposed to a busy second core.
  static constexpr int kMinParallelPixels = 384 * 384;

  RowBlocks Blocks(const GridLevel& g) const {
    return RowBlocks(g.h, g.w * g.h >= kMinParallelPixels ? num_threads_ : 1, pool_);
  }

  static void Coarsen(const GridLevel& f, GridLevel* c) {
    c->w = (f.w + 1) / 2;
    c->h = (f.h + 1) / 2;
    const size_t n = static_cast<size_t>(c->w) * c->h;
    c->diag.assign(n, 0.f);
    c->right.assign(n, 0.f);
    c->down.assign(n, 0.f);
    c->unknown.assign(n, 0);
    // Couplings are 0 unless both pixels are unknowns, so only the diagonal needs the mask.
    for (int y = 0; y < f.h; ++y)
      for (int x = 0; x < f.w; ++x) {
        const size_t i = static_cast<size_t>(y) * f.w + x;
        const size_t ci = static_cast<size_t>(y / 2) * c->w + x / 2;
        if (f.unknown[i]) {
          c->diag[ci] += f.diag[i];
          c->unknown[ci] = 1;
        }
        if (x + 1 < f.w) {
          if (x % 2 == 0) c->diag[ci] += 2 * f.right[i];  // pair inside the aggregate
          else c->right[ci] += f.right[i];
        }
        if (y + 1 < f.h) {
          if (y % 2 == 0) c->diag[ci] += 2 * f.down[i];
          else c->down[ci] += f.down[i];
        }
      }
    for (size_t ci = 0; ci < n; ++ci)
      if (!c->unknown[ci]) c->diag[ci] = 1.f;
  }

  // Gauss-Seidel on the pixels of one colour ((x + y) % 2 == colour) of rows [y0, y1): the update of
  // a whole row is computed (vectorised; a pixel's neighbours all have the other colour), then the
  // pixels of the colour are written. The first and last row of the range read only the other colour
  // of the rows beyond it: another thread is writing this colour there (a data race, found by TSan,
  // even though those values were discarded).
  static void SmoothRows(GridLevel& g, int colour, int y0, int y1, float* t) {
    const int w = g.w;
    for (int y = y0; y < y1; ++y) {
      const size_t row = static_cast<size_t>(y) * w;
      const float* rt = g.right.data() + row;
      const float* dn = g.down.data() + row;
      const float* id = g.inv_diag.data() + row;
      const float* bb = g.b.data() + row;
      float* xc = g.x.data() + row;
      if (y == y0 || y + 1 == y1) {  // same operations in the same order as below: the same result
        for (int x = (colour + y) & 1; x < w; x += 2) {
          float v = bb[x];
          if (x + 1 < w) v -= rt[x] * xc[x + 1];
          if (x > 0) v -= rt[x - 1] * xc[x - 1];
          if (y + 1 < g.h) v -= dn[x] * xc[x + w];
          if (y > 0) v -= dn[x - w] * xc[x - w];
          xc[x] = v * id[x];
        }
        continue;
      }
      for (int x = 0; x < w; ++x) t[x] = bb[x];
      for (int x = 0; x + 1 < w; ++x) t[x] -= rt[x] * xc[x + 1];
      for (int x = 1; x < w; ++x) t[x] -= rt[x - 1] * xc[x - 1];
      if (y + 1 < g.h) {
        const float* xd = xc + w;
        for (int x = 0; x < w; ++x) t[x] -= dn[x] * xd[x];
      }
      if (y > 0) {
        const float* up = dn - w;
        const float* xu = xc - w;
        for (int x = 0; x < w; ++x) t[x] -= up[x] * xu[x];
      }
      for (int x = (colour + y) & 1; x < w; x += 2) xc[x] = t[x] * id[x];
    }
  }

  void Smooth(GridLevel& g, int colour) {
    Blocks(g).Run([&](int y0, int y1, int block) {
      SmoothRows(g, colour, y0, y1, g.row_scratch.data() + static_cast<size_t>(block) * g.w);
    });
  }

  void Cycle(int l) {
    GridLevel& g = levels_[l];
    if (l + 1 == static_cast<int>(levels_.size())) {
      Eigen::VectorXd b(g.b.size());
      for (size_t i = 0; i < g.b.size(); ++i) b[i] = g.b[i];
      const Eigen::VectorXd x = coarsest_.solve(b);
      for (size_t i = 0; i < g.x.size(); ++i) g.x[i] = static_cast<float>(x[i]);
      return;
    }
    // Red sweep from x = 0 (its neighbours are all 0), then black.
    Blocks(g).Run([&](int y0, int y1, int) {
      for (int y = y0; y < y1; ++y) {
        const size_t row = static_cast<size_t>(y) * g.w;
        for (int x = 0; x < g.w; ++x) g.x[row + x] = ((x + y) & 1) ? 0.f : g.b[row + x] * g.inv_diag[row + x];
      }
    });
    Smooth(g, 1);
    // Residual, restricted (summed over each 2x2 aggregate) into the coarse right-hand side. Row
    // blocks have an even number of rows, so each coarse row is written by one block only.
    GridLevel& c = levels_[l + 1];
    std::fill(c.b.begin(), c.b.end(), 0.f);
    Blocks(g).Run([&](int y0, int y1, int) {
      ApplyStencil(g.diag.data(), g.right.data(), g.down.data(), g.w, g.h, g.x.data(), g.r.data(), y0, y1);
      for (int y = y0; y < y1; ++y) {
        const size_t row = static_cast<size_t>(y) * g.w;
        float* cb = c.b.data() + static_cast<size_t>(y / 2) * c.w;
        const float* bb = g.b.data() + row;
        float* rr = g.r.data() + row;
        for (int x = 0; x < g.w; ++x) rr[x] = bb[x] - rr[x];
        const int pairs = g.w / 2;
        for (int cx = 0; cx < pairs; ++cx) cb[cx] += rr[2 * cx] + rr[2 * cx + 1];
        if (g.w % 2) cb[pairs] += rr[g.w - 1];
      }
    });
    Cycle(l + 1);
    Blocks(g).Run([&](int y0, int y1, int) {
      for (int y = y0; y < y1; ++y) {
        float* xr = g.x.data() + static_cast<size_t>(y) * g.w;
        const float* cx = c.x.data() + static_cast<size_t>(y / 2) * c.w;
        const int pairs = g.w / 2;
        for (int k = 0; k < pairs; ++k) {
          const float v = kCoarseCorrectionScale * cx[k];
          xr[2 * k] += v;
          xr[2 * k + 1] += v;
        }
        if (g.w % 2) xr[g.w - 1] += kCoarseCorrectionScale * cx[pairs];
      }
    });
    Smooth(g, 1);
    if (l > 0) {
      Smooth(g, 0);
      return;
    }
    // The last sweep of the finest grid also forms r . z of its rows.
    const RowBlocks blocks = Blocks(g);
    dots_.assign(blocks.blocks(), 0.0);
    blocks.Run([&](int y0, int y1, int block) {
      SmoothRows(g, 0, y0, y1, g.row_scratch.data() + static_cast<size_t>(block) * g.w);
      const size_t begin = static_cast<size_t>(y0) * g.w, end = static_cast<size_t>(y1) * g.w;
      dots_[block] = Dot(g.b.data() + begin, g.x.data() + begin, end - begin);
    });
  }

  std::vector<double> dots_;
  int num_threads_ = 1;
  ThreadPool* pool_ = nullptr;
  std::vector<GridLevel> levels_;
  Eigen::LLT<Eigen::MatrixXd> coarsest_;
};

struct CgWorkspace {
  std::vector<float> r, z, p, q, inv_diag;
  std::vector<double> partial_a, partial_b;
  MultigridPreconditioner multigrid;
};

internal::CgSummary SolveCg(const internal::FusionStencil& s, int max_iterations, double tolerance,
                            FusionPreconditioner preconditioner, int num_threads, ThreadPool* pool, CgWorkspace* ws,
                            std::vector<float>* x_out) {
  const int w = s.width, h = s.height;
  const size_t n = static_cast<size_t>(w) * h;
  PRISM_CHECK_EQ(x_out->size(), n);
  std::vector<float>& x = *x_out;
  std::vector<float>&r = ws->r, &z = ws->z, &p = ws->p, &q = ws->q, &inv_diag = ws->inv_diag;
  r.resize(n);
  z.resize(n);
  p.resize(n);
  q.resize(n);
  inv_diag.resize(n);
  const RowBlocks blocks(h, num_threads, pool);
  ws->partial_a.assign(blocks.blocks(), 0.0);
  ws->partial_b.assign(blocks.blocks(), 0.0);
  std::vector<double>&partial_a = ws->partial_a, &partial_b = ws->partial_b;
  const bool multigrid = preconditioner == FusionPreconditioner::kMultigrid;
  if (multigrid) ws->multigrid.Setup(s, num_threads, pool);
  // z = M^-1 r; returns r . z.
  auto precondition = [&]() {
    if (multigrid) return ws->multigrid.Apply(&r, &z);
    blocks.Run([&](int y0, int y1, int block) {
      const size_t begin = static_cast<size_t>(y0) * w, end = static_cast<size_t>(y1) * w;
      for (size_t i = begin; i < end; ++i) z[i] = inv_diag[i] * r[i];
      partial_a[block] = Dot(r.data() + begin, z.data() + begin, end - begin);
    });
    return Sum(partial_a);
  };

  // r = b - A x.
  blocks.Run([&](int y0, int y1, int block) {
    ApplyStencil(s.diag.data(), s.right.data(), s.down.data(), w, h, x.data(), q.data(), y0, y1);
    double rr = 0, bb = 0;
    for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
      inv_diag[i] = 1.f / s.diag[i];
      r[i] = s.rhs[i] - q[i];
      rr += static_cast<double>(r[i]) * r[i];
      bb += static_cast<double>(s.rhs[i]) * s.rhs[i];
    }
    partial_a[block] = rr;
    partial_b[block] = bb;
  });
  const double b_norm = std::sqrt(Sum(partial_b));
  internal::CgSummary summary;
  if (b_norm == 0) {
    std::fill(x.begin(), x.end(), 0.f);
    summary.converged = true;
    return summary;
  }
  summary.relative_residual = std::sqrt(Sum(partial_a)) / b_norm;
  if (summary.relative_residual <= tolerance) {
    summary.converged = true;
    return summary;
  }
  double rz = precondition();
  p = z;
  for (int it = 0; it < max_iterations; ++it) {
    // q = A p, p . q
    blocks.Run([&](int y0, int y1, int block) {
      ApplyStencil(s.diag.data(), s.right.data(), s.down.data(), w, h, p.data(), q.data(), y0, y1);
      const size_t begin = static_cast<size_t>(y0) * w, end = static_cast<size_t>(y1) * w;
      partial_a[block] = Dot(p.data() + begin, q.data() + begin, end - begin);
    });
    const double pq = Sum(partial_a);
    if (!(pq > 0)) break;  // converged to machine precision
    const float alpha = static_cast<float>(rz / pq);
    // x += alpha p, r -= alpha q, r . r
    blocks.Run([&](int y0, int y1, int block) {
      const size_t begin = static_cast<size_t>(y0) * w, end = static_cast<size_t>(y1) * w;
      for (size_t i = begin; i < end; ++i) {
        x[i] += alpha * p[i];
        r[i] -= alpha * q[i];
      }
      partial_a[block] = Dot(r.data() + begin, r.data() + begin, end - begin);
    });
    summary.iterations = it + 1;
    summary.relative_residual = std::sqrt(Sum(partial_a)) / b_norm;
    if (summary.relative_residual <= tolerance) {
      summary.converged = true;
      break;
    }
    const double rz_new = precondition();
    const float beta = static_cast<float>(rz_new / rz);
    rz = rz_new;
    blocks.Run([&](int y0, int y1, int) {
      for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) p[i] = z[i] + beta * p[i];
    });
  }
  return summary;
}

// ---------------------------------------------------------------------------------------------------
// Normals.

// Normals of the surface Z r(u) into *out (CV_32FC3): central differences along the tangent rows that
// were used (one-sided where a neighbour is cut off), facing the camera; 0 where a direction has no
// neighbour or the depth is not positive.
void SurfaceNormals(const std::vector<float>& depth, const internal::FusionStencil& s, const Rays& rays,
                    const RowBlocks& blocks, cv::Mat* out) {
  const int w = s.width, h = s.height;
  out->create(h, w, CV_32FC3);
  auto point = [&](size_t i) { return cv::Vec3f(rays.x[i] * depth[i], rays.y[i] * depth[i], depth[i]); };
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      cv::Vec3f* o = out->ptr<cv::Vec3f>(y);
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        o[x] = cv::Vec3f(0, 0, 0);
        if (!s.unknown[i] || !(depth[i] > 0)) continue;
        const bool r = x + 1 < w && s.right[i] != 0.f;
        const bool l = x > 0 && s.right[i - 1] != 0.f;
        const bool d = y + 1 < h && s.down[i] != 0.f;
        const bool u = y > 0 && s.down[i - w] != 0.f;
        if (!(r || l) || !(d || u)) continue;
        const cv::Vec3f tx = point(r ? i + 1 : i) - point(l ? i - 1 : i);
        const cv::Vec3f ty = point(d ? i + w : i) - point(u ? i - w : i);
        cv::Vec3f nm = tx.cross(ty);
        const float len = std::sqrt(nm.dot(nm));
        if (!(len > 0)) continue;
        nm /= len;
        if (nm[0] * rays.x[i] + nm[1] * rays.y[i] + nm[2] > 0) nm = -nm;
        o[x] = nm;
      }
    }
  });
}

// Gaussian low-pass of a normal map's directions (not normalised). Large scales are filtered on a
// downsampled image.
cv::Mat GaussianLowPass(const cv::Mat& normals, double sigma_px) {
  const int factor = std::max(1, static_cast<int>(std::floor(sigma_px / 2.0)));
  cv::Mat small = normals;
  if (factor > 1)
    cv::resize(normals, small, cv::Size((normals.cols + factor - 1) / factor, (normals.rows + factor - 1) / factor), 0,
               0, cv::INTER_AREA);
  const double s = sigma_px / factor;
  const int k = 2 * static_cast<int>(std::ceil(3 * s)) + 1;
  cv::Mat blurred;
  cv::GaussianBlur(small, blurred, cv::Size(k, k), s, s, cv::BORDER_REPLICATE);
  if (factor == 1) return blurred;
  cv::Mat out;
  cv::resize(blurred, out, normals.size(), 0, 0, cv::INTER_LINEAR);
  return out;
}

// Edge-aware low-pass of two CV_32FC3 maps in place: the recursive filter of the domain transform
// (Gastal & Oliveira 2011), iterations of a horizontal and a vertical first-order recursive
// (exponential) filter of scale sigma_px that does not propagate across pairs without a tangent row
// (depth discontinuities, creases, holes). `factors` is scratch.
void EdgeAwareLowPass(const internal::FusionStencil& links, double sigma_px, const RowBlocks& blocks,
                      std::vector<float>* factors, cv::Mat* a, cv::Mat* b) {
  const int w = links.width, h = links.height;
  const size_t n = static_cast<size_t>(w) * h;
  // Two iterations: the third of the domain transform changed the corrected normals by < 0.05 deg.
  constexpr int kIterations = 2;
  std::vector<float>& fr = *factors;  // feedback to the right neighbour, then 3 per pixel downwards
  fr.resize(4 * n);
  float* fd = fr.data() + n;
  for (int k = 0; k < kIterations; ++k) {
    const double sigma_k =
        sigma_px * std::sqrt(3.0) * std::pow(2.0, kIterations - 1 - k) / std::sqrt(std::pow(4.0, kIterations) - 1);
    const float f = static_cast<float>(std::exp(-std::sqrt(2.0) / sigma_k));
    blocks.Run([&](int y0, int y1, int) {
      for (size_t i = static_cast<size_t>(y0) * w; i < static_cast<size_t>(y1) * w; ++i) {
        fr[i] = links.right[i] != 0.f ? f : 0.f;
        const float d = links.down[i] != 0.f ? f : 0.f;
        fd[3 * i] = fd[3 * i + 1] = fd[3 * i + 2] = d;
      }
      for (cv::Mat* m : {a, b})
        for (int y = y0; y < y1; ++y) {
          cv::Vec3f* v = m->ptr<cv::Vec3f>(y);
          const float* rt = fr.data() + static_cast<size_t>(y) * w;
          for (int x = 1; x < w; ++x) v[x] += rt[x - 1] * (v[x - 1] - v[x]);
          for (int x = w - 2; x >= 0; --x) v[x] += rt[x] * (v[x + 1] - v[x]);
        }
    });
    // Vertical, a row at a time (sequential in y, vectorised in x).
    for (cv::Mat* m : {a, b}) {
      for (int y = 1; y < h; ++y) {
        float* v = m->ptr<float>(y);
        const float* u = m->ptr<float>(y - 1);
        const float* dn = fd + 3 * static_cast<size_t>(y - 1) * w;
        for (int x = 0; x < 3 * w; ++x) v[x] += dn[x] * (u[x] - v[x]);
      }
      for (int y = h - 2; y >= 0; --y) {
        float* v = m->ptr<float>(y);
        const float* d = m->ptr<float>(y + 1);
        const float* dn = fd + 3 * static_cast<size_t>(y) * w;
        for (int x = 0; x < 3 * w; ++x) v[x] += dn[x] * (d[x] - v[x]);
      }
    }
  }
}

// Rotates `n` by the rotation taking unit vector a to unit vector b (Rodrigues, without trig).
inline cv::Vec3f RotateByAlignment(const cv::Vec3f& a, const cv::Vec3f& b, const cv::Vec3f& n) {
  const cv::Vec3f v = a.cross(b);
  const float c = a.dot(b);
  if (c <= -0.99f) return n;  // (nearly) opposite: no well-defined rotation
  return n * c + v.cross(n) + v * (v.dot(n) / (1.f + c));
}

// Nehab's correction (see internal::CorrectNormals) into *out; a and b are scratch images.
void CorrectNormalsInto(const cv::Mat& input, const cv::Mat& reference, double sigma_px,
                        const internal::FusionStencil* links, const RowBlocks& blocks, std::vector<float>* factors,
                        cv::Mat* a, cv::Mat* b, cv::Mat* out) {
  a->create(input.size(), CV_32FC3);
  b->create(input.size(), CV_32FC3);
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      const cv::Vec3f* ni = input.ptr<cv::Vec3f>(y);
      const cv::Vec3f* nr = reference.ptr<cv::Vec3f>(y);
      cv::Vec3f* pa = a->ptr<cv::Vec3f>(y);
      cv::Vec3f* pb = b->ptr<cv::Vec3f>(y);
      for (int x = 0; x < input.cols; ++x) {
        const bool both = NormalPresent(ni[x]) && NormalPresent(nr[x]);
        pa[x] = both ? ni[x] / std::sqrt(ni[x].dot(ni[x])) : cv::Vec3f(0, 0, 0);
        pb[x] = both ? nr[x] / std::sqrt(nr[x].dot(nr[x])) : cv::Vec3f(0, 0, 0);
      }
    }
  });
  if (links != nullptr) {
    EdgeAwareLowPass(*links, sigma_px, blocks, factors, a, b);
  } else {
    *a = GaussianLowPass(*a, sigma_px);
    *b = GaussianLowPass(*b, sigma_px);
  }
  out->create(input.size(), CV_32FC3);
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      const cv::Vec3f* ni = input.ptr<cv::Vec3f>(y);
      const cv::Vec3f* pa = a->ptr<cv::Vec3f>(y);
      const cv::Vec3f* pb = b->ptr<cv::Vec3f>(y);
      cv::Vec3f* o = out->ptr<cv::Vec3f>(y);
      for (int x = 0; x < input.cols; ++x) {
        o[x] = ni[x];
        if (!NormalPresent(ni[x])) continue;
        const float na = std::sqrt(pa[x].dot(pa[x])), nb = std::sqrt(pb[x].dot(pb[x]));
        if (!(na > 1e-6f && nb > 1e-6f)) continue;
        const cv::Vec3f n = RotateByAlignment(pa[x] / na, pb[x] / nb, ni[x] / std::sqrt(ni[x].dot(ni[x])));
        const float len = std::sqrt(n.dot(n));
        if (len > 0) o[x] = n / len;
      }
    }
  });
}

}  // namespace

Status FusionOptions::Check() const {
  std::ostringstream e;
  if (!(position_weight >= 0 && position_weight <= 10))
    e << "FusionOptions.position_weight = " << position_weight << "; violated: in [0, 10]";
  else if (!(prior_weight >= 0 && prior_weight <= 1))
    e << "FusionOptions.prior_weight = " << prior_weight << "; violated: in [0, 1]";
  else if (!(position_weight > 0 || prior_weight > 0))
    e << "FusionOptions.position_weight and prior_weight are both 0; violated: one > 0";
  else if (!(corrected_pass_position_scale > 0 && corrected_pass_position_scale <= 1))
    e << "FusionOptions.corrected_pass_position_scale = " << corrected_pass_position_scale << "; violated: in (0, 1]";
  else if (preconditioner != FusionPreconditioner::kJacobi && preconditioner != FusionPreconditioner::kMultigrid)
    e << "FusionOptions.preconditioner = " << static_cast<int>(preconditioner) << "; violated: kJacobi or kMultigrid";
  else if (max_solver_iterations < 1 || max_solver_iterations > 100000)
    e << "FusionOptions.max_solver_iterations = " << max_solver_iterations << "; violated: in [1, 100000]";
  else if (!(solver_tolerance > 0 && solver_tolerance < 1))
    e << "FusionOptions.solver_tolerance = " << solver_tolerance << "; violated: in (0, 1)";
  else if (!(max_depth_jump > 0 && max_depth_jump <= 10))
    e << "FusionOptions.max_depth_jump = " << max_depth_jump << "; violated: in (0, 10]";
  else if (!(max_normal_angle_deg > 0 && max_normal_angle_deg <= 180))
    e << "FusionOptions.max_normal_angle_deg = " << max_normal_angle_deg << "; violated: in (0, 180]";
  else if (!(contour_slant_deg > 0 && contour_slant_deg <= 90))
    e << "FusionOptions.contour_slant_deg = " << contour_slant_deg << "; violated: in (0, 90]";
  else if (!(contour_slant_drop_deg >= 0 && contour_slant_drop_deg <= 90))
    e << "FusionOptions.contour_slant_drop_deg = " << contour_slant_drop_deg << "; violated: in [0, 90]";
  else if (!(max_slant_deg > 0 && max_slant_deg <= 90))
    e << "FusionOptions.max_slant_deg = " << max_slant_deg << "; violated: in (0, 90]";
  else if (min_unsupported_region_px < 1)
    e << "FusionOptions.min_unsupported_region_px = " << min_unsupported_region_px << "; violated: >= 1";
  else if (!(correction_sigma_px >= 1 && correction_sigma_px <= 200))
    e << "FusionOptions.correction_sigma_px = " << correction_sigma_px << "; violated: in [1, 200]";
  else if (passes < 1 || passes > 10) e << "FusionOptions.passes = " << passes << "; violated: in [1, 10]";
  else if (num_threads < 0 || num_threads > 256)
    e << "FusionOptions.num_threads = " << num_threads << "; violated: in [0, 256]";
  if (!e.str().empty()) return InvalidArgumentError(e.str());
  return densify.Check();
}

namespace internal {

FusionStencil BuildFusionStencil(const FusionInput& input, const cv::Mat& normals, const cv::Mat& prior_depth,
                                 const FusionOptions& options) {
  Rays rays;
  rays.Update(input.camera);
  StencilScratch scratch;
  StencilCounts counts;
  FusionStencil s;
  BuildStencil(input, normals, prior_depth, rays, options, RowBlocks(input.camera.height, 1, nullptr), nullptr, nullptr,
               &scratch, &s, &counts);
  return s;
}

CgSummary SolveStencilCg(const FusionStencil& stencil, int max_iterations, double tolerance,
                         FusionPreconditioner preconditioner, std::vector<float>* x) {
  CgWorkspace ws;
  return SolveCg(stencil, max_iterations, tolerance, preconditioner, 1, nullptr, &ws, x);
}

cv::Mat CorrectNormals(const cv::Mat& input, const cv::Mat& reference, double sigma_px, const FusionStencil* links) {
  PRISM_CHECK(input.type() == CV_32FC3 && reference.type() == CV_32FC3 && input.size() == reference.size());
  PRISM_CHECK(links == nullptr || (links->width == input.cols && links->height == input.rows));
  cv::Mat a, b, out;
  std::vector<float> factors;
  CorrectNormalsInto(input, reference, sigma_px, links, RowBlocks(input.rows, 1, nullptr), &factors, &a, &b, &out);
  return out;
}

}  // namespace internal

struct DepthNormalFusion::Workspace {
  Rays rays;
  cv::Mat prior_depth;
  std::vector<float> x;
  internal::FusionStencil stencil, previous;
  StencilScratch scratch;
  CgWorkspace cg;
  cv::Mat fused_normals, low_a, low_b;
  std::vector<float> filter_factors;
};

DepthNormalFusion::DepthNormalFusion(const FusionOptions& options, ThreadPool* pool)
    : options_(options), pool_(pool), workspace_(std::make_unique<Workspace>()) {}

DepthNormalFusion::~DepthNormalFusion() = default;

StatusOr<FusionResult> DepthNormalFusion::Fuse(const FusionInput& input) {
  const FusionOptions& options = options_;
  PRISM_RETURN_IF_ERROR(options.Check());
  PRISM_RETURN_IF_ERROR(input.camera.Check());
  const PinholeCamera& camera = input.camera;
  PRISM_RETURN_IF_ERROR(CheckImage(input.normals, "normals", CV_32FC3, camera, false));
  PRISM_RETURN_IF_ERROR(CheckImage(input.confidence, "confidence", CV_32F, camera, true));
  PRISM_RETURN_IF_ERROR(CheckImage(input.semi_dense.inverse_depth, "semi_dense.inverse_depth", CV_32F, camera, false));
  PRISM_RETURN_IF_ERROR(CheckImage(input.semi_dense.variance, "semi_dense.variance", CV_32F, camera, false));
  PRISM_RETURN_IF_ERROR(CheckImage(input.prior_inverse_depth, "prior_inverse_depth", CV_32F, camera, true));
  PRISM_RETURN_IF_ERROR(CheckImage(input.initial_depth, "initial_depth", CV_32F, camera, true));
  PRISM_RETURN_IF_ERROR(CheckImage(input.valid_mask, "valid_mask", CV_8U, camera, true));
  if (cv::countNonZero(input.semi_dense.inverse_depth > 0) == 0)
    return FailedPreconditionError("FuseDepthAndNormals: the semi-dense depth is empty");

  Workspace& ws = *workspace_;
  const int w = camera.width, h = camera.height;
  const size_t n = static_cast<size_t>(w) * h;
  const RowBlocks blocks(h, options.num_threads, pool_);
  ws.rays.Update(camera);
  // Prior depth (SLAM units) from the densified inverse depth; the solve starts there (or at the
  // given initial depth).
  const cv::Mat prior_id = input.prior_inverse_depth.empty() ? DensifyInverseDepth(input.semi_dense, options.densify)
                                                             : input.prior_inverse_depth;
  ws.prior_depth.create(h, w, CV_32F);
  ws.x.resize(n);
  blocks.Run([&](int y0, int y1, int) {
    for (int y = y0; y < y1; ++y) {
      const float* p = prior_id.ptr<float>(y);
      const float* init = input.initial_depth.empty() ? nullptr : input.initial_depth.ptr<float>(y);
      float* zp = ws.prior_depth.ptr<float>(y);
      for (int x = 0; x < w; ++x) {
        zp[x] = p[x] > 0 && std::isfinite(p[x]) ? 1.f / p[x] : 0.f;
        const bool has_init = init != nullptr && init[x] > 0 && std::isfinite(init[x]);
        ws.x[static_cast<size_t>(y) * w + x] = has_init ? init[x] : zp[x];
      }
    }
  });

  FusionResult result;
  cv::Mat normals = input.normals;
  StencilCounts counts;
  for (int pass = 0; pass < options.passes; ++pass) {
    if (pass > 0) std::swap(ws.previous, ws.stencil);
    BuildStencil(input, normals, ws.prior_depth, ws.rays, options, blocks, pass > 0 ? &ws.previous : nullptr,
                 pass > 0 ? &ws.x : nullptr, &ws.scratch, &ws.stencil, &counts);
    for (size_t i = 0; i < n; ++i)
      if (!ws.stencil.unknown[i]) ws.x[i] = 0.f;
    const internal::CgSummary cg = SolveCg(ws.stencil, options.max_solver_iterations, options.solver_tolerance,
                                           options.preconditioner, options.num_threads, pool_, &ws.cg, &ws.x);
    result.iterations += cg.iterations;
    result.iterations_per_pass.push_back(cg.iterations);
    result.residual = cg.relative_residual;
    result.converged = cg.converged;
    result.passes = pass + 1;
    if (pass + 1 == options.passes || !options.normal_correction) continue;
    SurfaceNormals(ws.x, ws.stencil, ws.rays, blocks, &ws.fused_normals);
    cv::Mat corrected;
    CorrectNormalsInto(input.normals, ws.fused_normals, options.correction_sigma_px, &ws.stencil, blocks,
                       &ws.filter_factors, &ws.low_a, &ws.low_b, &corrected);
    normals = corrected;
  }
  result.corrected_normals = normals;
  result.unknowns = counts.unknowns;
  result.tangent_rows = counts.tangent_rows;
  result.dropped_tangent_rows = counts.dropped;
  result.depth.create(h, w, CV_32F);
  std::vector<int> samples(blocks.blocks(), 0);
  blocks.Run([&](int y0, int y1, int block) {
    for (int y = y0; y < y1; ++y) {
      float* d = result.depth.ptr<float>(y);
      const float* rho = input.semi_dense.inverse_depth.ptr<float>(y);
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        const float z = ws.x[i];
        // Depth must stay in front of the camera; a non-positive value marks a failed pixel.
        d[x] = ws.stencil.unknown[i] && z > 0 && std::isfinite(z) ? z : 0.f;
        if (ws.stencil.unknown[i] && rho[x] > 0) ++samples[block];
      }
    }
  });
  for (int c : samples) result.position_rows += c;
  SurfaceNormals(ws.x, ws.stencil, ws.rays, blocks, &result.normals);
  return result;
}

StatusOr<FusionResult> FuseDepthAndNormals(const FusionInput& input, const FusionOptions& options, ThreadPool* pool) {
  DepthNormalFusion fusion(options, pool);
  return fusion.Fuse(input);
}

cv::Mat DepthEdgeFreeMask(const cv::Mat& depth, double max_relative_step) {
  PRISM_CHECK(depth.type() == CV_32F) << "DepthEdgeFreeMask needs CV_32F depth";
  cv::Mat keep(depth.size(), CV_8U, cv::Scalar(0));
  const float t = static_cast<float>(max_relative_step);
  for (int y = 0; y < depth.rows; ++y)
    for (int x = 0; x < depth.cols; ++x) {
      const float z = depth.at<float>(y, x);
      if (!(z > 0)) continue;
      bool ok = true;
      for (int dy = -1; dy <= 1 && ok; ++dy)
        for (int dx = -1; dx <= 1 && ok; ++dx) {
          const int yy = y + dy, xx = x + dx;
          if (yy < 0 || xx < 0 || yy >= depth.rows || xx >= depth.cols) continue;
          const float zn = depth.at<float>(yy, xx);
          if (zn > 0 && std::abs(zn - z) > t * z) ok = false;
        }
      if (ok) keep.at<uint8_t>(y, x) = 255;
    }
  return keep;
}

StatusOr<PointCloud> DepthToCloud(const cv::Mat& depth, const cv::Mat& normals, const cv::Mat& rgb,
                                  const PinholeCamera& camera, const Sim3d& world_from_keyframe, int stride,
                                  const cv::Mat& mask, const cv::Mat& confidence) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (stride < 1) return InvalidArgumentError("DepthToCloud: stride = " + std::to_string(stride) + "; violated: >= 1");
  auto check = [&](const cv::Mat& m, const char* name, int type, bool may_be_empty) -> Status {
    if (m.empty() && may_be_empty) return Status::Ok();
    if (m.type() != type || m.cols != camera.width || m.rows != camera.height) {
      std::ostringstream e;
      e << "DepthToCloud: " << name << " is " << m.cols << "x" << m.rows << " of type " << m.type() << "; expected "
        << camera.width << "x" << camera.height << " of type " << type;
      return InvalidArgumentError(e.str());
    }
    return Status::Ok();
  };
  PRISM_RETURN_IF_ERROR(check(depth, "depth", CV_32F, false));
  PRISM_RETURN_IF_ERROR(check(normals, "normals", CV_32FC3, true));
  PRISM_RETURN_IF_ERROR(check(rgb, "rgb", CV_8UC3, true));
  PRISM_RETURN_IF_ERROR(check(mask, "mask", CV_8U, true));
  PRISM_RETURN_IF_ERROR(check(confidence, "confidence", CV_32F, true));
  if (!(world_from_keyframe.scale > 0) || !std::isfinite(world_from_keyframe.scale))
    return InvalidArgumentError("DepthToCloud: world_from_keyframe.scale must be finite and > 0");

  Rays rays;
  rays.Update(camera);
  const Eigen::Matrix3f rotation = world_from_keyframe.rotation.toRotationMatrix().cast<float>();
  const Eigen::Matrix3f scaled_rotation = static_cast<float>(world_from_keyframe.scale) * rotation;
  const Eigen::Vector3f translation = world_from_keyframe.translation.cast<float>();
  PointCloud cloud;
  for (int y = 0; y < depth.rows; y += stride)
    for (int x = 0; x < depth.cols; x += stride) {
      const size_t i = static_cast<size_t>(y) * depth.cols + x;
      const float z = depth.at<float>(y, x);
      if (!(z > 0) || !std::isfinite(z)) continue;
      if (!mask.empty() && mask.at<uint8_t>(y, x) == 0) continue;
      if (!normals.empty() && !NormalPresent(normals.at<cv::Vec3f>(y, x))) continue;
      const Eigen::Vector3f p(rays.x[i] * z, rays.y[i] * z, z);
      cloud.positions.push_back(scaled_rotation * p + translation);
      if (!normals.empty()) {
        const cv::Vec3f& nm = normals.at<cv::Vec3f>(y, x);
        cloud.normals.push_back((rotation * Eigen::Vector3f(nm[0], nm[1], nm[2])).normalized());
      }
      if (!rgb.empty()) {
        const cv::Vec3b& c = rgb.at<cv::Vec3b>(y, x);
        cloud.colors.emplace_back(c[0], c[1], c[2]);
      }
      cloud.confidences.push_back(confidence.empty() ? 1.f : confidence.at<float>(y, x));
    }
  return cloud;
}

StatusOr<InverseDepthMap> ProjectCloudToKeyframe(const PointCloud& cloud_in_world, const Sim3d& keyframe_from_world,
                                                 const PinholeCamera& camera, double default_variance) {
  PRISM_RETURN_IF_ERROR(camera.Check());
  if (!cloud_in_world.IsConsistent()) return InvalidArgumentError("ProjectCloudToKeyframe: inconsistent cloud");
  if (!(default_variance > 0) || !std::isfinite(default_variance))
    return InvalidArgumentError("ProjectCloudToKeyframe: default_variance must be finite and > 0");
  InverseDepthMap out;
  out.inverse_depth = cv::Mat(camera.height, camera.width, CV_32F, cv::Scalar(0));
  out.variance = cv::Mat(camera.height, camera.width, CV_32F, cv::Scalar(0));
  for (size_t k = 0; k < cloud_in_world.size(); ++k) {
    const Eigen::Vector3d p = keyframe_from_world * cloud_in_world.positions[k].cast<double>();
    if (!(p.z() > 0) || !p.allFinite()) continue;
    const Eigen::Vector2d uv = camera.Project(p);
    if (!uv.allFinite()) continue;
    const long x = std::lround(uv.x()), y = std::lround(uv.y());
    if (x < 0 || y < 0 || x >= camera.width || y >= camera.height) continue;
    double variance = default_variance;
    if (cloud_in_world.HasConfidences()) {
      const float c = cloud_in_world.confidences[k];
      if (!(c > 0) || !std::isfinite(c)) continue;
      variance = 1.0 / c;
    }
    const float rho = static_cast<float>(1.0 / p.z());
    float& id = out.inverse_depth.at<float>(static_cast<int>(y), static_cast<int>(x));
    if (rho <= id) continue;  // keep the nearest point
    id = rho;
    out.variance.at<float>(static_cast<int>(y), static_cast<int>(x)) = static_cast<float>(variance);
  }
  return out;
}

}  // namespace prism
