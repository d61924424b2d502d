#include "core/slam/keyframe_ba.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <memory>
#include <sstream>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <opencv2/imgproc.hpp>

#include "core/util/thread_pool.h"

namespace prism {
namespace {

Eigen::Matrix3d Skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

double HuberCost(double e, double delta) { return e <= delta ? 0.5 * e * e : delta * (e - 0.5 * delta); }

// PinholeCamera::Project without distortion (the problem's camera has none), inlined: the same
// operations in the same order.
[[gnu::always_inline]] inline Eigen::Vector2d ProjectUndistorted(const PinholeCamera& c, const Eigen::Vector3d& p) {
  const Eigen::Vector2d n(p.x() / p.z(), p.y() / p.z());
  return {c.fx * n.x() + c.cx, c.fy * n.y() + c.cy};
}

// Bilinear sample of a CV_32F image and its gradient (central differences of the bilinear surface);
// false within 2 pixels of the border.
[[gnu::always_inline]] inline bool SampleWithGradient(const cv::Mat& img, double x, double y, double* value,
                                                      Eigen::Vector2d* grad) {
  if (!(x >= 1 && y >= 1 && x < img.cols - 2 && y < img.rows - 2)) return false;
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const double fx = x - x0, fy = y - y0;
  // Rows y0 - 1 .. y0 + 2 (the bounds test above keeps them and columns x0 - 1 .. x0 + 2 inside).
  const float* rows[4] = {img.ptr<float>(y0 - 1), img.ptr<float>(y0), img.ptr<float>(y0 + 1), img.ptr<float>(y0 + 2)};
  // The bilinear sample with top-left tap (row r of `rows`, column xx).
  auto bil = [&](int r, int xx) __attribute__((always_inline)) {
    const float* a = rows[r];
    const float* b = rows[r + 1];
    return (1 - fx) * (1 - fy) * static_cast<double>(a[xx]) + fx * (1 - fy) * static_cast<double>(a[xx + 1]) +
           (1 - fx) * fy * static_cast<double>(b[xx]) + fx * fy * static_cast<double>(b[xx + 1]);
  };
  *value = bil(1, x0);
  // Central differences of the bilinear surface, sampled at the neighbours.
  const double gx = 0.5 * (bil(1, x0 + 1) - bil(1, x0 - 1));
  const double gy = 0.5 * (bil(2, x0) - bil(0, x0));
  *grad = Eigen::Vector2d(gx, gy);
  return true;
}

// The value of SampleWithGradient alone (the same bilinear sum; false where it is false).
[[gnu::always_inline]] inline bool SampleValue(const cv::Mat& img, double x, double y, double* value) {
  if (!(x >= 1 && y >= 1 && x < img.cols - 2 && y < img.rows - 2)) return false;
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const double fx = x - x0, fy = y - y0;
  const float* a = img.ptr<float>(y0) + x0;
  const float* b = img.ptr<float>(y0 + 1) + x0;
  *value = (1 - fx) * (1 - fy) * static_cast<double>(a[0]) + fx * (1 - fy) * static_cast<double>(a[1]) +
           (1 - fx) * fy * static_cast<double>(b[0]) + fx * fy * static_cast<double>(b[1]);
  return true;
}

// Prefetches the cache lines SampleWithGradient (and SampleValue) read at (x, y): rows y0 - 1 .. y0 + 2,
// columns x0 - 1 .. x0 + 2. The adjustment reads one pixel per 16x16 cell of each host in each target, so
// hardly any two samples share a line, and without this the linearisation waits on memory for about a
// third of its time (perf, armadillo preset). Reading ahead changes no arithmetic.
[[gnu::always_inline]] inline void PrefetchSample(const cv::Mat& img, double x, double y) {
  const int x0 = std::clamp(static_cast<int>(x), 1, img.cols - 3),
            y0 = std::clamp(static_cast<int>(y), 1, img.rows - 3);
  for (int r = -1; r <= 2; ++r) {
    const float* row = img.ptr<float>(y0 + r);
    __builtin_prefetch(row + x0 - 1);
    __builtin_prefetch(row + x0 + 2);
  }
}

// A residual's projection into its target, computed ahead of its image reads.
struct Projected {
  int point;
  Eigen::Vector3d pt;  // in the target camera
  Eigen::Vector2d px;
};

// One target's projections: at most one per point. The scratch lists get room for all at once, so an
// append never reallocates (std::vector's push_back, with its growth path, was a call per residual); the
// lists kept per target (linearise_from_evaluation) start empty and grow to what their target sees.
class ProjectedList {
 public:
  // The entries are left uninitialised (each is written before it is read).
  explicit ProjectedList(size_t capacity)
      : items_(capacity > 0 ? new Projected[capacity] : nullptr), capacity_(capacity) {}
  void clear() { size_ = 0; }
  void push_back(const Projected& p) {
    if (size_ == capacity_) [[unlikely]]
      Grow();
    items_[size_++] = p;
  }
  size_t size() const { return size_; }
  const Projected& operator[](size_t k) const { return items_[k]; }

 private:
  [[gnu::noinline]] void Grow() {
    const size_t capacity = std::max<size_t>(1024, 2 * capacity_);
    std::unique_ptr<Projected[]> items(new Projected[capacity]);
    std::copy(items_.get(), items_.get() + size_, items.get());
    items_ = std::move(items);
    capacity_ = capacity;
  }
  std::unique_ptr<Projected[]> items_;
  size_t capacity_ = 0;
  size_t size_ = 0;
};

// A residual's image value and gradient (false ok: too near the border, no residual).
struct Sampled {
  double value;
  Eigen::Vector2d g;
  bool ok;
};

// One target's residuals as a cost evaluation read them (linearise_from_evaluation): projections, values
// and gradients.
struct TargetSamples {
  ProjectedList visible{0};
  std::vector<Sampled> sampled;
};

// How many residuals ahead the image rows are prefetched.
constexpr size_t kPrefetchAhead = 8;

// Sums of one (host, target) pair's residuals in the target pose's parameters: h (lower triangle) of
// w j^T j and b of w j^T r.
struct PairSums {
  Eigen::Matrix<double, 6, 6> h = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
  bool used = false;
};

}  // namespace

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
  a.block<3, 3>(3, 0) = -Skew(host_centre - target_centre) * host_rotation;
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

