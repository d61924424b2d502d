// DirectBaSolver's relit model, cost evaluation, linearisation and normal equations (keyframe_ba_internal.h).
#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>

#include <Eigen/Geometry>

#include "core/slam/keyframe_ba_internal.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {
namespace {

constexpr double kLogKStep = 1e-4;  // for d residual / d log K

}  // namespace

// The image point i's residual in target t reads: J (or with relit.rig alone the raw grey level, which
// grey_j then holds), or in mixed mode the raw grey level for relit points.
const cv::Mat& DirectBaSolver::ImageOf(const std::vector<cv::Mat>& level_images, int i, int t) const {
  return relit_.mixed && relit_point_[static_cast<size_t>(i)] ? raw_grey_[static_cast<size_t>(t)]
                                                              : level_images[static_cast<size_t>(t)];
}

// S(p): rows E_l(p) L_l(p)^T at a metric point in the camera.
Eigen::Matrix3d DirectBaSolver::Lighting(const Eigen::Vector3d& point_m) const {
  Eigen::Matrix3d m;
  for (int l = 0; l < 3; ++l) {
    Eigen::Vector3d to_light;
    double irradiance;
    relit_.rig->lights[static_cast<size_t>(l)].Illuminate(point_m, &to_light, &irradiance);
    m.row(l) = irradiance * to_light.transpose();
  }
  return m;
}

// rho n of point i at inverse depth r (host camera), NaN when its implied normal faces away.
Eigen::Vector3d DirectBaSolver::ImpliedNormal(const std::vector<Pose>& ps, int i, double r, double k) const {
  const Pose& h = ps[static_cast<size_t>(problem_->points[static_cast<size_t>(i)].host)];
  const Eigen::Vector3d x = (k * h.scale / r) * ray_[static_cast<size_t>(i)];
  const Eigen::Vector3d m = Lighting(x).inverse() * bands_[static_cast<size_t>(i)];
  if (!m.allFinite() || m.dot(-x.normalized()) < 0.1 * m.norm())
    return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  return m;
}

// The predicted raw grey level of point i (rho n = m in its host's camera) at pt in target t's camera
// (world units).
double DirectBaSolver::RelitPrediction(const std::vector<Pose>& ps, int i, int t, const Eigen::Vector3d& pt,
                                       const Eigen::Vector3d& m, double k) const {
  const Pose& h = ps[static_cast<size_t>(problem_->points[static_cast<size_t>(i)].host)];
  const Eigen::Vector3d n_t = ps[static_cast<size_t>(t)].rotation.transpose() * (h.rotation * m);
  const Eigen::Vector3d x = k * pt;
  Eigen::Vector3d shading;
  for (int l = 0; l < 3; ++l) {
    Eigen::Vector3d to_light;
    double irradiance;
    relit_.rig->lights[static_cast<size_t>(l)].Illuminate(x, &to_light, &irradiance);
    shading[l] = irradiance * std::max(0.0, n_t.dot(to_light)) * relit_.albedo_colour(l);
  }
  return (grey_of_light_ * shading)(0);
}

// Point i in the world (once per point; CollectVisible takes it into each target's camera).
Eigen::Vector3d DirectBaSolver::WorldPoint(const std::vector<Pose>& ps, int i, double r) const {
  const Pose& h = ps[static_cast<size_t>(problem_->points[static_cast<size_t>(i)].host)];
  return h.centre + h.scale * (h.rotation * (ray_[static_cast<size_t>(i)] / r));
}

// Target t's residuals that project into its image at the current level: the points `usable` accepts,
// hosted elsewhere and active in t, in point order (xw: the points in the world). The image reads come
// after, prefetched kPrefetchAhead residuals ahead.
template <typename Usable>
void DirectBaSolver::CollectVisible(int t, const Eigen::Matrix3d& rt_t, const Eigen::Vector3d& c_t,
                                    const std::vector<Eigen::Vector3d>& xw, const Usable& usable,
                                    ProjectedList* out) const {
  out->clear();
  for (int i = 0; i < num_points_; ++i) {
    if (!usable(i) || t == problem_->points[static_cast<size_t>(i)].host ||
        !active_[static_cast<size_t>(i) * num_kf_ + t])
      continue;
    const Eigen::Vector3d pt = rt_t * (xw[static_cast<size_t>(i)] - c_t);
    if (!(pt.z() > 1e-9)) continue;
    const Eigen::Vector2d px = ProjectUndistorted(lcam_, pt);
    if (!lcam_.InImage(px, border_)) continue;
    out->push_back({i, pt, px});
  }
}

