#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Cholesky>

#include "core/fusion/fusion_internal.h"
#include "core/util/check.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {
namespace {

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

}  // namespace

void MultigridPreconditioner::Setup(const internal::FusionStencil& s, int num_threads, ThreadPool* pool) {
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

double MultigridPreconditioner::Apply(std::vector<float>* r, std::vector<float>* z) {
  GridLevel& f = levels_[0];
  f.b.swap(*r);
  Cycle(0);
  f.b.swap(*r);
  z->swap(f.x);
  f.x.resize(r->size());
  return Sum(dots_);
}

void MultigridPreconditioner::Coarsen(const GridLevel& f, GridLevel* c) {
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

void MultigridPreconditioner::SmoothRows(GridLevel& g, int colour, int y0, int y1, float* t) {
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

void MultigridPreconditioner::Smooth(GridLevel& g, int colour) {
  Blocks(g).Run([&](int y0, int y1, int block) {
    SmoothRows(g, colour, y0, y1, g.row_scratch.data() + static_cast<size_t>(block) * g.w);
  });
}

void MultigridPreconditioner::Cycle(int l) {
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

}  // namespace internal
}  // namespace prism
