#include "core/fusion/fusion.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <string>

#include "core/fusion/fusion_internal.h"
#include "core/util/check.h"
#include "core/util/thread_pool.h"

namespace prism {

using internal::BuildStencil;
using internal::CgWorkspace;
using internal::CorrectNormalsInto;
using internal::Rays;
using internal::RowBlocks;
using internal::SolveCg;
using internal::StencilCounts;
using internal::StencilScratch;
using internal::SurfaceNormals;

namespace {

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

}  // namespace prism