// The image reads of target t's residuals `visible`, all at once: a short loop whose loads overlap
// (inside the long loops after it each one waited for its sample; 12% of the adjustment's time,
// BM_KeyframeWindowAdjustment), prefetched kPrefetchAhead residuals ahead, and in the order of their
// image rows (a counting sort). In point order each host's points sweep the whole target image, one
// sweep per host, and what one sweep read has left the cache (1 MB per image at 512x512) before the next
// sweep reads near it; the hosts' points often land near each other (their strongest gradients are the
// same edges), and row by row those reads follow each other. The window adjustment 155 -> 122 ms on the
// armadillo's benchmark window (medians of three alternating runs). Each residual's sample is written to
// its own slot, so the order changes no result. The gradients with the values when `with_gradient`.
void DirectBaSolver::ReadImages(const ProjectedList& visible, int t, bool with_gradient,
                                std::vector<Sampled>* sampled) {
  const size_t n = visible.size();
  sampled->resize(n);
  const int rows = limg_->front().rows;
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
      PrefetchSample(ImageOf(*limg_, ahead.point, t), ahead.px.x(), ahead.px.y());
    }
    const size_t k = order[q];
    const cv::Mat& image = ImageOf(*limg_, visible[k].point, t);
    const Eigen::Vector2d& px = visible[k].px;
    Sampled& sk = (*sampled)[k];
    sk.ok = with_gradient ? SampleWithGradient(image, px.x(), px.y(), &sk.value, &sk.g)
                          : SampleValue(image, px.x(), px.y(), &sk.value);
  }
  image_samples_.fetch_add(static_cast<long long>(n), std::memory_order_relaxed);
}

// Runs fn(t, worker) for every target, each worker pulling the next target (its own scratch).
template <typename Fn>
void DirectBaSolver::ForEachTargetParallel(const Fn& fn) {
  std::atomic<int> next{0};
  pool_->ParallelFor(0, workers_, [&](std::ptrdiff_t w) {
    for (int t = next.fetch_add(1); t < num_kf_; t = next.fetch_add(1)) fn(t, static_cast<int>(w));
  });
}

// Runs fn(i) for every point: with workers in chunks on the pool (fn writes point i's entries alone).
template <typename Fn>
void DirectBaSolver::ForEachPoint(const Fn& fn) {
  if (workers_ <= 1) {
    for (int i = 0; i < num_points_; ++i) fn(i);
    return;
  }
  const int chunk = 256;
  pool_->ParallelFor(0, (num_points_ + chunk - 1) / chunk, [&](std::ptrdiff_t c) {
    const int i1 = std::min(num_points_, static_cast<int>(c + 1) * chunk);
    for (int i = static_cast<int>(c) * chunk; i < i1; ++i) fn(i);
  });
}

// Target t's residuals at poses ps and inverse depths rs: residual(point, |scaled residual|) for each, in
// the order they are summed (each target's image read in about raster order). With `store`
// (linearise_from_evaluation) the projections and samples go there, with the gradients.
template <typename Residual>
void DirectBaSolver::EvaluateTarget(const std::vector<Pose>& ps, const std::vector<double>& rs, int t,
                                    ProjectedList* vis, std::vector<Sampled>* values, TargetSamples* store,
                                    const Residual& residual) {
  const Eigen::Matrix3d rt_t = ps[static_cast<size_t>(t)].rotation.transpose();
  const Eigen::Vector3d& c_t = ps[static_cast<size_t>(t)].centre;
  if (store != nullptr) {
    vis = &store->visible;
    values = &store->sampled;
  }
  // The projections first, then the image reads (prefetched kPrefetchAhead residuals ahead).
  CollectVisible(
      t, rt_t, c_t, eval_world_,
      [&](int i) { return rs[static_cast<size_t>(i)] > 0 && !std::isnan(lint_[static_cast<size_t>(i)]); }, vis);
  // The image reads first, then the residuals.
  ReadImages(*vis, t, /*with_gradient=*/store != nullptr, values);
  for (size_t k = 0; k < vis->size(); ++k) {
    if (!(*values)[k].ok) continue;
    const int i = (*vis)[k].point;
    const Eigen::Vector3d& pt = (*vis)[k].pt;
    const double value = (*values)[k].value;
    double expected = lint_[static_cast<size_t>(i)];
    if (relit_point_[static_cast<size_t>(i)]) {
      if (!normal_rho_[static_cast<size_t>(i)].allFinite()) continue;
      expected = RelitPrediction(ps, i, t, pt, normal_rho_[static_cast<size_t>(i)], metres_);
    }
    residual(i, residual_scale_[static_cast<size_t>(i)] * std::abs(value - expected));
  }
}

