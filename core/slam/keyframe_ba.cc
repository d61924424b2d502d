#include "core/slam/keyframe_ba.h"

#include <cmath>
#include <sstream>

#include "core/slam/keyframe_ba_internal.h"

namespace prism {

Eigen::Matrix<double, 6, 6> DirectBaHostFromTarget(const Eigen::Matrix3d& host_rotation,
                                                   const Eigen::Vector3d& host_centre,
                                                   const Eigen::Matrix3d& target_rotation,
                                                   const Eigen::Vector3d& target_centre) {
  // With x = c_h + s_h R_h q and p = R_t^T (x - c_t): d p / d w_h = -R_t^T Skew(x - c_h) R_h, and
  // x - c_h = R_t p + c_t - c_h, so d p / d w_h = -Skew(p) R_t^T R_h + R_t^T Skew(c_h - c_t) R_h; with
  // d p / d w_t = Skew(p) and d p / d c_t = -R_t^T that is (d p / d w_t) (-R_t^T R_h) +
  // (d p / d c_t) (-Skew(c_h - c_t) R_h); and d p / d c_h = R_t^T = -(d p / d c_t).
  Eigen::Matrix<double, 6, 6> a = Eigen::Matrix<double, 6, 6>::Zero();
  a.block<3, 3>(0, 0) = -target_rotation.transpose() * host_rotation;
  a.block<3, 3>(3, 0) = -internal::Skew(host_centre - target_centre) * host_rotation;
  a.block<3, 3>(3, 3) = -Eigen::Matrix3d::Identity();
  return a;
}

double DepthOverlapFraction(const PinholeCamera& camera, const cv::Mat& inverse_depth, const Sim3d& world_from_a,
                            const Sim3d& world_from_b, int step) {
  if (inverse_depth.empty() || step < 1) return 1.0;
  // In a's depth unit (the projection does not depend on the unit).
  const Rigid3d b_from_a = BFromAInUnitsOfA(world_from_a, world_from_b);
  const Eigen::Matrix3d r = b_from_a.RotationMatrix();
  const Eigen::Vector3d& t = b_from_a.translation;
  int total = 0, inside = 0;
  for (int y = 0; y < inverse_depth.rows; y += step) {
    const float* row = inverse_depth.ptr<float>(y);
    for (int x = 0; x < inverse_depth.cols; x += step) {
      if (!(row[x] > 0)) continue;
      ++total;
      const Eigen::Vector3d p = r * (camera.Unproject(Eigen::Vector2d(x, y)) / row[x]) + t;
      if (p.z() > 0 && camera.InImage(camera.Project(p))) ++inside;
    }
  }
  return total > 0 ? static_cast<double>(inside) / total : 1.0;
}

Status DirectBaOptions::Check() const {
  std::ostringstream e;
  if (max_iterations < 1 || max_iterations > 100)
    e << "DirectBaOptions.max_iterations = " << max_iterations << "; violated: in [1, 100]";
  else if (!(huber > 0)) e << "DirectBaOptions.huber = " << huber << "; violated: > 0";
  else if (!(outlier > huber)) e << "DirectBaOptions.outlier = " << outlier << "; violated: > huber";
  else if (pyramid_levels < 1 || pyramid_levels > 5)
    e << "DirectBaOptions.pyramid_levels = " << pyramid_levels << "; violated: in [1, 5]";
  else if (border_px < 2) e << "DirectBaOptions.border_px = " << border_px << "; violated: >= 2";
  else if (!(function_tolerance > 0))
    e << "DirectBaOptions.function_tolerance = " << function_tolerance << "; violated: > 0";
  else if (!(gradient_weight_c >= 0))
    e << "DirectBaOptions.gradient_weight_c = " << gradient_weight_c << "; violated: >= 0";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

cv::Mat MeanOfChannels(const cv::Mat& rgb) {
  cv::Mat grey(rgb.size(), CV_32F);
  for (int y = 0; y < rgb.rows; ++y) {
    const cv::Vec3b* in = rgb.ptr<cv::Vec3b>(y);
    float* out = grey.ptr<float>(y);
    for (int x = 0; x < rgb.cols; ++x) out[x] = (in[x][0] + in[x][1] + in[x][2]) / 3.0f;
  }
  return grey;
}

StatusOr<DirectBaSummary> AdjustKeyframeWindowDirect(const DirectBaOptions& options, DirectBaProblem* problem,
                                                     ThreadPool* pool) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (problem == nullptr) return InvalidArgumentError("AdjustKeyframeWindowDirect: problem is null");
  const int num_kf = static_cast<int>(problem->world_from_keyframe.size());
  if (num_kf < 2) return InvalidArgumentError("AdjustKeyframeWindowDirect: needs >= 2 keyframes");
  if (static_cast<int>(problem->grey_j.size()) != num_kf)
    return InvalidArgumentError("AdjustKeyframeWindowDirect: one grey image per keyframe expected");
  const PinholeCamera& cam = problem->camera;
  if (cam.HasDistortion()) return InvalidArgumentError("AdjustKeyframeWindowDirect: camera has distortion");
  for (const cv::Mat& g : problem->grey_j)
    if (g.type() != CV_32F || g.cols != cam.width || g.rows != cam.height)
      return InvalidArgumentError("AdjustKeyframeWindowDirect: grey images must be CV_32F of the camera's size");
  for (const DirectBaPoint& p : problem->points)
    if (p.host < 0 || p.host >= num_kf || !(p.inverse_depth > 0))
      return InvalidArgumentError("AdjustKeyframeWindowDirect: point with a bad host or inverse depth");
  const DirectBaRelit& relit = problem->relit;
  const bool use_relit = relit.rig != nullptr;
  if (use_relit) {
    if (static_cast<int>(relit.rgb.size()) != num_kf)
      return InvalidArgumentError("AdjustKeyframeWindowDirect: relit needs one colour image per keyframe");
    for (const cv::Mat& c : relit.rgb)
      if (c.type() != CV_8UC3 || c.cols != cam.width || c.rows != cam.height)
        return InvalidArgumentError(
            "AdjustKeyframeWindowDirect: relit colour images must be CV_8UC3 of the camera's size");
    if (!(relit.metres_per_world_unit > 0) || !std::isfinite(relit.metres_per_world_unit))
      return InvalidArgumentError("AdjustKeyframeWindowDirect: relit metres_per_world_unit must be > 0");
    if (!(relit.albedo_colour.minCoeff() > 0) || !relit.albedo_colour.allFinite())
      return InvalidArgumentError("AdjustKeyframeWindowDirect: relit albedo_colour must be > 0");
    if (!(relit.min_band_fraction >= 0 && relit.min_band_fraction < 1))
      return InvalidArgumentError("AdjustKeyframeWindowDirect: relit min_band_fraction must be in [0, 1)");
    if (options.pyramid_levels != 1)
      return InvalidArgumentError("AdjustKeyframeWindowDirect: the relit residual needs pyramid_levels = 1");
    if (relit.mixed && !(relit.relit_residual_scale > 0 && std::isfinite(relit.relit_residual_scale)))
      return InvalidArgumentError("AdjustKeyframeWindowDirect: relit relit_residual_scale must be > 0");
  } else if (relit.mixed) {
    return InvalidArgumentError("AdjustKeyframeWindowDirect: relit.mixed needs relit.rig");
  }

  internal::DirectBaSolver solver(options, problem, pool);
  return solver.Run();
}

}  // namespace prism