  struct Pose {
    Eigen::Matrix3d rotation;
    Eigen::Vector3d centre;
    double scale;
  };
  std::vector<Pose> poses(static_cast<size_t>(num_kf));
  for (int k = 0; k < num_kf; ++k) {
    const Sim3d& s = problem->world_from_keyframe[static_cast<size_t>(k)];
    poses[static_cast<size_t>(k)] = {s.rotation.toRotationMatrix(), s.translation, s.scale};
  }
  const int num_points = static_cast<int>(problem->points.size());
  std::vector<double> rho(static_cast<size_t>(num_points));
  std::vector<Eigen::Vector3d> ray(static_cast<size_t>(num_points));
  for (int i = 0; i < num_points; ++i) {
    const DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
    rho[static_cast<size_t>(i)] = p.inverse_depth;
    ray[static_cast<size_t>(i)] = cam.Unproject(Eigen::Vector2d(p.u, p.v));
  }
  // Which points take the relit residual (all with relit.rig, those marked with relit.mixed), its scale
  // (1 for J points, or their gradient weight below), and in mixed mode the raw grey images they are
  // compared against.
  std::vector<uint8_t> relit_point(static_cast<size_t>(num_points), 0);
  std::vector<double> residual_scale(static_cast<size_t>(num_points), 1.0);
  for (int i = 0; i < num_points; ++i) {
    relit_point[static_cast<size_t>(i)] = use_relit && (!relit.mixed || problem->points[static_cast<size_t>(i)].relit);
    if (relit.mixed && relit_point[static_cast<size_t>(i)])
      residual_scale[static_cast<size_t>(i)] = relit.relit_residual_scale;
  }
  std::vector<cv::Mat> raw_grey;
  if (use_relit && relit.mixed)
    for (const cv::Mat& rgb : relit.rgb) raw_grey.push_back(MeanOfChannels(rgb));
  // The image point i's residual in target t reads: J (or with relit.rig alone the raw grey level, which
  // grey_j then holds), or in mixed mode the raw grey level for relit points.
  auto image_of = [&](const std::vector<cv::Mat>& level_images, int i, int t) -> const cv::Mat& {
    return relit.mixed && relit_point[static_cast<size_t>(i)] ? raw_grey[static_cast<size_t>(t)]
                                                              : level_images[static_cast<size_t>(t)];
  };
  // Relit: each point's demixed host colour (NaN intensity marks a point left out), and the model.
  std::vector<Eigen::Vector3d> bands(use_relit ? static_cast<size_t>(num_points) : 0);
  std::vector<Eigen::Vector3d> normal_rho(use_relit ? static_cast<size_t>(num_points) : 0);       // rho n, host camera
  std::vector<Eigen::Vector3d> normal_rho_drho(use_relit ? static_cast<size_t>(num_points) : 0);  // its d / d rho
  Eigen::RowVector3d grey_of_light = Eigen::RowVector3d::Constant(1.0 / 3);
  double metres = relit.metres_per_world_unit;  // K: changes when it is estimated
  const bool estimate_k = use_relit && relit.estimate_metres_per_world_unit;
  const double log_k_step = 1e-4;  // for d residual / d log K
  std::vector<Eigen::Vector3d> normal_rho_kp(estimate_k ? static_cast<size_t>(num_points) : 0);  // at K e^+step
  std::vector<Eigen::Vector3d> normal_rho_km(estimate_k ? static_cast<size_t>(num_points) : 0);  // at K e^-step
  if (use_relit) {
    const Eigen::Matrix3d demix = relit.rig->crosstalk.inverse();
    grey_of_light = relit.rig->crosstalk.colwise().sum() / 3.0;
    for (int i = 0; i < num_points; ++i) {
      DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
      if (!relit_point[static_cast<size_t>(i)]) {
        bands[static_cast<size_t>(i)].setConstant(std::numeric_limits<double>::quiet_NaN());
        continue;
      }
      const cv::Vec3b c =
          relit.rgb[static_cast<size_t>(p.host)].at<cv::Vec3b>(static_cast<int>(p.v), static_cast<int>(p.u));
      const Eigen::Vector3d b = demix * Eigen::Vector3d(c[0], c[1], c[2]);
      bands[static_cast<size_t>(i)] = b.cwiseQuotient(relit.albedo_colour);
      const bool usable = std::max({c[0], c[1], c[2]}) < 250 && b.maxCoeff() > 0 &&
                          b.minCoeff() >= relit.min_band_fraction * b.maxCoeff();
      if (!usable) bands[static_cast<size_t>(i)].setConstant(std::numeric_limits<double>::quiet_NaN());
    }
  }
  // S(p): rows E_l(p) L_l(p)^T at a metric point in the camera.
  auto lighting = [&](const Eigen::Vector3d& point_m) {
    Eigen::Matrix3d m;
    for (int l = 0; l < 3; ++l) {
      Eigen::Vector3d to_light;
      double irradiance;
      relit.rig->lights[static_cast<size_t>(l)].Illuminate(point_m, &to_light, &irradiance);
      m.row(l) = irradiance * to_light.transpose();
    }
    return m;
  };
  // rho n of point i at inverse depth r (host camera), NaN when its implied normal faces away.
  auto implied_normal = [&](const std::vector<Pose>& ps, int i, double r, double k) -> Eigen::Vector3d {
    const Pose& h = ps[static_cast<size_t>(problem->points[static_cast<size_t>(i)].host)];
    const Eigen::Vector3d x = (k * h.scale / r) * ray[static_cast<size_t>(i)];
    const Eigen::Vector3d m = lighting(x).inverse() * bands[static_cast<size_t>(i)];
    if (!m.allFinite() || m.dot(-x.normalized()) < 0.1 * m.norm())
      return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
    return m;
  };
  // The predicted raw grey level of point i (rho n = m in its host's camera) at pt in target t's camera
  // (world units).
  auto relit_prediction = [&](const std::vector<Pose>& ps, int i, int t, const Eigen::Vector3d& pt,
                              const Eigen::Vector3d& m, double k) {
    const Pose& h = ps[static_cast<size_t>(problem->points[static_cast<size_t>(i)].host)];
    const Eigen::Vector3d n_t = ps[static_cast<size_t>(t)].rotation.transpose() * (h.rotation * m);
    const Eigen::Vector3d x = k * pt;
    Eigen::Vector3d shading;
    for (int l = 0; l < 3; ++l) {
      Eigen::Vector3d to_light;
      double irradiance;
      relit.rig->lights[static_cast<size_t>(l)].Illuminate(x, &to_light, &irradiance);
      shading[l] = irradiance * std::max(0.0, n_t.dot(to_light)) * relit.albedo_colour(l);
    }
    return (grey_of_light * shading)(0);
  };
  Eigen::Vector3d baseline = poses[1].centre - poses[0].centre;
  const double baseline_norm = baseline.norm();
  baseline = baseline_norm > 0 ? Eigen::Vector3d(baseline / baseline_norm) : Eigen::Vector3d::UnitX();
  const Eigen::Vector3d centre1_initial = poses[1].centre;
  const int dim = 6 * (num_kf - 1);
  // Stiff against the photometric rows (gradient^2 f^2 / z^2 per residual, many residuals).
  const double gauge_weight = 1e10 * cam.fx * cam.fx / std::max(1e-12, baseline_norm * baseline_norm);
  const double border = options.border_px;
  // active[point * num_kf + target]
  std::vector<uint8_t> active(static_cast<size_t>(num_points) * num_kf, 1);