// The cost at (ps, rs), target by target; with slot >= 0 (and reuse_samples_) its reads are kept in
// sample_slots_[slot]. The residuals above options.outlier are listed in *over (point * num_kf + target)
// as they are summed: the outlier test after the first solve then reads the current state's list instead
// of projecting and sampling every residual again (the same residuals, values and test).
double DirectBaSolver::Evaluate(const std::vector<Pose>& ps, const std::vector<double>& rs, int* count, double* sq,
                                std::vector<int>* over, int slot) {
  ++summary_.evaluations;
  auto store_of = [&](int t) -> TargetSamples* {
    return reuse_samples_ && slot >= 0 ? &sample_slots_[slot][static_cast<size_t>(t)] : nullptr;
  };
  double cost = 0;
  *count = 0;
  *sq = 0;
  over->clear();
  ForEachPoint([&](int i) {
    if (rs[static_cast<size_t>(i)] > 0) {
      eval_world_[static_cast<size_t>(i)] = WorldPoint(ps, i, rs[static_cast<size_t>(i)]);
      if (relit_point_[static_cast<size_t>(i)] && !std::isnan(lint_[static_cast<size_t>(i)]))
        normal_rho_[static_cast<size_t>(i)] = ImpliedNormal(ps, i, rs[static_cast<size_t>(i)], metres_);
    }
  });
  auto add = [&](int t, int i, double e) {
    cost += HuberCost(e, options_.huber);
    *sq += e * e;
    ++*count;
    if (e > options_.outlier) over->push_back(i * num_kf_ + t);
  };
  if (workers_ > 1) {
    ForEachTargetParallel([&](int t, int w) {
      std::vector<EvalTerm>& terms = eval_terms_[static_cast<size_t>(t)];
      terms.clear();
      EvaluateTarget(ps, rs, t, &worker_visible_[static_cast<size_t>(w)], &worker_sampled_[static_cast<size_t>(w)],
                     store_of(t), [&](int i, double e) {
                       terms.push_back({i, e});
                     });
    });
    for (int t = 0; t < num_kf_; ++t)
      for (const EvalTerm& term : eval_terms_[static_cast<size_t>(t)]) add(t, term.point, term.e);
  } else {
    for (int t = 0; t < num_kf_; ++t)
      EvaluateTarget(ps, rs, t, &eval_visible_, &eval_values_, store_of(t), [&](int i, double e) { add(t, i, e); });
  }
  const double along = baseline_.dot(ps[1].centre - centre1_initial_);
  return cost + 0.5 * gauge_weight_ * along * along;
}

// The points' world positions (and relit: their implied normals and those's derivatives) for a
// linearisation, and which points take part.
void DirectBaSolver::PrepareLinearisationPoints() {
  ForEachPoint([&](int i) {
    hcp_[static_cast<size_t>(i)].setZero();
    std::fill(&touched_[static_cast<size_t>(i) * num_kf_], &touched_[static_cast<size_t>(i) * num_kf_] + num_kf_, 0);
    const double r = rho_[static_cast<size_t>(i)];
    point_ok_[static_cast<size_t>(i)] = r > 0 && !std::isnan(lint_[static_cast<size_t>(i)]);
    if (point_ok_[static_cast<size_t>(i)]) world_[static_cast<size_t>(i)] = WorldPoint(poses_, i, r);
    if (point_ok_[static_cast<size_t>(i)] && relit_point_[static_cast<size_t>(i)]) {
      normal_rho_[static_cast<size_t>(i)] = ImpliedNormal(poses_, i, r, metres_);
      normal_rho_drho_[static_cast<size_t>(i)] =
          (ImpliedNormal(poses_, i, r * (1 + 1e-5), metres_) - ImpliedNormal(poses_, i, r * (1 - 1e-5), metres_)) /
          (2e-5 * r);
      point_ok_[static_cast<size_t>(i)] =
          normal_rho_[static_cast<size_t>(i)].allFinite() && normal_rho_drho_[static_cast<size_t>(i)].allFinite();
      if (estimate_k_ && point_ok_[static_cast<size_t>(i)]) {
        normal_rho_kp_[static_cast<size_t>(i)] = ImpliedNormal(poses_, i, r, metres_ * std::exp(kLogKStep));
        normal_rho_km_[static_cast<size_t>(i)] = ImpliedNormal(poses_, i, r, metres_ * std::exp(-kLogKStep));
        point_ok_[static_cast<size_t>(i)] =
            normal_rho_kp_[static_cast<size_t>(i)].allFinite() && normal_rho_km_[static_cast<size_t>(i)].allFinite();
      }
    }
  });
}

