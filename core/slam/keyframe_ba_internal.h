// The windowed direct adjustment's internals (keyframe_ba.h): the sampling helpers and DirectBaSolver, whose
// parts are split by concern over keyframe_ba_solver.cc (set-up, Levenberg-Marquardt, Schur complement,
// write-back) and keyframe_ba_residuals.cc (the relit model, cost evaluation, linearisation, normal equations).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/geometry/camera.h"
#include "core/slam/keyframe_ba.h"

namespace prism {

class ThreadPool;

namespace internal {

inline Eigen::Matrix3d Skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

inline double HuberCost(double e, double delta) { return e <= delta ? 0.5 * e * e : delta * (e - 0.5 * delta); }

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

// One run of AdjustKeyframeWindowDirect on a validated problem: the constructor sets the problem up
// (poses, rays, the relit model's colours, the gauge, the image pyramid, the scratch), Run() solves it
// level by level and writes the result back. Not reused: one solver per call.
class DirectBaSolver {
 public:
  DirectBaSolver(const DirectBaOptions& options, DirectBaProblem* problem, ThreadPool* pool);
  DirectBaSummary Run();

 private:
  struct Pose {
    Eigen::Matrix3d rotation;
    Eigen::Vector3d centre;
    double scale;
  };
  struct EvalTerm {
    int point;
    double e;
  };
  // With workers: each target's residual terms of its points' sums in its order (see LineariseTarget),
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
  // The poses' normal equations of one linearisation, and with K estimated log K's Hessian, gradient and
  // couplings with the poses (the points' are in h_pk_).
  struct NormalEquations {
    explicit NormalEquations(int dim)
        : hcc(Eigen::MatrixXd::Zero(dim, dim)), bc(Eigen::VectorXd::Zero(dim)), h_ck(Eigen::VectorXd::Zero(dim)) {}
    Eigen::MatrixXd hcc;
    Eigen::VectorXd bc;
    double h_kk = 0, b_k = 0;
    Eigen::VectorXd h_ck;
  };
  // The cost at a linearisation, summed with it when `sum` (see SolveRound).
  struct LinearisedCost {
    bool sum = false;
    double cost = 0, sq = 0;
    int count = 0;
  };
  // The points' Schur complement at lambda = 0 (lower block triangle), and with K estimated log K's row.
  struct SchurComplement {
    Eigen::MatrixXd schur;
    Eigen::VectorXd schur_b;
    double schur_kk = 0, schur_bk = 0;
    Eigen::VectorXd schur_ck;
  };
  // A solve's Levenberg-Marquardt state.
  struct LmState {
    double lambda = 1e-3;
    double nu = 2;  // gain_ratio_damping: lambda's factor after the next rejected step
    double cost = 0.0;
    bool converged = false;  // the last accepted step decreased the cost by less than function_tolerance
  };

  // Set-up (keyframe_ba_solver.cc).
  void InitPoints();
  void InitRelit();
  void InitGauge();
  void InitPyramid();
  void InitScratch();
  // The camera, images and point intensities of pyramid level `level`.
  void SetLevel(int level);
  // One solve at the current level (round 0: the first, 1: the one after the outlier test).
  void SolveRound(int level, int round, double initial_cost);
  SchurComplement ComputeSchurComplement();
  // Up to 8 attempts of one iteration's step with growing damping; false: none decreased the cost.
  bool Step(const NormalEquations& ne, const SchurComplement& sc, LmState* lm);
  // The damped system's solution for the poses (dc) and log K at lambda; sets hinv_.
  void SolveDamped(const NormalEquations& ne, const SchurComplement& sc, double lambda, Eigen::VectorXd* dc,
                   double* d_log_k);
  // The decrease the damped model predicts for the step (dc, d_log_k, the depths nr) at lambda.
  double PredictedDecrease(const NormalEquations& ne, double lambda, const Eigen::VectorXd& dc, double d_log_k,
                           const std::vector<double>& nr) const;
  void WriteBack();

  // The relit model, evaluation and linearisation (keyframe_ba_residuals.cc).
  const cv::Mat& ImageOf(const std::vector<cv::Mat>& level_images, int i, int t) const;
  Eigen::Matrix3d Lighting(const Eigen::Vector3d& point_m) const;
  Eigen::Vector3d ImpliedNormal(const std::vector<Pose>& ps, int i, double r, double k) const;
  double RelitPrediction(const std::vector<Pose>& ps, int i, int t, const Eigen::Vector3d& pt, const Eigen::Vector3d& m,
                         double k) const;
  Eigen::Vector3d WorldPoint(const std::vector<Pose>& ps, int i, double r) const;
  template <typename Usable>
  void CollectVisible(int t, const Eigen::Matrix3d& rt_t, const Eigen::Vector3d& c_t,
                      const std::vector<Eigen::Vector3d>& xw, const Usable& usable, ProjectedList* out) const;
  void ReadImages(const ProjectedList& visible, int t, bool with_gradient, std::vector<Sampled>* sampled);
  template <typename Fn>
  void ForEachTargetParallel(const Fn& fn);
  template <typename Fn>
  void ForEachPoint(const Fn& fn);
  template <typename Residual>
  void EvaluateTarget(const std::vector<Pose>& ps, const std::vector<double>& rs, int t, ProjectedList* vis,
                      std::vector<Sampled>* values, TargetSamples* store, const Residual& residual);
  double Evaluate(const std::vector<Pose>& ps, const std::vector<double>& rs, int* count, double* sq,
                  std::vector<int>* over, int slot);
  void PrepareLinearisationPoints();
  template <typename PointTerms, typename KTermFn>
  void LineariseTarget(int t, ProjectedList& visible, std::vector<Sampled>& sampled,
                       std::vector<Eigen::Matrix3d>& target_from_host, const PointTerms& point_terms,
                       const KTermFn& k_term);
  void Linearise(NormalEquations* ne, LinearisedCost* lin);
  void AddPairSums(NormalEquations* ne);