  // Point i in the world (once per point; collect_visible takes it into each target's camera).
  auto world_point = [&](const std::vector<Pose>& ps, int i, double r) -> Eigen::Vector3d {
    const Pose& h = ps[static_cast<size_t>(problem->points[static_cast<size_t>(i)].host)];
    return h.centre + h.scale * (h.rotation * (ray[static_cast<size_t>(i)] / r));
  };
  // Image pyramid (2x2 box averages) for a wider convergence basin: coarse to fine.
  const int levels = options.pyramid_levels;
  std::vector<std::vector<cv::Mat>> pyramid(static_cast<size_t>(levels));
  pyramid[0] = problem->grey_j;
  for (int l = 1; l < levels; ++l)
    for (const cv::Mat& g : pyramid[static_cast<size_t>(l - 1)]) {
      cv::Mat half;
      cv::resize(g, half, cv::Size(g.cols / 2, g.rows / 2), 0, 0, cv::INTER_AREA);
      pyramid[static_cast<size_t>(l)].push_back(half);
    }
  if (options.gradient_weight_c > 0) {
    const double c2 = options.gradient_weight_c * options.gradient_weight_c;
    for (int i = 0; i < num_points; ++i) {
      if (relit_point[static_cast<size_t>(i)]) continue;
      const DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
      double value;
      Eigen::Vector2d g;
      if (SampleWithGradient(pyramid[0][static_cast<size_t>(p.host)], p.u, p.v, &value, &g))
        residual_scale[static_cast<size_t>(i)] = std::sqrt(c2 / (c2 + g.squaredNorm()));
    }
  }
  PinholeCamera lcam = cam;
  const std::vector<cv::Mat>* limg = &pyramid[0];
  std::vector<float> lint(static_cast<size_t>(num_points));
  for (int i = 0; i < num_points; ++i) lint[static_cast<size_t>(i)] = problem->points[static_cast<size_t>(i)].intensity;
  // Relit points: lint only marks the points left out (NaN).
  for (int i = 0; i < num_points; ++i)
    if (relit_point[static_cast<size_t>(i)])
      lint[static_cast<size_t>(i)] =
          bands[static_cast<size_t>(i)].allFinite() ? 0.0f : std::numeric_limits<float>::quiet_NaN();

  // Target t's residuals that project into its image at the current level: the points `usable` accepts,
  // hosted elsewhere and active in t, in point order (xw: the points in the world). The image reads come
  // after, prefetched kPrefetchAhead residuals ahead.
  auto collect_visible = [&](int t, const Eigen::Matrix3d& rt_t, const Eigen::Vector3d& c_t,
                             const std::vector<Eigen::Vector3d>& xw, const auto& usable, ProjectedList* out) {
    out->clear();
    for (int i = 0; i < num_points; ++i) {
      if (!usable(i) || t == problem->points[static_cast<size_t>(i)].host ||
          !active[static_cast<size_t>(i) * num_kf + t])
        continue;
      const Eigen::Vector3d pt = rt_t * (xw[static_cast<size_t>(i)] - c_t);
      if (!(pt.z() > 1e-9)) continue;
      const Eigen::Vector2d px = ProjectUndistorted(lcam, pt);
      if (!lcam.InImage(px, border)) continue;
      out->push_back({i, pt, px});
    }
  };
  std::atomic<long long> image_samples{0};  // residuals whose image was read (DirectBaSummary::image_samples)
  // The image reads of target t's residuals `visible`, all at once: a short loop whose loads overlap
  // (inside the long loops after it each one waited for its sample; 12% of the adjustment's time,
  // BM_KeyframeWindowAdjustment), prefetched kPrefetchAhead residuals ahead, and in the order of their
  // image rows (a counting sort). In point order each host's points sweep the whole target image, one
  // sweep per host, and what one sweep read has left the cache (1 MB per image at 512x512) before the next
  // sweep reads near it; the hosts' points often land near each other (their strongest gradients are the
  // same edges), and row by row those reads follow each other. The window adjustment 155 -> 122 ms on the
  // armadillo's benchmark window (medians of three alternating runs). Each residual's sample is written to
  // its own slot, so the order changes no result. The gradients with the values when `with_gradient`.
  auto read_images = [&](const ProjectedList& visible, int t, bool with_gradient, std::vector<Sampled>* sampled) {
    const size_t n = visible.size();
    sampled->resize(n);
    const int rows = limg->front().rows;
    auto row_of = [&](size_t k) {
      return static_cast<size_t>(std::clamp(static_cast<int>(visible[k].px.y()), 0, rows - 1));
    };
    std::vector<uint32_t> row_start(static_cast<size_t>(rows) + 1, 0), order(n);
    for (size_t k = 0; k < n; ++k) ++row_start[row_of(k) + 1];
    for (int r = 0; r < rows; ++r) row_start[static_cast<size_t>(r) + 1] += row_start[static_cast<size_t>(r)];
    for (size_t k = 0; k < n; ++k) order[row_start[row_of(k)]++] = static_cast<uint32_t>(k);
    for (size_t q = 0; q < n; ++q) {
      if (q + kPrefetchAhead < n) {
        const Projected& ahead = visible[order[q + kPrefetchAhead]];
        PrefetchSample(image_of(*limg, ahead.point, t), ahead.px.x(), ahead.px.y());
      }
      const size_t k = order[q];
      const cv::Mat& image = image_of(*limg, visible[k].point, t);
      const Eigen::Vector2d& px = visible[k].px;
      Sampled& sk = (*sampled)[k];
      sk.ok = with_gradient ? SampleWithGradient(image, px.x(), px.y(), &sk.value, &sk.g)
                            : SampleValue(image, px.x(), px.y(), &sk.value);
    }
    image_samples.fetch_add(static_cast<long long>(n), std::memory_order_relaxed);
  };

  // With a pool: how many workers take targets in parallel, and each worker's scratch. Each target's
  // terms are kept apart and summed target by target afterwards, in the one-thread order.
  const int workers = pool != nullptr ? std::max(1, std::min(pool->num_threads(), num_kf)) : 1;
  std::vector<ProjectedList> worker_visible;
  std::vector<std::vector<Sampled>> worker_sampled(static_cast<size_t>(workers));
  std::vector<std::vector<Eigen::Matrix3d>> worker_target_from_host(
      static_cast<size_t>(workers), std::vector<Eigen::Matrix3d>(static_cast<size_t>(num_kf)));
  if (workers > 1)
    for (int w = 0; w < workers; ++w) worker_visible.emplace_back(static_cast<size_t>(num_points));
  // Runs fn(t, worker) for every target, each worker pulling the next target (its own scratch).
  auto for_each_target_parallel = [&](const auto& fn) {
    std::atomic<int> next{0};
    pool->ParallelFor(0, workers, [&](std::ptrdiff_t w) {
      for (int t = next.fetch_add(1); t < num_kf; t = next.fetch_add(1)) fn(t, static_cast<int>(w));
    });
  };
  // Runs fn(i) for every point: with workers in chunks on the pool (fn writes point i's entries alone).
  auto for_each_point = [&](const auto& fn) {
    if (workers <= 1) {
      for (int i = 0; i < num_points; ++i) fn(i);
      return;
    }
    const int chunk = 256;
    pool->ParallelFor(0, (num_points + chunk - 1) / chunk, [&](std::ptrdiff_t c) {
      const int i1 = std::min(num_points, static_cast<int>(c + 1) * chunk);
      for (int i = static_cast<int>(c) * chunk; i < i1; ++i) fn(i);
    });
  };

