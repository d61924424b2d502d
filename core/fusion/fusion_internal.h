// The internals of DepthNormalFusion (fusion.h), shared by its parts: the row-block loops and the
// camera rays (here), the stencil assembly (fusion_stencil.cc), the multigrid-preconditioned
// conjugate gradients (fusion_solver.cc), the surface normals and Nehab's normal correction
// (fusion_normals.cc), and the fusion driver and the dense cloud (fusion.cc, fusion_cloud.cc).
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include <Eigen/Cholesky>
#include <opencv2/core.hpp>

#include "core/fusion/fusion.h"
#include "core/geometry/camera.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {

// Rows per block of the parallel loops (even: see the multigrid restriction). Blocks, not threads,
// own the partial sums of reductions, so results do not depend on the number of threads.
constexpr int kRowsPerBlock = 8;
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

inline double Sum(const std::vector<double>& v) {
  double t = 0;
  for (double e : v) t += e;  // fixed order
  return t;
}

// sum a[i] * b[i] over [0, n): eight float lanes (vectorised without -ffast-math), summed in double.
inline double Dot(const float* a, const float* b, size_t n) {
  float acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  size_t i = 0;
  for (; i + 8 <= n; i += 8)
    for (int k = 0; k < 8; ++k) acc[k] += a[i + k] * b[i + k];
  double sum = 0;
  for (int k = 0; k < 8; ++k) sum += acc[k];
  for (; i < n; ++i) sum += static_cast<double>(a[i]) * b[i];
  return sum;
}

inline bool NormalPresent(const cv::Vec3f& n) {
  const float len2 = n.dot(n);
  return std::isfinite(len2) && len2 >= kMinNormalLength * kMinNormalLength;
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
// Stencil assembly (fusion_stencil.cc).

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
                  StencilCounts* counts);

// ---------------------------------------------------------------------------------------------------
// Solver (fusion_solver.cc).

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
  void Setup(const internal::FusionStencil& s, int num_threads, ThreadPool* pool);

  // z = M^-1 r; returns r . z (summed per row block in a fixed order). r is borrowed as the finest
  // right-hand side during the cycle (no copy) and handed back unchanged.
  double Apply(std::vector<float>* r, std::vector<float>* z);

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

  static void Coarsen(const GridLevel& f, GridLevel* c);

  // Gauss-Seidel on the pixels of one colour ((x + y) % 2 == colour) of rows [y0, y1): the update of
  // a whole row is computed (vectorised; a pixel's neighbours all have the other colour), then the
  // pixels of the colour are written. The first and last row of the range read only the other colour
  // of the rows beyond it: another thread is writing this colour there (a data race, found by TSan,
  // even though those values were discarded).
  static void SmoothRows(GridLevel& g, int colour, int y0, int y1, float* t);

  void Smooth(GridLevel& g, int colour);

  void Cycle(int l);

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

// Preconditioned conjugate gradients on the stencil from *x_out, on up to num_threads threads of pool.
internal::CgSummary SolveCg(const internal::FusionStencil& s, int max_iterations, double tolerance,
                            FusionPreconditioner preconditioner, int num_threads, ThreadPool* pool, CgWorkspace* ws,
                            std::vector<float>* x_out);

// ---------------------------------------------------------------------------------------------------
// Normals (fusion_normals.cc).

// Normals of the surface Z r(u) into *out (CV_32FC3): central differences along the tangent rows that
// were used (one-sided where a neighbour is cut off), facing the camera; 0 where a direction has no
// neighbour or the depth is not positive.
void SurfaceNormals(const std::vector<float>& depth, const internal::FusionStencil& s, const Rays& rays,
                    const RowBlocks& blocks, cv::Mat* out);

// Nehab's correction (see internal::CorrectNormals) into *out; a and b are scratch images.
void CorrectNormalsInto(const cv::Mat& input, const cv::Mat& reference, double sigma_px,
                        const internal::FusionStencil* links, const RowBlocks& blocks, std::vector<float>* factors,
                        cv::Mat* a, cv::Mat* b, cv::Mat* out);

}  // namespace internal
}  // namespace prism