  const DirectBaOptions& options_;
  DirectBaProblem* problem_;
  ThreadPool* pool_;
  const int num_kf_;
  const PinholeCamera& cam_;
  const DirectBaRelit& relit_;
  const bool use_relit_;
  const int num_points_;
  const bool estimate_k_;
  const int dim_;
  const int levels_;
  // With a pool: how many workers take targets in parallel (each has its own scratch).
  const int workers_;

  // The state: poses, inverse depths and K (changes when it is estimated).
  std::vector<Pose> poses_;
  std::vector<double> rho_;
  double metres_;
  std::vector<Eigen::Vector3d> ray_;
  std::vector<uint8_t> relit_point_;
  std::vector<double> residual_scale_;
  std::vector<cv::Mat> raw_grey_;
  // Relit: each point's demixed host colour (NaN intensity marks a point left out), and the model.
  std::vector<Eigen::Vector3d> bands_;
  std::vector<Eigen::Vector3d> normal_rho_;       // rho n, host camera
  std::vector<Eigen::Vector3d> normal_rho_drho_;  // its d / d rho
  Eigen::RowVector3d grey_of_light_ = Eigen::RowVector3d::Constant(1.0 / 3);
  std::vector<Eigen::Vector3d> normal_rho_kp_;  // at K e^+step
  std::vector<Eigen::Vector3d> normal_rho_km_;  // at K e^-step
  Eigen::Vector3d baseline_;
  Eigen::Vector3d centre1_initial_;
  double gauge_weight_ = 0;
  double border_ = 0;
  // active_[point * num_kf + target]
  std::vector<uint8_t> active_;
  std::vector<std::vector<cv::Mat>> pyramid_;
  // The current level's camera, images and point intensities.
  PinholeCamera lcam_;
  const std::vector<cv::Mat>* limg_ = nullptr;
  std::vector<float> lint_;
  std::atomic<long long> image_samples_{0};  // residuals whose image was read (DirectBaSummary::image_samples)

  // Each worker's scratch. Each target's terms are kept apart and summed target by target afterwards, in
  // the one-thread order.
  std::vector<ProjectedList> worker_visible_;
  std::vector<std::vector<Sampled>> worker_sampled_;
  std::vector<std::vector<Eigen::Matrix3d>> worker_target_from_host_;

  // The cost's scratch.
  std::vector<Eigen::Vector3d> eval_world_;
  ProjectedList eval_visible_{0};     // one target's
  std::vector<Sampled> eval_values_;  // their image values (the gradients unused)
  std::vector<std::vector<EvalTerm>> eval_terms_;
  DirectBaSummary summary_;
  // linearise_from_evaluation: two slots of per-target samples, the current state's (valid when its
  // evaluation read the images of the current level) and a trial's.
  bool reuse_samples_ = false;
  std::vector<TargetSamples> sample_slots_[2];
  int current_slot_ = 0;
  bool current_samples_valid_ = false;
  // The current state's residual count and sum of squares, and its residuals above the outlier threshold
  // (point * num_kf + target); a trial's.
  int count_ = 0;
  double sq_ = 0;
  std::vector<int> over_, trial_over_;

  // Per point: the Hessian of its inverse depth, its gradient, and its coupling with the poses.
  std::vector<double> hpp_, bp_;
  std::vector<Eigen::VectorXd> hcp_;
  // touched_[point * num_kf + k]: the point's coupling hcp_ has a (possibly) non-zero segment for pose k
  // (a residual hosted or observed there); it is exactly zero elsewhere.
  std::vector<uint8_t> touched_;
  std::vector<int> segments_;           // scratch: the offsets of a point's touched segments, ascending
  std::vector<PairSums> pairs_;         // [target * num_kf + host]
  std::vector<Eigen::Vector3d> world_;  // scratch: the points in the world
  std::vector<uint8_t> point_ok_;
  ProjectedList lin_visible_{0};      // scratch: one target's residuals
  std::vector<Sampled> lin_sampled_;  // scratch: their image values and gradients
  std::vector<Eigen::Matrix3d> lin_target_from_host_;
  std::vector<std::vector<KTerm>> k_terms_;
  std::vector<std::vector<LinTerm>> lin_terms_;
  std::vector<int> lin_term_index_;
  std::vector<double> hinv0_, hinv_;
  std::vector<double> h_pk_;  // relit, K estimated
};

}  // namespace internal
}  // namespace prism