  // The cost, target by target (each target's image read in about raster order).
  std::vector<Eigen::Vector3d> eval_world(static_cast<size_t>(num_points));  // scratch
  ProjectedList eval_visible(static_cast<size_t>(num_points));               // scratch: one target's
  std::vector<Sampled> eval_values;  // scratch: their image values (the gradients unused)
  // Target t's residuals at poses ps and inverse depths rs: residual(point, |scaled residual|) for each, in
  // the order they are summed. With `store` (linearise_from_evaluation) the projections and samples go
  // there, with the gradients.
  auto evaluate_target = [&](const std::vector<Pose>& ps, const std::vector<double>& rs, int t, ProjectedList* vis,
                             std::vector<Sampled>* values, TargetSamples* store, const auto& residual) {
    const Eigen::Matrix3d rt_t = ps[static_cast<size_t>(t)].rotation.transpose();
    const Eigen::Vector3d& c_t = ps[static_cast<size_t>(t)].centre;
    if (store != nullptr) {
      vis = &store->visible;
      values = &store->sampled;
    }
    // The projections first, then the image reads (prefetched kPrefetchAhead residuals ahead).
    collect_visible(
        t, rt_t, c_t, eval_world,
        [&](int i) { return rs[static_cast<size_t>(i)] > 0 && !std::isnan(lint[static_cast<size_t>(i)]); }, vis);
    // The image reads first, then the residuals.
    read_images(*vis, t, /*with_gradient=*/store != nullptr, values);
    for (size_t k = 0; k < vis->size(); ++k) {
      if (!(*values)[k].ok) continue;
      const int i = (*vis)[k].point;
      const Eigen::Vector3d& pt = (*vis)[k].pt;
      const double value = (*values)[k].value;
      double expected = lint[static_cast<size_t>(i)];
      if (relit_point[static_cast<size_t>(i)]) {
        if (!normal_rho[static_cast<size_t>(i)].allFinite()) continue;
        expected = relit_prediction(ps, i, t, pt, normal_rho[static_cast<size_t>(i)], metres);
      }
      residual(i, residual_scale[static_cast<size_t>(i)] * std::abs(value - expected));
    }
  };
  struct EvalTerm {
    int point;
    double e;
  };
  std::vector<std::vector<EvalTerm>> eval_terms(workers > 1 ? static_cast<size_t>(num_kf) : 0);
  // The residuals above options.outlier are listed in *over (point * num_kf + target) as they are summed:
  // the outlier test after the first solve then reads the current state's list instead of projecting and
  // sampling every residual again (the same residuals, values and test).
  DirectBaSummary summary;
  // linearise_from_evaluation: two slots of per-target samples, the current state's (valid when its
  // evaluation read the images of the current level) and a trial's.
  const bool reuse_samples = options.linearise_from_evaluation && !use_relit;
  std::vector<TargetSamples> sample_slots[2];
  if (reuse_samples)
    for (std::vector<TargetSamples>& slot : sample_slots) slot.resize(static_cast<size_t>(num_kf));
  int current_slot = 0;
  bool current_samples_valid = false;
  // The cost at (ps, rs); with slot >= 0 (and reuse_samples) its reads are kept in sample_slots[slot].
  auto evaluate = [&](const std::vector<Pose>& ps, const std::vector<double>& rs, int* count, double* sq,
                      std::vector<int>* over, int slot) {
    ++summary.evaluations;
    auto store_of = [&](int t) -> TargetSamples* {
      return reuse_samples && slot >= 0 ? &sample_slots[slot][static_cast<size_t>(t)] : nullptr;
    };
    double cost = 0;
    *count = 0;
    *sq = 0;
    over->clear();
    for_each_point([&](int i) {
      if (rs[static_cast<size_t>(i)] > 0) {
        eval_world[static_cast<size_t>(i)] = world_point(ps, i, rs[static_cast<size_t>(i)]);
        if (relit_point[static_cast<size_t>(i)] && !std::isnan(lint[static_cast<size_t>(i)]))
          normal_rho[static_cast<size_t>(i)] = implied_normal(ps, i, rs[static_cast<size_t>(i)], metres);
      }
    });
    auto add = [&](int t, int i, double e) {
      cost += HuberCost(e, options.huber);
      *sq += e * e;
      ++*count;
      if (e > options.outlier) over->push_back(i * num_kf + t);
    };
    if (workers > 1) {
      for_each_target_parallel([&](int t, int w) {
        std::vector<EvalTerm>& terms = eval_terms[static_cast<size_t>(t)];
        terms.clear();
        evaluate_target(ps, rs, t, &worker_visible[static_cast<size_t>(w)], &worker_sampled[static_cast<size_t>(w)],
                        store_of(t), [&](int i, double e) {
                          terms.push_back({i, e});
                        });
      });
      for (int t = 0; t < num_kf; ++t)
        for (const EvalTerm& term : eval_terms[static_cast<size_t>(t)]) add(t, term.point, term.e);
    } else {
      for (int t = 0; t < num_kf; ++t)
        evaluate_target(ps, rs, t, &eval_visible, &eval_values, store_of(t), [&](int i, double e) { add(t, i, e); });
    }
    const double along = baseline.dot(ps[1].centre - centre1_initial);
    return cost + 0.5 * gauge_weight * along * along;
  };

  int count = 0;
  double sq = 0;
  std::vector<int> over, trial_over;  // the current state's residuals above the outlier threshold; a trial's
  // Its reads serve the first linearisation when that is at this level (pyramid_levels 1).
  const double initial_cost = evaluate(poses, rho, &count, &sq, &over, levels == 1 ? current_slot : -1);
  current_samples_valid = reuse_samples && levels == 1;
  summary.initial_rms = count > 0 ? std::sqrt(sq / count) : 0;

