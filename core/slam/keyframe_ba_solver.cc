// DirectBaSolver's set-up, Levenberg-Marquardt loop, Schur complement and write-back (keyframe_ba_internal.h).
#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <opencv2/imgproc.hpp>

#include "core/slam/keyframe_ba_internal.h"
#include "core/util/thread_pool.h"

namespace prism {
namespace internal {

DirectBaSolver::DirectBaSolver(const DirectBaOptions& options, DirectBaProblem* problem, ThreadPool* pool)
    : options_(options),
      problem_(problem),
      pool_(pool),
      num_kf_(static_cast<int>(problem->world_from_keyframe.size())),
      cam_(problem->camera),
      relit_(problem->relit),
      use_relit_(relit_.rig != nullptr),
      num_points_(static_cast<int>(problem->points.size())),
      estimate_k_(use_relit_ && relit_.estimate_metres_per_world_unit),
      dim_(6 * (num_kf_ - 1)),
      levels_(options.pyramid_levels),
      workers_(pool != nullptr ? std::max(1, std::min(pool->num_threads(), num_kf_)) : 1),
      metres_(relit_.metres_per_world_unit),
      eval_visible_(static_cast<size_t>(num_points_)),
      lin_visible_(static_cast<size_t>(num_points_)) {
  InitPoints();
  InitRelit();
  InitGauge();
  InitPyramid();
  InitScratch();
}

void DirectBaSolver::InitPoints() {
  poses_.resize(static_cast<size_t>(num_kf_));
  for (int k = 0; k < num_kf_; ++k) {
    const Sim3d& s = problem_->world_from_keyframe[static_cast<size_t>(k)];
    poses_[static_cast<size_t>(k)] = {s.rotation.toRotationMatrix(), s.translation, s.scale};
  }
  rho_.resize(static_cast<size_t>(num_points_));
  ray_.resize(static_cast<size_t>(num_points_));
  for (int i = 0; i < num_points_; ++i) {
    const DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
    rho_[static_cast<size_t>(i)] = p.inverse_depth;
    ray_[static_cast<size_t>(i)] = cam_.Unproject(Eigen::Vector2d(p.u, p.v));
  }
  // Which points take the relit residual (all with relit.rig, those marked with relit.mixed), its scale
  // (1 for J points, or their gradient weight below), and in mixed mode the raw grey images they are
  // compared against.
  relit_point_.assign(static_cast<size_t>(num_points_), 0);
  residual_scale_.assign(static_cast<size_t>(num_points_), 1.0);
  for (int i = 0; i < num_points_; ++i) {
    relit_point_[static_cast<size_t>(i)] =
        use_relit_ && (!relit_.mixed || problem_->points[static_cast<size_t>(i)].relit);
    if (relit_.mixed && relit_point_[static_cast<size_t>(i)])
      residual_scale_[static_cast<size_t>(i)] = relit_.relit_residual_scale;
  }
  if (use_relit_ && relit_.mixed)
    for (const cv::Mat& rgb : relit_.rgb) raw_grey_.push_back(MeanOfChannels(rgb));
}

void DirectBaSolver::InitRelit() {
  bands_.resize(use_relit_ ? static_cast<size_t>(num_points_) : 0);
  normal_rho_.resize(use_relit_ ? static_cast<size_t>(num_points_) : 0);
  normal_rho_drho_.resize(use_relit_ ? static_cast<size_t>(num_points_) : 0);
  normal_rho_kp_.resize(estimate_k_ ? static_cast<size_t>(num_points_) : 0);
  normal_rho_km_.resize(estimate_k_ ? static_cast<size_t>(num_points_) : 0);
  if (use_relit_) {
    const Eigen::Matrix3d demix = relit_.rig->crosstalk.inverse();
    grey_of_light_ = relit_.rig->crosstalk.colwise().sum() / 3.0;
    for (int i = 0; i < num_points_; ++i) {
      DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
      if (!relit_point_[static_cast<size_t>(i)]) {
        bands_[static_cast<size_t>(i)].setConstant(std::numeric_limits<double>::quiet_NaN());
        continue;
      }
      const cv::Vec3b c =
          relit_.rgb[static_cast<size_t>(p.host)].at<cv::Vec3b>(static_cast<int>(p.v), static_cast<int>(p.u));
      const Eigen::Vector3d b = demix * Eigen::Vector3d(c[0], c[1], c[2]);
      bands_[static_cast<size_t>(i)] = b.cwiseQuotient(relit_.albedo_colour);
      const bool usable = std::max({c[0], c[1], c[2]}) < 250 && b.maxCoeff() > 0 &&
                          b.minCoeff() >= relit_.min_band_fraction * b.maxCoeff();
      if (!usable) bands_[static_cast<size_t>(i)].setConstant(std::numeric_limits<double>::quiet_NaN());
    }
  }
}

void DirectBaSolver::InitGauge() {
  Eigen::Vector3d baseline = poses_[1].centre - poses_[0].centre;
  const double baseline_norm = baseline.norm();
  baseline_ = baseline_norm > 0 ? Eigen::Vector3d(baseline / baseline_norm) : Eigen::Vector3d::UnitX();
  centre1_initial_ = poses_[1].centre;
  // Stiff against the photometric rows (gradient^2 f^2 / z^2 per residual, many residuals).
  gauge_weight_ = 1e10 * cam_.fx * cam_.fx / std::max(1e-12, baseline_norm * baseline_norm);
  border_ = options_.border_px;
  active_.assign(static_cast<size_t>(num_points_) * num_kf_, 1);
}

void DirectBaSolver::InitPyramid() {
  // Image pyramid (2x2 box averages) for a wider convergence basin: coarse to fine.
  pyramid_.resize(static_cast<size_t>(levels_));
  pyramid_[0] = problem_->grey_j;
  for (int l = 1; l < levels_; ++l)
    for (const cv::Mat& g : pyramid_[static_cast<size_t>(l - 1)]) {
      cv::Mat half;
      cv::resize(g, half, cv::Size(g.cols / 2, g.rows / 2), 0, 0, cv::INTER_AREA);
      pyramid_[static_cast<size_t>(l)].push_back(half);
    }
  if (options_.gradient_weight_c > 0) {
    const double c2 = options_.gradient_weight_c * options_.gradient_weight_c;
    for (int i = 0; i < num_points_; ++i) {
      if (relit_point_[static_cast<size_t>(i)]) continue;
      const DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
      double value;
      Eigen::Vector2d g;
      if (SampleWithGradient(pyramid_[0][static_cast<size_t>(p.host)], p.u, p.v, &value, &g))
        residual_scale_[static_cast<size_t>(i)] = std::sqrt(c2 / (c2 + g.squaredNorm()));
    }
  }
  lcam_ = cam_;
  limg_ = &pyramid_[0];
  lint_.resize(static_cast<size_t>(num_points_));
  for (int i = 0; i < num_points_; ++i)
    lint_[static_cast<size_t>(i)] = problem_->points[static_cast<size_t>(i)].intensity;
  // Relit points: lint only marks the points left out (NaN).
  for (int i = 0; i < num_points_; ++i)
    if (relit_point_[static_cast<size_t>(i)])
      lint_[static_cast<size_t>(i)] =
          bands_[static_cast<size_t>(i)].allFinite() ? 0.0f : std::numeric_limits<float>::quiet_NaN();
}

void DirectBaSolver::InitScratch() {
  worker_sampled_.resize(static_cast<size_t>(workers_));
  worker_target_from_host_.assign(static_cast<size_t>(workers_),
                                  std::vector<Eigen::Matrix3d>(static_cast<size_t>(num_kf_)));
  if (workers_ > 1)
    for (int w = 0; w < workers_; ++w) worker_visible_.emplace_back(static_cast<size_t>(num_points_));
  eval_world_.resize(static_cast<size_t>(num_points_));
  eval_terms_.resize(workers_ > 1 ? static_cast<size_t>(num_kf_) : 0);
  reuse_samples_ = options_.linearise_from_evaluation && !use_relit_;
  if (reuse_samples_)
    for (std::vector<TargetSamples>& slot : sample_slots_) slot.resize(static_cast<size_t>(num_kf_));
  hpp_.resize(static_cast<size_t>(num_points_));
  bp_.resize(static_cast<size_t>(num_points_));
  hcp_.assign(static_cast<size_t>(num_points_), Eigen::VectorXd::Zero(dim_));
  touched_.assign(static_cast<size_t>(num_points_) * num_kf_, 0);
  pairs_.resize(static_cast<size_t>(num_kf_ * num_kf_));
  world_.resize(static_cast<size_t>(num_points_));
  point_ok_.resize(static_cast<size_t>(num_points_));
  lin_target_from_host_.resize(static_cast<size_t>(num_kf_));
  k_terms_.resize(workers_ > 1 && estimate_k_ ? static_cast<size_t>(num_kf_) : 0);
  lin_terms_.resize(workers_ > 1 ? static_cast<size_t>(num_kf_) : 0);
  lin_term_index_.resize(workers_ > 1 ? static_cast<size_t>(num_kf_) * num_points_ : 0);
  hinv0_.resize(static_cast<size_t>(num_points_));
  hinv_.resize(static_cast<size_t>(num_points_));
  h_pk_.assign(static_cast<size_t>(num_points_), 0.0);
}

DirectBaSummary DirectBaSolver::Run() {
  // Its reads serve the first linearisation when that is at this level (pyramid_levels 1).
  const double initial_cost = Evaluate(poses_, rho_, &count_, &sq_, &over_, levels_ == 1 ? current_slot_ : -1);
  current_samples_valid_ = reuse_samples_ && levels_ == 1;
  summary_.initial_rms = count_ > 0 ? std::sqrt(sq_ / count_) : 0;
  for (int level = levels_ - 1; level >= 0; --level) {
    SetLevel(level);
    const int rounds = level == 0 ? 2 : 1;
    for (int round = 0; round < rounds; ++round) {
      SolveRound(level, round, initial_cost);
      if (round + 1 == rounds) break;
      // Drop the residuals above the outlier threshold (listed by the current state's evaluation), then
      // solve again.
      for (int idx : over_) active_[static_cast<size_t>(idx)] = 0;
    }
  }
  // count and sq are the final state's already (from its evaluation at the start of the last round or
  // when its step was accepted; nothing it depends on has changed since): no evaluation of its own.
  summary_.final_rms = count_ > 0 ? std::sqrt(sq_ / count_) : 0;
  summary_.image_samples = image_samples_.load();
  summary_.residuals = count_;
  WriteBack();
  return summary_;
}

void DirectBaSolver::SetLevel(int level) {
  const double f = std::ldexp(1.0, -level);
  lcam_ = cam_.AtPyramidLevel(level);
  limg_ = &pyramid_[static_cast<size_t>(level)];
  if (levels_ > 1) current_samples_valid_ = false;  // read at another level (or none)
  for (int i = 0; i < num_points_; ++i) {
    const DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
    double value = p.intensity;
    Eigen::Vector2d g;
    if (level > 0 && !SampleWithGradient((*limg_)[static_cast<size_t>(p.host)], (p.u + 0.5) * f - 0.5,
                                         (p.v + 0.5) * f - 0.5, &value, &g))
      value = std::numeric_limits<double>::quiet_NaN();
    lint_[static_cast<size_t>(i)] = static_cast<float>(value);
  }
}

void DirectBaSolver::SolveRound(int level, int round, double initial_cost) {
  LmState lm;
  // The first solve at full resolution without coarser levels starts where initial_cost was taken
  // (the same poses, depths, intensities and residuals). A solve after which no outlier test follows
  // takes its starting cost from its first linearisation, which reads the same residuals in the same
  // order (not with the relit residual, whose linearisation leaves out more points).
  const bool cost_from_linearisation = !use_relit_ && (round > 0 || level > 0);
  if (levels_ == 1 && round == 0) {
    lm.cost = initial_cost;
  } else if (!cost_from_linearisation) {
    lm.cost = Evaluate(poses_, rho_, &count_, &sq_, &over_, current_slot_);
    current_samples_valid_ = reuse_samples_;
  }
  for (int it = 0; it < options_.max_iterations; ++it) {
    ++summary_.iterations;
    // The cost at this linearisation, summed with it (cost_from_linearisation, first iteration).
    LinearisedCost lin;
    lin.sum = cost_from_linearisation && it == 0;
    NormalEquations ne(dim_);
    Linearise(&ne, &lin);
    AddPairSums(&ne);
    if (lin.sum) {
      const double along = baseline_.dot(poses_[1].centre - centre1_initial_);
      lm.cost = lin.cost + 0.5 * gauge_weight_ * along * along;
      count_ = lin.count;
      sq_ = lin.sq;
    }
    ne.hcc.block<3, 3>(3, 3) += gauge_weight_ * baseline_ * baseline_.transpose();
    ne.bc.segment<3>(3) += gauge_weight_ * baseline_ * baseline_.dot(poses_[1].centre - centre1_initial_);
    const SchurComplement sc = ComputeSchurComplement();
    // A step that decreased the cost by less than function_tolerance ends the solve.
    if (!Step(ne, sc, &lm) || lm.converged) break;
  }
}

DirectBaSolver::SchurComplement DirectBaSolver::ComputeSchurComplement() {
  // The points' Schur complement at lambda = 0; damping scales every point's 1 / hpp by 1 / (1 + lambda),
  // so each attempt below only rescales it.
  SchurComplement sc;
  sc.schur = Eigen::MatrixXd::Zero(dim_, dim_);  // lower block triangle
  sc.schur_b = Eigen::VectorXd::Zero(dim_);
  for (int i = 0; i < num_points_; ++i) {
    const double h = hpp_[static_cast<size_t>(i)];
    hinv0_[static_cast<size_t>(i)] = h > 1e-12 ? 1.0 / h : 0.0;
    if (hinv0_[static_cast<size_t>(i)] == 0) continue;
    const Eigen::VectorXd& hc = hcp_[static_cast<size_t>(i)];
    // schur -= hc hc^T / h over the touched segments' blocks only (hc is zero elsewhere). On one thread:
    // split by block columns between two threads (each block still summing its points in order) a
    // 24-keyframe adjustment took 3.15 instead of 2.79 s (both threads read every point's coupling).
    const double alpha = -hinv0_[static_cast<size_t>(i)];
    segments_.clear();
    for (int k = 1; k < num_kf_; ++k)
      if (touched_[static_cast<size_t>(i) * num_kf_ + k]) segments_.push_back(6 * (k - 1));
    for (size_t cb = 0; cb < segments_.size(); ++cb) {
      const Eigen::Matrix<double, 6, 1> scaled = alpha * hc.segment<6>(segments_[cb]);
      for (size_t rb = cb; rb < segments_.size(); ++rb)
        sc.schur.block<6, 6>(segments_[rb], segments_[cb]).noalias() +=
            hc.segment<6>(segments_[rb]) * scaled.transpose();
      sc.schur_b.segment<6>(segments_[cb]) += scaled * bp_[static_cast<size_t>(i)];
    }
  }
  // Relit with K estimated: log K's row of the Schur complement (every point couples to it).
  sc.schur_ck = Eigen::VectorXd::Zero(estimate_k_ ? dim_ : 0);
  if (estimate_k_) {
    for (int i = 0; i < num_points_; ++i) {
      const double hi = hinv0_[static_cast<size_t>(i)], pk = h_pk_[static_cast<size_t>(i)];
      if (hi == 0 || pk == 0) continue;
      sc.schur_kk -= hi * pk * pk;
      sc.schur_bk -= hi * pk * bp_[static_cast<size_t>(i)];
      sc.schur_ck.noalias() -= (hi * pk) * hcp_[static_cast<size_t>(i)];
    }
  }
  return sc;
}

bool DirectBaSolver::Step(const NormalEquations& ne, const SchurComplement& sc, LmState* lm) {
  bool accepted = false;
  for (int attempt = 0; attempt < 8 && !accepted; ++attempt) {
    Eigen::VectorXd dc;
    double d_log_k = 0;
    SolveDamped(ne, sc, lm->lambda, &dc, &d_log_k);
    if (!dc.allFinite() || !std::isfinite(d_log_k)) {
      lm->lambda *= 10;
      continue;
    }
    std::vector<Pose> np = poses_;
    for (int k = 1; k < num_kf_; ++k) {
      const Eigen::Matrix<double, 6, 1> d = dc.segment<6>(6 * (k - 1));
      np[static_cast<size_t>(k)].rotation =
          poses_[static_cast<size_t>(k)].rotation * ExpSo3(d.head<3>()).toRotationMatrix();
      np[static_cast<size_t>(k)].centre = poses_[static_cast<size_t>(k)].centre + d.tail<3>();
    }
    std::vector<double> nr = rho_;
    for (int i = 0; i < num_points_; ++i) {
      if (hinv_[static_cast<size_t>(i)] == 0) continue;
      const double d =
          -hinv_[static_cast<size_t>(i)] * (bp_[static_cast<size_t>(i)] + hcp_[static_cast<size_t>(i)].dot(dc) +
                                            (estimate_k_ ? h_pk_[static_cast<size_t>(i)] * d_log_k : 0.0));
      // Keep the inverse depth positive (a step to <= 0 is halved towards it).
      nr[static_cast<size_t>(i)] = rho_[static_cast<size_t>(i)] + d > 0.2 * rho_[static_cast<size_t>(i)]
                                       ? rho_[static_cast<size_t>(i)] + d
                                       : 0.2 * rho_[static_cast<size_t>(i)];
    }
    int nc = 0;
    double nsq = 0;
    const double k_before = metres_;
    metres_ = k_before * std::exp(d_log_k);  // evaluate at the trial K (restored if rejected)
    const double ncost = Evaluate(np, nr, &nc, &nsq, &trial_over_, 1 - current_slot_);
    if (!(ncost < lm->cost)) metres_ = k_before;
    if (ncost < lm->cost) {
      const double decrease = (lm->cost - ncost) / std::max(1e-300, lm->cost);
      const double predicted = options_.gain_ratio_damping ? PredictedDecrease(ne, lm->lambda, dc, d_log_k, nr) : 0;
      const double gain = predicted > 0 ? (lm->cost - ncost) / predicted : 0.0;
      poses_.swap(np);
      rho_.swap(nr);
      lm->cost = ncost;
      count_ = nc;  // count, sq and over: always the current state's
      sq_ = nsq;
      over_.swap(trial_over_);
      current_slot_ = 1 - current_slot_;  // the trial's reads are the current state's now
      current_samples_valid_ = reuse_samples_;
      if (options_.gain_ratio_damping) {
        const double c = 2 * gain - 1;
        lm->lambda = std::max(1e-7, lm->lambda * std::max(1.0 / 3, 1 - c * c * c));
        lm->nu = 2;
      } else {
        lm->lambda = std::max(1e-7, lm->lambda / 3);
      }
      accepted = true;
      if (decrease < options_.function_tolerance) lm->converged = true;
    } else if (options_.gain_ratio_damping) {
      lm->lambda *= lm->nu;
      lm->nu *= 2;
    } else {
      lm->lambda *= 5;
    }
  }
  return accepted;
}

void DirectBaSolver::SolveDamped(const NormalEquations& ne, const SchurComplement& sc, double lambda,
                                 Eigen::VectorXd* dc, double* d_log_k) {
  const double damp = 1.0 / (1 + lambda);
  Eigen::MatrixXd s = ne.hcc + damp * sc.schur;
  const Eigen::VectorXd b = ne.bc + damp * sc.schur_b;
  for (int i = 0; i < num_points_; ++i) hinv_[static_cast<size_t>(i)] = damp * hinv0_[static_cast<size_t>(i)];
  for (int d = 0; d < dim_; ++d) s(d, d) += lambda * std::max(1e-6, ne.hcc(d, d));
  if (estimate_k_) {
    // The poses' system bordered by log K (lower triangle filled).
    Eigen::MatrixXd full = Eigen::MatrixXd::Zero(dim_ + 1, dim_ + 1);
    full.topLeftCorner(dim_, dim_) = s.selfadjointView<Eigen::Lower>();
    full.block(dim_, 0, 1, dim_) = (ne.h_ck + damp * sc.schur_ck).transpose();
    full.block(0, dim_, dim_, 1) = ne.h_ck + damp * sc.schur_ck;
    full(dim_, dim_) = (ne.h_kk + damp * sc.schur_kk) + lambda * std::max(1e-6, ne.h_kk);
    Eigen::VectorXd full_b(dim_ + 1);
    full_b << b, ne.b_k + damp * sc.schur_bk;
    const Eigen::VectorXd sol = full.ldlt().solve(-full_b);
    *dc = sol.head(dim_);
    *d_log_k = std::clamp(sol(dim_), -0.2, 0.2);
  } else {
    *dc = s.selfadjointView<Eigen::Lower>().ldlt().solve(-b);
  }
}

double DirectBaSolver::PredictedDecrease(const NormalEquations& ne, double lambda, const Eigen::VectorXd& dc,
                                         double d_log_k, const std::vector<double>& nr) const {
  // gain_ratio_damping: the decrease the damped model predicts over the step d taken (a step
  // rejected needs none), (lambda d^T D d - g^T d) / 2 (g: the gradient; D: the damping's diagonal,
  // max(1e-6, hcc) for the poses, hpp for the points, max(1e-6, h_kk) for log K).
  double predicted = 0;
  for (int d = 0; d < dim_; ++d) predicted += lambda * std::max(1e-6, ne.hcc(d, d)) * dc(d) * dc(d) - ne.bc(d) * dc(d);
  for (int i = 0; i < num_points_; ++i) {
    const double d = nr[static_cast<size_t>(i)] - rho_[static_cast<size_t>(i)];
    predicted += lambda * hpp_[static_cast<size_t>(i)] * d * d - bp_[static_cast<size_t>(i)] * d;
  }
  if (estimate_k_) predicted += lambda * std::max(1e-6, ne.h_kk) * d_log_k * d_log_k - ne.b_k * d_log_k;
  predicted *= 0.5;
  return predicted;
}

void DirectBaSolver::WriteBack() {
  for (int k = 1; k < num_kf_; ++k) {
    Sim3d& out = problem_->world_from_keyframe[static_cast<size_t>(k)];
    out.rotation = Eigen::Quaterniond(poses_[static_cast<size_t>(k)].rotation).normalized();
    out.translation = poses_[static_cast<size_t>(k)].centre;
  }
  if (estimate_k_) problem_->relit.metres_per_world_unit = metres_;
  for (int i = 0; i < num_points_; ++i) {
    DirectBaPoint& p = problem_->points[static_cast<size_t>(i)];
    p.inverse_depth = static_cast<float>(rho_[static_cast<size_t>(i)]);
    int inl = 0;
    for (int t = 0; t < num_kf_; ++t) inl += t != p.host && active_[static_cast<size_t>(i) * num_kf_ + t];
    p.ok = inl > 0 && rho_[static_cast<size_t>(i)] > 0;
  }
}

}  // namespace internal
}  // namespace prism