// Target t's residuals. Its pairs' sums are written here (no other target writes them); each
// residual's terms of its point's sums (the Hessian and gradient of the inverse depth, the target's
// and the host's segments of the coupling) and its cost go to point_terms(point, host, target, h, b,
// target segment, host segment, |scaled residual|). With workers they are kept per target and
// added afterwards: written here, the points' sums of two targets would share cache lines.
// With K estimated, each residual's terms of log K's sums go to k_term(point, host, target, h_kk, b_k,
// h_ck's target segment, its host segment, h_pk) (the same way).
template <typename PointTerms, typename KTermFn>
void DirectBaSolver::LineariseTarget(int t, ProjectedList& visible, std::vector<Sampled>& sampled,
                                     std::vector<Eigen::Matrix3d>& target_from_host, const PointTerms& point_terms,
                                     const KTermFn& k_term) {
  const Pose& tp = poses_[static_cast<size_t>(t)];
  const Eigen::Matrix3d rt_t = tp.rotation.transpose();
  // d (point in target) / d (point in host camera, host units), per host: R_t^T s_h R_h.
  for (int k = 0; k < num_kf_; ++k)
    target_from_host[static_cast<size_t>(k)] =
        rt_t * (poses_[static_cast<size_t>(k)].scale * poses_[static_cast<size_t>(k)].rotation);
  // With the current state's evaluation kept (linearise_from_evaluation), its projections and reads
  // (in the same order as below; residuals dropped as outliers since then are skipped).
  const bool from_evaluation = current_samples_valid_;
  const ProjectedList& vis = from_evaluation ? sample_slots_[current_slot_][static_cast<size_t>(t)].visible : visible;
  const std::vector<Sampled>& smp =
      from_evaluation ? sample_slots_[current_slot_][static_cast<size_t>(t)].sampled : sampled;
  if (!from_evaluation) {
    // The projections first, then the image reads (prefetched kPrefetchAhead residuals ahead).
    CollectVisible(
        t, rt_t, tp.centre, world_, [&](int i) { return point_ok_[static_cast<size_t>(i)] != 0; }, &visible);
    ReadImages(visible, t, /*with_gradient=*/true, &sampled);
  }
  for (size_t k = 0; k < vis.size(); ++k) {
    if (!smp[k].ok) continue;
    const int i = vis[k].point;
    if (from_evaluation && !active_[static_cast<size_t>(i) * num_kf_ + t]) continue;
    const DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
    const Eigen::Vector3d& pt = vis[k].pt;
    const double value = smp[k].value;
    const Eigen::Vector2d& g = smp[k].g;
    const double r = rho_[static_cast<size_t>(i)];
    const bool relit_i = relit_point_[static_cast<size_t>(i)];
    const double res =
        value - (relit_i ? RelitPrediction(poses_, i, t, pt, normal_rho_[static_cast<size_t>(i)], metres_)
                         : static_cast<double>(lint_[static_cast<size_t>(i)]));
    // The residual scaled by s: Huber on s |res|, and s^2 in the weight of the unscaled rows.
    const double s_i = residual_scale_[static_cast<size_t>(i)];
    const double e = s_i * std::abs(res);
    const double w = (e <= options_.huber ? 1.0 : options_.huber / e) * s_i * s_i;
    const double iz = 1.0 / pt.z();
    Eigen::Matrix<double, 2, 3> du_dp;
    du_dp << lcam_.fx * iz, 0, -lcam_.fx * pt.x() * iz * iz, 0, lcam_.fy * iz, -lcam_.fy * pt.y() * iz * iz;
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
      const Eigen::Vector3d& m = normal_rho_[static_cast<size_t>(i)];
      r_th = rt_t * poses_[static_cast<size_t>(p.host)].rotation;
      n_t = r_th * m;
      const Eigen::Vector3d x = metres_ * pt;
      Eigen::RowVector3d dpred_dx = Eigen::RowVector3d::Zero();
      for (int l = 0; l < 3; ++l) {
        Eigen::Vector3d to_light;
        double irradiance;
        relit_.rig->lights[static_cast<size_t>(l)].Illuminate(x, &to_light, &irradiance);
        if (n_t.dot(to_light) > 0)
          j_n -= grey_of_light_(l) * relit_.albedo_colour(l) * irradiance * to_light.transpose();
      }
      const double hx = 1e-6 * std::max(1e-3, x.norm());
      for (int c = 0; c < 3; ++c) {
        Eigen::Vector3d d = Eigen::Vector3d::Zero();
        d(c) = hx / metres_;
        dpred_dx(c) =
            (RelitPrediction(poses_, i, t, pt + d, m, metres_) - RelitPrediction(poses_, i, t, pt - d, m, metres_)) /
            (2 * hx / metres_);
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
    const Eigen::Vector3d& ray_i = ray_[static_cast<size_t>(i)];
    Eigen::Matrix<double, 1, 6> j_host;
    j_host.head<3>() = -j_q.cross((ray_i / r).transpose());
    j_host.tail<3>() = -j_target.tail<3>();
    double j_rho = -j_q.dot(ray_i) / (r * r);
    if (relit_i) {
      j_host.head<3>() -= j_n * r_th * Skew(normal_rho_[static_cast<size_t>(i)]);
      j_rho += j_n.dot(r_th * normal_rho_drho_[static_cast<size_t>(i)]);
    }
    if (estimate_k_ && relit_i) {
      // d residual / d log K: the target's lighting and the host's implied normal both move with K.
      const double j_k =
          -(RelitPrediction(poses_, i, t, pt, normal_rho_kp_[static_cast<size_t>(i)], metres_ * std::exp(kLogKStep)) -
            RelitPrediction(poses_, i, t, pt, normal_rho_km_[static_cast<size_t>(i)], metres_ * std::exp(-kLogKStep))) /
          (2 * kLogKStep);
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
    PairSums& pair = pairs_[static_cast<size_t>(kt * num_kf_ + kh)];
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
}

// One linearisation at the current state: the points' sums (hpp_, bp_, hcp_, h_pk_), the pairs' sums
// (pairs_, mapped by AddPairSums), log K's sums in *ne, and with lin->sum the cost.
void DirectBaSolver::Linearise(NormalEquations* ne, LinearisedCost* lin) {
  std::fill(h_pk_.begin(), h_pk_.end(), 0.0);
  std::fill(hpp_.begin(), hpp_.end(), 0.0);
  std::fill(bp_.begin(), bp_.end(), 0.0);
  // The points' world positions; then the residuals target by target (each target's image is read
  // in about raster order: the points are in their hosts' raster order).
  PrepareLinearisationPoints();
  auto add_cost = [&](double e) {
    if (lin->sum) {
      lin->cost += HuberCost(e, options_.huber);
      lin->sq += e * e;
      ++lin->count;
    }
  };
  auto add_k_terms = [&](int i, int kh, int kt, double hk, double bk, const Eigen::Matrix<double, 6, 1>& target_segment,
                         const Eigen::Matrix<double, 6, 1>& host_segment, double hpk) {
    ne->h_kk += hk;
    ne->b_k += bk;
    if (kt > 0) ne->h_ck.segment<6>(6 * (kt - 1)) += target_segment;
    if (kh > 0) ne->h_ck.segment<6>(6 * (kh - 1)) += host_segment;
    h_pk_[static_cast<size_t>(i)] += hpk;
  };
  auto add_point_terms = [&](int i, int kh, int kt, double h, double b,
                             const Eigen::Matrix<double, 6, 1>& target_segment,
                             const Eigen::Matrix<double, 6, 1>& host_segment) {
    hpp_[static_cast<size_t>(i)] += h;
    bp_[static_cast<size_t>(i)] += b;
    // The target's segment has this one term (one residual per point and target), the host's one per
    // target.
    if (kt > 0) {
      hcp_[static_cast<size_t>(i)].segment<6>(6 * (kt - 1)) += target_segment;
      touched_[static_cast<size_t>(i) * num_kf_ + kt] = 1;
    }
    if (kh > 0) {
      hcp_[static_cast<size_t>(i)].segment<6>(6 * (kh - 1)) += host_segment;
      touched_[static_cast<size_t>(i) * num_kf_ + kh] = 1;
    }
  };
  if (workers_ > 1) {
    ForEachTargetParallel([&](int t, int w) {
      std::vector<LinTerm>& terms = lin_terms_[static_cast<size_t>(t)];
      int* index = &lin_term_index_[static_cast<size_t>(t) * num_points_];
      terms.clear();
      std::fill(index, index + num_points_, -1);
      std::vector<KTerm>* kt_terms = estimate_k_ ? &k_terms_[static_cast<size_t>(t)] : nullptr;
      if (kt_terms != nullptr) kt_terms->clear();
      LineariseTarget(
          t, worker_visible_[static_cast<size_t>(w)], worker_sampled_[static_cast<size_t>(w)],
          worker_target_from_host_[static_cast<size_t>(w)],
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
    for (int t = 0; t < num_kf_; ++t)
      for (const LinTerm& term : lin_terms_[static_cast<size_t>(t)]) add_cost(term.e);
    if (estimate_k_)
      for (int t = 0; t < num_kf_; ++t)
        for (const KTerm& term : k_terms_[static_cast<size_t>(t)])
          add_k_terms(term.point, term.host, t, term.h_kk, term.b_k, term.target_segment, term.host_segment, term.h_pk);
    const int chunk = 256;
    pool_->ParallelFor(0, (num_points_ + chunk - 1) / chunk, [&](std::ptrdiff_t c) {
      const int i1 = std::min(num_points_, static_cast<int>(c + 1) * chunk);
      for (int i = static_cast<int>(c) * chunk; i < i1; ++i)
        for (int t = 0; t < num_kf_; ++t) {
          const int k = lin_term_index_[static_cast<size_t>(t) * num_points_ + i];
          if (k < 0) continue;
          const LinTerm& term = lin_terms_[static_cast<size_t>(t)][static_cast<size_t>(k)];
          add_point_terms(i, term.host, t, term.h, term.b, term.target_segment, term.host_segment);
        }
    });
  } else {
    for (int t = 0; t < num_kf_; ++t)
      LineariseTarget(
          t, lin_visible_, lin_sampled_, lin_target_from_host_,
          [&](int i, int kh, int kt, double h, double b, const Eigen::Matrix<double, 6, 1>& target_segment,
              const Eigen::Matrix<double, 6, 1>& host_segment, double e) {
            add_cost(e);
            add_point_terms(i, kh, kt, h, b, target_segment, host_segment);
          },
          add_k_terms);
  }
}

// Each pair's sums, in the target's parameters, and mapped to the host's: j_host = j_target A.
void DirectBaSolver::AddPairSums(NormalEquations* ne) {
  for (int kh = 0; kh < num_kf_; ++kh)
    for (int kt = 0; kt < num_kf_; ++kt) {
      PairSums& pair = pairs_[static_cast<size_t>(kt * num_kf_ + kh)];
      if (!pair.used) continue;
      const Eigen::Matrix<double, 6, 6> h_tt = pair.h.selfadjointView<Eigen::Lower>();
      const Eigen::Matrix<double, 6, 6> a =
          DirectBaHostFromTarget(poses_[static_cast<size_t>(kh)].rotation, poses_[static_cast<size_t>(kh)].centre,
                                 poses_[static_cast<size_t>(kt)].rotation, poses_[static_cast<size_t>(kt)].centre);
      const int oh = 6 * (kh - 1), ot = 6 * (kt - 1);
      if (kt > 0) {
        ne->hcc.block<6, 6>(ot, ot) += h_tt;
        ne->bc.segment<6>(ot) += pair.b;
      }
      if (kh > 0) {
        const Eigen::Matrix<double, 6, 6> at_h = a.transpose() * h_tt;
        ne->hcc.block<6, 6>(oh, oh) += at_h * a;
        ne->bc.segment<6>(oh) += a.transpose() * pair.b;
        // Off the diagonal only the block below it: the solve reads the lower triangle alone.
        if (kt > 0) {
          if (oh > ot) ne->hcc.block<6, 6>(oh, ot) += at_h;
          else ne->hcc.block<6, 6>(ot, oh) += at_h.transpose();
        }
      }
      pair = PairSums();
    }
}

}  // namespace internal
}  // namespace prism