  // Per point: the Hessian of its inverse depth, its gradient, and its coupling with the poses.
  std::vector<double> hpp(static_cast<size_t>(num_points)), bp(static_cast<size_t>(num_points));
  std::vector<Eigen::VectorXd> hcp(static_cast<size_t>(num_points), Eigen::VectorXd::Zero(dim));
  // touched[point * num_kf + k]: the point's coupling hcp has a (possibly) non-zero segment for pose k
  // (a residual hosted or observed there); it is exactly zero elsewhere.
  std::vector<uint8_t> touched(static_cast<size_t>(num_points) * num_kf, 0);
  std::vector<int> segments;  // scratch: the offsets of a point's touched segments, ascending
  std::vector<PairSums> pairs(static_cast<size_t>(num_kf * num_kf));    // [target * num_kf + host]
  std::vector<Eigen::Vector3d> world(static_cast<size_t>(num_points));  // scratch: the points in the world
  std::vector<uint8_t> point_ok(static_cast<size_t>(num_points));
  ProjectedList lin_visible(static_cast<size_t>(num_points));  // scratch: one target's residuals
  std::vector<Sampled> lin_sampled;                            // scratch: their image values and gradients
  std::vector<Eigen::Matrix3d> lin_target_from_host(static_cast<size_t>(num_kf));
  // With workers: each target's residual terms of its points' sums in its order (see linearise_target),
  // and per target and point the index of the point's term there (-1: none).
  struct LinTerm {
    int host;
    double h, b, e;
    Eigen::Matrix<double, 6, 1> target_segment, host_segment;
  };
  // Relit with K estimated, with workers: each target's residual terms of log K's sums, in its order.
  struct KTerm {
    int point, host;
    double h_kk, b_k, h_pk;
    Eigen::Matrix<double, 6, 1> target_segment, host_segment;  // of h_ck
  };
  std::vector<std::vector<KTerm>> k_terms(workers > 1 && estimate_k ? static_cast<size_t>(num_kf) : 0);
  std::vector<std::vector<LinTerm>> lin_terms(workers > 1 ? static_cast<size_t>(num_kf) : 0);
  std::vector<int> lin_term_index(workers > 1 ? static_cast<size_t>(num_kf) * num_points : 0);
  std::vector<double> hinv0(static_cast<size_t>(num_points)), hinv(static_cast<size_t>(num_points));
  std::vector<double> h_pk(static_cast<size_t>(num_points), 0.0);  // relit, K estimated
  for (int level = levels - 1; level >= 0; --level) {
    const double f = std::ldexp(1.0, -level);
    lcam = cam;
    lcam.width = cam.width >> level;
    lcam.height = cam.height >> level;
    lcam.fx = cam.fx * f;
    lcam.fy = cam.fy * f;
    lcam.cx = (cam.cx + 0.5) * f - 0.5;
    lcam.cy = (cam.cy + 0.5) * f - 0.5;
    limg = &pyramid[static_cast<size_t>(level)];
    if (levels > 1) current_samples_valid = false;  // read at another level (or none)
    for (int i = 0; i < num_points; ++i) {
      const DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
      double value = p.intensity;
      Eigen::Vector2d g;
      if (level > 0 && !SampleWithGradient((*limg)[static_cast<size_t>(p.host)], (p.u + 0.5) * f - 0.5,
                                           (p.v + 0.5) * f - 0.5, &value, &g))
        value = std::numeric_limits<double>::quiet_NaN();
      lint[static_cast<size_t>(i)] = static_cast<float>(value);
    }
    const int rounds = level == 0 ? 2 : 1;
    for (int round = 0; round < rounds; ++round) {
      double lambda = 1e-3;
      double nu = 2;  // gain_ratio_damping: lambda's factor after the next rejected step
      // The first solve at full resolution without coarser levels starts where initial_cost was taken
      // (the same poses, depths, intensities and residuals). A solve after which no outlier test follows
      // takes its starting cost from its first linearisation, which reads the same residuals in the same
      // order (not with the relit residual, whose linearisation leaves out more points).
      const bool cost_from_linearisation = !use_relit && (round > 0 || level > 0);
      double cost = 0.0;
      if (levels == 1 && round == 0) {
        cost = initial_cost;
      } else if (!cost_from_linearisation) {
        cost = evaluate(poses, rho, &count, &sq, &over, current_slot);
        current_samples_valid = reuse_samples;
      }
      for (int it = 0; it < options.max_iterations; ++it) {
        ++summary.iterations;
        // The cost at this linearisation, summed with it (cost_from_linearisation, first iteration).
        const bool sum_cost = cost_from_linearisation && it == 0;
        double lin_cost = 0, lin_sq = 0;
        int lin_count = 0;
        Eigen::MatrixXd hcc = Eigen::MatrixXd::Zero(dim, dim);
        Eigen::VectorXd bc = Eigen::VectorXd::Zero(dim);
        // Relit with K estimated: log K's Hessian, gradient and couplings with the poses and the points.
        double h_kk = 0, b_k = 0;
        Eigen::VectorXd h_ck = Eigen::VectorXd::Zero(dim);
        std::fill(h_pk.begin(), h_pk.end(), 0.0);
        std::fill(hpp.begin(), hpp.end(), 0.0);
        std::fill(bp.begin(), bp.end(), 0.0);
        // The points' world positions; then the residuals target by target (each target's image is read
        // in about raster order: the points are in their hosts' raster order).
        for_each_point([&](int i) {
          hcp[static_cast<size_t>(i)].setZero();
          std::fill(&touched[static_cast<size_t>(i) * num_kf], &touched[static_cast<size_t>(i) * num_kf] + num_kf, 0);
          const double r = rho[static_cast<size_t>(i)];
          point_ok[static_cast<size_t>(i)] = r > 0 && !std::isnan(lint[static_cast<size_t>(i)]);
          if (point_ok[static_cast<size_t>(i)]) world[static_cast<size_t>(i)] = world_point(poses, i, r);
          if (point_ok[static_cast<size_t>(i)] && relit_point[static_cast<size_t>(i)]) {
            normal_rho[static_cast<size_t>(i)] = implied_normal(poses, i, r, metres);
            normal_rho_drho[static_cast<size_t>(i)] =
                (implied_normal(poses, i, r * (1 + 1e-5), metres) - implied_normal(poses, i, r * (1 - 1e-5), metres)) /
                (2e-5 * r);
            point_ok[static_cast<size_t>(i)] =
                normal_rho[static_cast<size_t>(i)].allFinite() && normal_rho_drho[static_cast<size_t>(i)].allFinite();
            if (estimate_k && point_ok[static_cast<size_t>(i)]) {
              normal_rho_kp[static_cast<size_t>(i)] = implied_normal(poses, i, r, metres * std::exp(log_k_step));
              normal_rho_km[static_cast<size_t>(i)] = implied_normal(poses, i, r, metres * std::exp(-log_k_step));
              point_ok[static_cast<size_t>(i)] = normal_rho_kp[static_cast<size_t>(i)].allFinite() &&
                                                 normal_rho_km[static_cast<size_t>(i)].allFinite();
            }
          }
        });
        // Target t's residuals. Its pairs' sums are written here (no other target writes them); each
        // residual's terms of its point's sums (the Hessian and gradient of the inverse depth, the target's
        // and the host's segments of the coupling) and its cost go to point_terms(point, host, target, h, b,
        // target segment, host segment, |scaled residual|). With workers they are kept per target and
        // added afterwards: written here, the points' sums of two targets would share cache lines.
        // With K estimated, each residual's terms of log K's sums go to k_term(point, host, target, h_kk, b_k,
        // h_ck's target segment, its host segment, h_pk) (the same way).
        auto linearise_target = [&](int t, ProjectedList& visible, std::vector<Sampled>& sampled,
                                    std::vector<Eigen::Matrix3d>& target_from_host, const auto& point_terms,
                                    const auto& k_term) {
          const Pose& tp = poses[static_cast<size_t>(t)];
          const Eigen::Matrix3d rt_t = tp.rotation.transpose();
          // d (point in target) / d (point in host camera, host units), per host: R_t^T s_h R_h.
          for (int k = 0; k < num_kf; ++k)
            target_from_host[static_cast<size_t>(k)] =
                rt_t * (poses[static_cast<size_t>(k)].scale * poses[static_cast<size_t>(k)].rotation);
          // With the current state's evaluation kept (linearise_from_evaluation), its projections and reads
          // (in the same order as below; residuals dropped as outliers since then are skipped).
          const bool from_evaluation = current_samples_valid;
          const ProjectedList& vis =
              from_evaluation ? sample_slots[current_slot][static_cast<size_t>(t)].visible : visible;
          const std::vector<Sampled>& smp =
              from_evaluation ? sample_slots[current_slot][static_cast<size_t>(t)].sampled : sampled;
          if (!from_evaluation) {
            // The projections first, then the image reads (prefetched kPrefetchAhead residuals ahead).
            collect_visible(
                t, rt_t, tp.centre, world, [&](int i) { return point_ok[static_cast<size_t>(i)] != 0; }, &visible);
            read_images(visible, t, /*with_gradient=*/true, &sampled);
          }
          for (size_t k = 0; k < vis.size(); ++k) {
            if (!smp[k].ok) continue;
            const int i = vis[k].point;
            if (from_evaluation && !active[static_cast<size_t>(i) * num_kf + t]) continue;
            const DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
            const Eigen::Vector3d& pt = vis[k].pt;
            const double value = smp[k].value;
            const Eigen::Vector2d& g = smp[k].g;
            const double r = rho[static_cast<size_t>(i)];
            const bool relit_i = relit_point[static_cast<size_t>(i)];
            const double res =
                value - (relit_i ? relit_prediction(poses, i, t, pt, normal_rho[static_cast<size_t>(i)], metres)
                                 : static_cast<double>(lint[static_cast<size_t>(i)]));
            // The residual scaled by s: Huber on s |res|, and s^2 in the weight of the unscaled rows.
            const double s_i = residual_scale[static_cast<size_t>(i)];
            const double e = s_i * std::abs(res);
            const double w = (e <= options.huber ? 1.0 : options.huber / e) * s_i * s_i;
            const double iz = 1.0 / pt.z();
            Eigen::Matrix<double, 2, 3> du_dp;
            du_dp << lcam.fx * iz, 0, -lcam.fx * pt.x() * iz * iz, 0, lcam.fy * iz, -lcam.fy * pt.y() * iz * iz;
            Eigen::RowVector3d j_pt = g.transpose() * du_dp;  // d residual / d point in target
            // Relit: the prediction moves with the point in the target (through the lights' irradiance and
            // directions) and with rho n seen from the target, n_t = R_t^T R_h m; a right rotation of the
            // target turns n_t by Skew(n_t), one of the host by -R_th Skew(m) (which is Skew(n_t) times
            // DirectBaHostFromTarget's rotation block, so the pair sums below still hold), and rho moves
            // m through the host point's lighting.
            Eigen::RowVector3d j_n = Eigen::RowVector3d::Zero();  // d residual / d n_t
            Eigen::Vector3d n_t = Eigen::Vector3d::Zero();
            Eigen::Matrix3d r_th = Eigen::Matrix3d::Identity();
            if (relit_i) {
              const Eigen::Vector3d& m = normal_rho[static_cast<size_t>(i)];
              r_th = rt_t * poses[static_cast<size_t>(p.host)].rotation;
              n_t = r_th * m;
              const Eigen::Vector3d x = metres * pt;
              Eigen::RowVector3d dpred_dx = Eigen::RowVector3d::Zero();
              for (int l = 0; l < 3; ++l) {
                Eigen::Vector3d to_light;
                double irradiance;
                relit.rig->lights[static_cast<size_t>(l)].Illuminate(x, &to_light, &irradiance);
                if (n_t.dot(to_light) > 0)
                  j_n -= grey_of_light(l) * relit.albedo_colour(l) * irradiance * to_light.transpose();
              }
              const double hx = 1e-6 * std::max(1e-3, x.norm());
              for (int c = 0; c < 3; ++c) {
                Eigen::Vector3d d = Eigen::Vector3d::Zero();
                d(c) = hx / metres;
                dpred_dx(c) = (relit_prediction(poses, i, t, pt + d, m, metres) -
                               relit_prediction(poses, i, t, pt - d, m, metres)) /
                              (2 * hx / metres);
              }
              j_pt -= dpred_dx;
            }
            // Target pose: right rotation perturbation and centre.
            Eigen::Matrix<double, 1, 6> j_target;
            // j Skew(v) is the cross product j x v (the same products and sums; Skew's zeros skipped).
            j_target.head<3>() = j_pt.cross(pt.transpose());
            if (relit_i) j_target.head<3>() += j_n * Skew(n_t);
            j_target.tail<3>() = -j_pt * rt_t;
            // Host pose: x = c_h + s_h R_h exp(w) q with q = ray / rho; and rho.
            const Eigen::RowVector3d j_q = j_pt * target_from_host[static_cast<size_t>(p.host)];
            const Eigen::Vector3d& ray_i = ray[static_cast<size_t>(i)];
            Eigen::Matrix<double, 1, 6> j_host;
            j_host.head<3>() = -j_q.cross((ray_i / r).transpose());
            j_host.tail<3>() = -j_target.tail<3>();
            double j_rho = -j_q.dot(ray_i) / (r * r);
            if (relit_i) {
              j_host.head<3>() -= j_n * r_th * Skew(normal_rho[static_cast<size_t>(i)]);
              j_rho += j_n.dot(r_th * normal_rho_drho[static_cast<size_t>(i)]);
            }
            if (estimate_k && relit_i) {
              // d residual / d log K: the target's lighting and the host's implied normal both move with K.
              const double j_k = -(relit_prediction(poses, i, t, pt, normal_rho_kp[static_cast<size_t>(i)],
                                                    metres * std::exp(log_k_step)) -
                                   relit_prediction(poses, i, t, pt, normal_rho_km[static_cast<size_t>(i)],
                                                    metres * std::exp(-log_k_step))) /
                                 (2 * log_k_step);
              Eigen::Matrix<double, 6, 1> k_target = Eigen::Matrix<double, 6, 1>::Zero();
              if (t > 0) k_target = w * j_target.transpose() * j_k;
              Eigen::Matrix<double, 6, 1> k_host = Eigen::Matrix<double, 6, 1>::Zero();
              if (p.host > 0) k_host = w * j_host.transpose() * j_k;
              k_term(i, p.host, t, w * j_k * j_k, w * j_k * res, k_target, k_host, w * j_rho * j_k);
            }
            const int kh = p.host, kt = t;
            // The pose blocks are accumulated per (host, target) pair in the target's parameters alone
            // (lower triangle), and mapped to the host's after the loop (DirectBaHostFromTarget). A target's
            // pairs lie together (no two workers write the same ones).
            PairSums& pair = pairs[static_cast<size_t>(kt * num_kf + kh)];
            const Eigen::Matrix<double, 1, 6> wj = w * j_target;
            for (int c = 0; c < 6; ++c)
              for (int rr = c; rr < 6; ++rr) pair.h(rr, c) += wj(rr) * j_target(c);
            pair.b += wj.transpose() * res;
            pair.used = true;
            Eigen::Matrix<double, 6, 1> target_segment = Eigen::Matrix<double, 6, 1>::Zero();
            if (kt > 0) target_segment = wj.transpose() * j_rho;
            Eigen::Matrix<double, 6, 1> host_segment = Eigen::Matrix<double, 6, 1>::Zero();
            if (kh > 0) host_segment = w * j_host.transpose() * j_rho;
            point_terms(i, kh, kt, w * j_rho * j_rho, w * j_rho * res, target_segment, host_segment, e);
          }
        };
        auto add_cost = [&](double e) {
          if (sum_cost) {
            lin_cost += HuberCost(e, options.huber);
            lin_sq += e * e;
            ++lin_count;
          }
        };
        auto add_k_terms = [&](int i, int kh, int kt, double hk, double bk,
                               const Eigen::Matrix<double, 6, 1>& target_segment,
                               const Eigen::Matrix<double, 6, 1>& host_segment, double hpk) {
          h_kk += hk;
          b_k += bk;
          if (kt > 0) h_ck.segment<6>(6 * (kt - 1)) += target_segment;
          if (kh > 0) h_ck.segment<6>(6 * (kh - 1)) += host_segment;
          h_pk[static_cast<size_t>(i)] += hpk;
        };
        auto add_point_terms = [&](int i, int kh, int kt, double h, double b,
                                   const Eigen::Matrix<double, 6, 1>& target_segment,
                                   const Eigen::Matrix<double, 6, 1>& host_segment) {
          hpp[static_cast<size_t>(i)] += h;
          bp[static_cast<size_t>(i)] += b;
          // The target's segment has this one term (one residual per point and target), the host's one per
          // target.
          if (kt > 0) {
            hcp[static_cast<size_t>(i)].segment<6>(6 * (kt - 1)) += target_segment;
            touched[static_cast<size_t>(i) * num_kf + kt] = 1;
          }
          if (kh > 0) {
            hcp[static_cast<size_t>(i)].segment<6>(6 * (kh - 1)) += host_segment;
            touched[static_cast<size_t>(i) * num_kf + kh] = 1;
          }
        };
        if (workers > 1) {
          for_each_target_parallel([&](int t, int w) {
            std::vector<LinTerm>& terms = lin_terms[static_cast<size_t>(t)];
            int* index = &lin_term_index[static_cast<size_t>(t) * num_points];
            terms.clear();
            std::fill(index, index + num_points, -1);
            std::vector<KTerm>* kt_terms = estimate_k ? &k_terms[static_cast<size_t>(t)] : nullptr;
            if (kt_terms != nullptr) kt_terms->clear();
            linearise_target(
                t, worker_visible[static_cast<size_t>(w)], worker_sampled[static_cast<size_t>(w)],
                worker_target_from_host[static_cast<size_t>(w)],
                [&](int i, int kh, int /*kt: t*/, double h, double b, const Eigen::Matrix<double, 6, 1>& target_segment,
                    const Eigen::Matrix<double, 6, 1>& host_segment, double e) {
                  index[i] = static_cast<int>(terms.size());
                  terms.push_back({kh, h, b, e, target_segment, host_segment});
                },
                [&](int i, int kh, int /*kt: t*/, double hk, double bk, const Eigen::Matrix<double, 6, 1>& k_target,
                    const Eigen::Matrix<double, 6, 1>& k_host, double hpk) {
                  kt_terms->push_back({i, kh, hk, bk, hpk, k_target, k_host});
                });
          });
          // The cost and log K's sums in the one-thread order (target by target); each point's sums target by
          // target, as the one-thread order adds them, in parallel over the points.
          for (int t = 0; t < num_kf; ++t)
            for (const LinTerm& term : lin_terms[static_cast<size_t>(t)]) add_cost(term.e);
          if (estimate_k)
            for (int t = 0; t < num_kf; ++t)
              for (const KTerm& term : k_terms[static_cast<size_t>(t)])
                add_k_terms(term.point, term.host, t, term.h_kk, term.b_k, term.target_segment, term.host_segment,
                            term.h_pk);
          const int chunk = 256;
          pool->ParallelFor(0, (num_points + chunk - 1) / chunk, [&](std::ptrdiff_t c) {
            const int i1 = std::min(num_points, static_cast<int>(c + 1) * chunk);
            for (int i = static_cast<int>(c) * chunk; i < i1; ++i)
              for (int t = 0; t < num_kf; ++t) {
                const int k = lin_term_index[static_cast<size_t>(t) * num_points + i];
                if (k < 0) continue;
                const LinTerm& term = lin_terms[static_cast<size_t>(t)][static_cast<size_t>(k)];
                add_point_terms(i, term.host, t, term.h, term.b, term.target_segment, term.host_segment);
              }
          });
        } else {
          for (int t = 0; t < num_kf; ++t)
            linearise_target(
                t, lin_visible, lin_sampled, lin_target_from_host,
                [&](int i, int kh, int kt, double h, double b, const Eigen::Matrix<double, 6, 1>& target_segment,
                    const Eigen::Matrix<double, 6, 1>& host_segment, double e) {
                  add_cost(e);
                  add_point_terms(i, kh, kt, h, b, target_segment, host_segment);
                },
                add_k_terms);
        }
        // Each pair's sums, in the target's parameters, and mapped to the host's: j_host = j_target A.
        for (int kh = 0; kh < num_kf; ++kh)
          for (int kt = 0; kt < num_kf; ++kt) {
            PairSums& pair = pairs[static_cast<size_t>(kt * num_kf + kh)];
            if (!pair.used) continue;
            const Eigen::Matrix<double, 6, 6> h_tt = pair.h.selfadjointView<Eigen::Lower>();
            const Eigen::Matrix<double, 6, 6> a =
                DirectBaHostFromTarget(poses[static_cast<size_t>(kh)].rotation, poses[static_cast<size_t>(kh)].centre,
                                       poses[static_cast<size_t>(kt)].rotation, poses[static_cast<size_t>(kt)].centre);
            const int oh = 6 * (kh - 1), ot = 6 * (kt - 1);
            if (kt > 0) {
              hcc.block<6, 6>(ot, ot) += h_tt;
              bc.segment<6>(ot) += pair.b;
            }
            if (kh > 0) {
              const Eigen::Matrix<double, 6, 6> at_h = a.transpose() * h_tt;
              hcc.block<6, 6>(oh, oh) += at_h * a;
              bc.segment<6>(oh) += a.transpose() * pair.b;
              // Off the diagonal only the block below it: the solve reads the lower triangle alone.
              if (kt > 0) {
                if (oh > ot) hcc.block<6, 6>(oh, ot) += at_h;
                else hcc.block<6, 6>(ot, oh) += at_h.transpose();
              }
            }
            pair = PairSums();
          }
        if (sum_cost) {
          const double along = baseline.dot(poses[1].centre - centre1_initial);
          cost = lin_cost + 0.5 * gauge_weight * along * along;
          count = lin_count;
          sq = lin_sq;
        }
        hcc.block<3, 3>(3, 3) += gauge_weight * baseline * baseline.transpose();
        bc.segment<3>(3) += gauge_weight * baseline * baseline.dot(poses[1].centre - centre1_initial);

        // The points' Schur complement at lambda = 0; damping scales every point's 1 / hpp by 1 / (1 + lambda),
        // so each attempt below only rescales it.
        Eigen::MatrixXd schur = Eigen::MatrixXd::Zero(dim, dim);  // lower block triangle
        Eigen::VectorXd schur_b = Eigen::VectorXd::Zero(dim);
        for (int i = 0; i < num_points; ++i) {
          const double h = hpp[static_cast<size_t>(i)];
          hinv0[static_cast<size_t>(i)] = h > 1e-12 ? 1.0 / h : 0.0;
          if (hinv0[static_cast<size_t>(i)] == 0) continue;
          const Eigen::VectorXd& hc = hcp[static_cast<size_t>(i)];
          // schur -= hc hc^T / h over the touched segments' blocks only (hc is zero elsewhere). On one thread:
          // split by block columns between two threads (each block still summing its points in order) a
          // 24-keyframe adjustment took 3.15 instead of 2.79 s (both threads read every point's coupling).
          const double alpha = -hinv0[static_cast<size_t>(i)];
          segments.clear();
          for (int k = 1; k < num_kf; ++k)
            if (touched[static_cast<size_t>(i) * num_kf + k]) segments.push_back(6 * (k - 1));
          for (size_t cb = 0; cb < segments.size(); ++cb) {
            const Eigen::Matrix<double, 6, 1> scaled = alpha * hc.segment<6>(segments[cb]);
            for (size_t rb = cb; rb < segments.size(); ++rb)
              schur.block<6, 6>(segments[rb], segments[cb]).noalias() +=
                  hc.segment<6>(segments[rb]) * scaled.transpose();
            schur_b.segment<6>(segments[cb]) += scaled * bp[static_cast<size_t>(i)];
          }
        }
        // Relit with K estimated: log K's row of the Schur complement (every point couples to it).
        double schur_kk = 0, schur_bk = 0;
        Eigen::VectorXd schur_ck = Eigen::VectorXd::Zero(estimate_k ? dim : 0);
        if (estimate_k) {
          for (int i = 0; i < num_points; ++i) {
            const double hi = hinv0[static_cast<size_t>(i)], pk = h_pk[static_cast<size_t>(i)];
            if (hi == 0 || pk == 0) continue;
            schur_kk -= hi * pk * pk;
            schur_bk -= hi * pk * bp[static_cast<size_t>(i)];
            schur_ck.noalias() -= (hi * pk) * hcp[static_cast<size_t>(i)];
          }
        }
        bool accepted = false;
        for (int attempt = 0; attempt < 8 && !accepted; ++attempt) {
          const double damp = 1.0 / (1 + lambda);
          Eigen::MatrixXd s = hcc + damp * schur;
          const Eigen::VectorXd b = bc + damp * schur_b;
          for (int i = 0; i < num_points; ++i) hinv[static_cast<size_t>(i)] = damp * hinv0[static_cast<size_t>(i)];
          for (int d = 0; d < dim; ++d) s(d, d) += lambda * std::max(1e-6, hcc(d, d));
          Eigen::VectorXd dc;
          double d_log_k = 0;
          if (estimate_k) {
            // The poses' system bordered by log K (lower triangle filled).
            Eigen::MatrixXd full = Eigen::MatrixXd::Zero(dim + 1, dim + 1);
            full.topLeftCorner(dim, dim) = s.selfadjointView<Eigen::Lower>();
            full.block(dim, 0, 1, dim) = (h_ck + damp * schur_ck).transpose();
            full.block(0, dim, dim, 1) = h_ck + damp * schur_ck;
            full(dim, dim) = (h_kk + damp * schur_kk) + lambda * std::max(1e-6, h_kk);
            Eigen::VectorXd full_b(dim + 1);
            full_b << b, b_k + damp * schur_bk;
            const Eigen::VectorXd sol = full.ldlt().solve(-full_b);
            dc = sol.head(dim);
            d_log_k = std::clamp(sol(dim), -0.2, 0.2);
          } else {
            dc = s.selfadjointView<Eigen::Lower>().ldlt().solve(-b);
          }
          if (!dc.allFinite() || !std::isfinite(d_log_k)) {
            lambda *= 10;
            continue;
          }
          std::vector<Pose> np = poses;
          for (int k = 1; k < num_kf; ++k) {
            const Eigen::Matrix<double, 6, 1> d = dc.segment<6>(6 * (k - 1));
            np[static_cast<size_t>(k)].rotation =
                poses[static_cast<size_t>(k)].rotation * ExpSo3(d.head<3>()).toRotationMatrix();
            np[static_cast<size_t>(k)].centre = poses[static_cast<size_t>(k)].centre + d.tail<3>();
          }
          std::vector<double> nr = rho;
          for (int i = 0; i < num_points; ++i) {
            if (hinv[static_cast<size_t>(i)] == 0) continue;
            const double d =
                -hinv[static_cast<size_t>(i)] * (bp[static_cast<size_t>(i)] + hcp[static_cast<size_t>(i)].dot(dc) +
                                                 (estimate_k ? h_pk[static_cast<size_t>(i)] * d_log_k : 0.0));
            // Keep the inverse depth positive (a step to <= 0 is halved towards it).
            nr[static_cast<size_t>(i)] = rho[static_cast<size_t>(i)] + d > 0.2 * rho[static_cast<size_t>(i)]
                                             ? rho[static_cast<size_t>(i)] + d
                                             : 0.2 * rho[static_cast<size_t>(i)];
          }
          int nc = 0;
          double nsq = 0;
          const double k_before = metres;
          metres = k_before * std::exp(d_log_k);  // evaluate at the trial K (restored if rejected)
          const double ncost = evaluate(np, nr, &nc, &nsq, &trial_over, 1 - current_slot);
          if (!(ncost < cost)) metres = k_before;
          if (ncost < cost) {
            const double decrease = (cost - ncost) / std::max(1e-300, cost);
            // gain_ratio_damping: the decrease the damped model predicts over the step d taken (a step
            // rejected needs none), (lambda d^T D d - g^T d) / 2 (g: the gradient; D: the damping's diagonal,
            // max(1e-6, hcc) for the poses, hpp for the points, max(1e-6, h_kk) for log K).
            double predicted = 0;
            if (options.gain_ratio_damping) {
              for (int d = 0; d < dim; ++d)
                predicted += lambda * std::max(1e-6, hcc(d, d)) * dc(d) * dc(d) - bc(d) * dc(d);
              for (int i = 0; i < num_points; ++i) {
                const double d = nr[static_cast<size_t>(i)] - rho[static_cast<size_t>(i)];
                predicted += lambda * hpp[static_cast<size_t>(i)] * d * d - bp[static_cast<size_t>(i)] * d;
              }
              if (estimate_k) predicted += lambda * std::max(1e-6, h_kk) * d_log_k * d_log_k - b_k * d_log_k;
              predicted *= 0.5;
            }
            const double gain = predicted > 0 ? (cost - ncost) / predicted : 0.0;
            poses.swap(np);
            rho.swap(nr);
            cost = ncost;
            count = nc;  // count, sq and over: always the current state's
            sq = nsq;
            over.swap(trial_over);
            current_slot = 1 - current_slot;  // the trial's reads are the current state's now
            current_samples_valid = reuse_samples;
            if (options.gain_ratio_damping) {
              const double c = 2 * gain - 1;
              lambda = std::max(1e-7, lambda * std::max(1.0 / 3, 1 - c * c * c));
              nu = 2;
            } else {
              lambda = std::max(1e-7, lambda / 3);
            }
            accepted = true;
            if (decrease < options.function_tolerance) it = options.max_iterations;
          } else if (options.gain_ratio_damping) {
            lambda *= nu;
            nu *= 2;
          } else {
            lambda *= 5;
          }
        }
        if (!accepted) break;
      }
      if (round + 1 == rounds) break;
      // Drop the residuals above the outlier threshold (listed by the current state's evaluation), then
      // solve again.
      for (int idx : over) active[static_cast<size_t>(idx)] = 0;
    }
  }
  // count and sq are the final state's already (from its evaluation at the start of the last round or
  // when its step was accepted; nothing it depends on has changed since): no evaluation of its own.
  summary.final_rms = count > 0 ? std::sqrt(sq / count) : 0;
  summary.image_samples = image_samples.load();
  summary.residuals = count;
  for (int k = 1; k < num_kf; ++k) {
    Sim3d& out = problem->world_from_keyframe[static_cast<size_t>(k)];
    out.rotation = Eigen::Quaterniond(poses[static_cast<size_t>(k)].rotation).normalized();
    out.translation = poses[static_cast<size_t>(k)].centre;
  }
  if (estimate_k) problem->relit.metres_per_world_unit = metres;
  for (int i = 0; i < num_points; ++i) {
    DirectBaPoint& p = problem->points[static_cast<size_t>(i)];
    p.inverse_depth = static_cast<float>(rho[static_cast<size_t>(i)]);
    int inl = 0;
    for (int t = 0; t < num_kf; ++t) inl += t != p.host && active[static_cast<size_t>(i) * num_kf + t];
    p.ok = inl > 0 && rho[static_cast<size_t>(i)] > 0;
  }
  return summary;
}

}  // namespace prism
