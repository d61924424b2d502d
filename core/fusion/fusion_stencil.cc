#include <algorithm>
#include <cmath>
#include <vector>

#include "core/fusion/fusion_internal.h"
#include "core/util/check.h"

namespace prism {
namespace internal {
namespace {

// Largest weight of a SLAM sample relative to a median-variance one.
constexpr float kMaxRelativeInverseVariance = 10.f;

// Per pixel: unknown or not, SLAM sample (relative variance var_rho / rho^2), unit normal
// (confidence 0 = none), cosine and sine of its slant against the pixel's ray. Counts the unknowns
// per block in scratch->block_a and the samples in scratch->block_b.
void ClassifyPixels(const FusionInput& input, const cv::Mat& normals, const cv::Mat& prior_depth, const Rays& rays,
                    const RowBlocks& blocks, StencilScratch* scratch, internal::FusionStencil* s) {
  const int w = input.camera.width;
  StencilScratch& t = *scratch;
  const bool has_confidence = !input.confidence.empty();
  const bool has_mask = !input.valid_mask.empty();
  const cv::Mat& sd = input.semi_dense.inverse_depth;
  const cv::Mat& sd_var = input.semi_dense.variance;
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
}

// Pair rows, pre-multiplied by sqrt(weight), into scratch->ar, br, ad, bd; the pairs cut by the tests
// (a) to (d) are counted in counts->dropped.
void BuildPairRows(const FusionInput& input, const Rays& rays, const FusionOptions& options, const RowBlocks& blocks,
                   const internal::FusionStencil* previous, const std::vector<float>* previous_depth,
                   StencilScratch* scratch, internal::FusionStencil* s, StencilCounts* counts) {
  const int w = input.camera.width, h = input.camera.height;
  StencilScratch& t = *scratch;
  const cv::Mat& sd = input.semi_dense.inverse_depth;
  // Test (a): |log(A) - log(B)| > max_depth_jump <=> A / B outside [1 / e^t, e^t].
  const float max_ratio = static_cast<float>(std::exp(options.max_depth_jump));
  const float min_ratio = 1.f / max_ratio;
  const float cos_crease = static_cast<float>(std::cos(options.max_normal_angle_deg * M_PI / 180.0));
  const float cos_contour = static_cast<float>(std::cos(options.contour_slant_deg * M_PI / 180.0));
  const float cos_drop = static_cast<float>(std::cos(options.contour_slant_drop_deg * M_PI / 180.0));
  const float sin_drop = static_cast<float>(std::sin(options.contour_slant_drop_deg * M_PI / 180.0));
  const float cos_max_slant = static_cast<float>(std::cos(options.max_slant_deg * M_PI / 180.0));
  const float* prev_depth = previous_depth != nullptr && previous != nullptr ? previous_depth->data() : nullptr;

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
}

// Connected regions over the rows kept (union-find). Regions without SLAM depth are singular but
// for the prior tie: small ones (slivers along depth edges, where the blurred prior is wrong) are
// dropped (*unknowns counts them down); large ones follow the prior at low frequencies.
void DropUnsupportedRegions(const FusionOptions& options, int w, size_t n, StencilScratch* scratch,
                            internal::FusionStencil* s, int* unknowns) {
  StencilScratch& t = *scratch;
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
    --*unknowns;
    t.ar[i] = t.br[i] = t.ad[i] = t.bd[i] = 0.f;
  }
}

// The normal equations, gathered per pixel; the tangent rows kept are counted in counts->tangent_rows.
void GatherNormalEquations(const FusionInput& input, const cv::Mat& prior_depth, float position_weight,
                           float prior_weight, float median_var, const RowBlocks& blocks, StencilScratch* scratch,
                           internal::FusionStencil* s, StencilCounts* counts) {
  const int w = input.camera.width;
  StencilScratch& t = *scratch;
  const cv::Mat& sd = input.semi_dense.inverse_depth;
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
}

}  // namespace

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

  ClassifyPixels(input, normals, prior_depth, rays, blocks, scratch, s);
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

  BuildPairRows(input, rays, options, blocks, previous, previous_depth, scratch, s, counts);
  DropUnsupportedRegions(options, w, n, scratch, s, &unknowns);
  GatherNormalEquations(input, prior_depth, position_weight, prior_weight, median_var, blocks, scratch, s, counts);
  counts->unknowns = unknowns;
  counts->samples = samples;
}

}  // namespace internal
}  // namespace prism
