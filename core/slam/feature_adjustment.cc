#include "core/slam/feature_adjustment.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <sstream>

#include <Eigen/Cholesky>
#include <Eigen/SVD>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>

#include "core/util/thread_pool.h"

namespace prism {

Status FeatureAdjustmentOptions::Check() const {
  std::ostringstream e;
  if (max_features < 16) e << "FeatureAdjustmentOptions.max_features = " << max_features << "; violated: >= 16";
  else if (!(contrast_threshold > 0 && contrast_threshold < 1))
    e << "FeatureAdjustmentOptions.contrast_threshold = " << contrast_threshold << "; violated: in (0, 1)";
  else if (!(min_local_mean >= 0 && min_local_mean <= 255))
    e << "FeatureAdjustmentOptions.min_local_mean = " << min_local_mean << "; violated: in [0, 255]";
  else if (!(ratio > 0 && ratio <= 1)) e << "FeatureAdjustmentOptions.ratio = " << ratio << "; violated: in (0, 1]";
  else if (!(ransac_threshold_px > 0))
    e << "FeatureAdjustmentOptions.ransac_threshold_px = " << ransac_threshold_px << "; violated: > 0";
  else if (min_pair_matches < 8)
    e << "FeatureAdjustmentOptions.min_pair_matches = " << min_pair_matches << "; violated: >= 8";
  else if (!(max_pair_angle_deg > 0 && max_pair_angle_deg <= 180))
    e << "FeatureAdjustmentOptions.max_pair_angle_deg = " << max_pair_angle_deg << "; violated: in (0, 180]";
  else if (!(huber_px > 0)) e << "FeatureAdjustmentOptions.huber_px = " << huber_px << "; violated: > 0";
  else if (!(outlier_px > huber_px))
    e << "FeatureAdjustmentOptions.outlier_px = " << outlier_px << "; violated: > huber_px";
  else if (max_iterations < 1 || max_iterations > 500)
    e << "FeatureAdjustmentOptions.max_iterations = " << max_iterations << "; violated: in [1, 500]";
  else if (!(function_tolerance > 0))
    e << "FeatureAdjustmentOptions.function_tolerance = " << function_tolerance << "; violated: > 0";
  else if (!(min_triangulation_angle_deg >= 0 && min_triangulation_angle_deg < 180))
    e << "FeatureAdjustmentOptions.min_triangulation_angle_deg = " << min_triangulation_angle_deg
      << "; violated: in [0, 180)";
  if (e.str().empty()) return Status::Ok();
  return InvalidArgumentError(e.str());
}

namespace {

struct KeyframeFeatures {
  std::vector<cv::Point2f> points;
  cv::Mat descriptors;  // CV_32F, one row per point
};

KeyframeFeatures DetectFeatures(const FeatureImage& k, const FeatureAdjustmentOptions& options) {
  cv::Mat j8, mask;
  k.grey_j.convertTo(j8, CV_8U);  // saturates to [0, 255]
  mask = k.local_mean >= options.min_local_mean;
  cv::Ptr<cv::SIFT> sift = cv::SIFT::create(0, 3, options.contrast_threshold);
  std::vector<cv::KeyPoint> keypoints;
  sift->detect(j8, keypoints, mask);
  // The strongest max_features, in an order that does not depend on OpenCV's threads (ties by position,
  // size and angle), then their descriptors.
  std::sort(keypoints.begin(), keypoints.end(), [](const cv::KeyPoint& a, const cv::KeyPoint& b) {
    if (a.response != b.response) return a.response > b.response;
    if (a.pt.y != b.pt.y) return a.pt.y < b.pt.y;
    if (a.pt.x != b.pt.x) return a.pt.x < b.pt.x;
    if (a.size != b.size) return a.size < b.size;
    if (a.angle != b.angle) return a.angle < b.angle;
    return a.octave < b.octave;
  });
  if (static_cast<int>(keypoints.size()) > options.max_features)
    keypoints.resize(static_cast<size_t>(options.max_features));
  KeyframeFeatures f;
  if (keypoints.empty()) return f;
  sift->compute(j8, keypoints, f.descriptors);
  f.points.reserve(keypoints.size());
  for (const cv::KeyPoint& kp : keypoints) f.points.push_back(kp.pt);
  return f;
}

// Matches of a keyframe pair (feature indices in a and b) that pass the ratio test and a RANSAC
// fundamental matrix; empty when too few do.
std::vector<std::pair<int, int>> MatchPair(const KeyframeFeatures& a, const KeyframeFeatures& b,
                                           const FeatureAdjustmentOptions& options) {
  std::vector<std::pair<int, int>> out;
  if (a.descriptors.rows < options.min_pair_matches || b.descriptors.rows < 2) return out;
  cv::BFMatcher matcher(cv::NORM_L2);
  std::vector<std::vector<cv::DMatch>> knn;
  matcher.knnMatch(a.descriptors, b.descriptors, knn, 2);
  std::vector<cv::Point2f> pa, pb;
  std::vector<std::pair<int, int>> candidates;
  for (const std::vector<cv::DMatch>& m : knn) {
    if (m.size() < 2 || !(m[0].distance < options.ratio * m[1].distance)) continue;
    candidates.emplace_back(m[0].queryIdx, m[0].trainIdx);
    pa.push_back(a.points[static_cast<size_t>(m[0].queryIdx)]);
    pb.push_back(b.points[static_cast<size_t>(m[0].trainIdx)]);
  }
  if (static_cast<int>(candidates.size()) < options.min_pair_matches) return out;
  std::vector<uint8_t> inlier;
  const cv::Mat f = cv::findFundamentalMat(pa, pb, cv::FM_RANSAC, options.ransac_threshold_px, 0.999, inlier);
  if (f.empty() || inlier.size() != candidates.size()) return out;
  for (size_t i = 0; i < candidates.size(); ++i)
    if (inlier[i]) out.push_back(candidates[i]);
  if (static_cast<int>(out.size()) < options.min_pair_matches) out.clear();
  return out;
}

int Find(std::vector<int>& parent, int x) {
  while (parent[static_cast<size_t>(x)] != x) {
    parent[static_cast<size_t>(x)] = parent[static_cast<size_t>(parent[static_cast<size_t>(x)])];
    x = parent[static_cast<size_t>(x)];
  }
  return x;
}

struct Observation {
  int keyframe = 0;
  int track = 0;
  Eigen::Vector2d pixel;
};

struct Pose {
  Eigen::Matrix3d rotation;  // world_from_camera
  Eigen::Vector3d centre;
};

Eigen::Vector3d Triangulate(const PinholeCamera& camera, const std::vector<Pose>& poses,
                            const std::vector<const Observation*>& obs) {
  Eigen::MatrixXd a(2 * obs.size(), 4);
  const Eigen::Matrix3d k = camera.K();
  for (size_t i = 0; i < obs.size(); ++i) {
    const Pose& p = poses[static_cast<size_t>(obs[i]->keyframe)];
    Eigen::Matrix<double, 3, 4> proj;
    proj.leftCols<3>() = p.rotation.transpose();
    proj.col(3) = -p.rotation.transpose() * p.centre;
    proj = k * proj;
    a.row(static_cast<Eigen::Index>(2 * i)) = obs[i]->pixel.x() * proj.row(2) - proj.row(0);
    a.row(static_cast<Eigen::Index>(2 * i + 1)) = obs[i]->pixel.y() * proj.row(2) - proj.row(1);
  }
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(a, Eigen::ComputeFullV);
  const Eigen::Vector4d x = svd.matrixV().col(3);
  if (std::abs(x(3)) < 1e-15) return Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  return x.head<3>() / x(3);
}

Eigen::Matrix3d Skew(const Eigen::Vector3d& a) {
  Eigen::Matrix3d s;
  s << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
  return s;
}

double Huber(double e, double h) { return e <= h ? 0.5 * e * e : h * (e - 0.5 * h); }

// The adjustment over the observations marked `use` (the tracks' points in `points`).
class Solver {
 public:
  Solver(const PinholeCamera& camera, const FeatureAdjustmentOptions& options, std::vector<Pose>* poses,
         std::vector<Eigen::Vector3d>* points, const std::vector<Observation>* obs, const std::vector<uint8_t>* use)
      : camera_(camera), options_(options), poses_(poses), points_(points), obs_(obs), use_(use) {
    const int n = static_cast<int>(poses->size());
    offset_.assign(static_cast<size_t>(n), -1);
    dim_ = 0;
    for (int k = 1; k < n; ++k) {
      offset_[static_cast<size_t>(k)] = dim_;
      dim_ += k == 1 ? 5 : 6;
    }
    // Keyframe 1's centre moves only across the baseline (the scale's gauge).
    baseline_length_ = ((*poses)[1].centre - (*poses)[0].centre).norm();
    const Eigen::Vector3d baseline = ((*poses)[1].centre - (*poses)[0].centre).normalized();
    Eigen::Vector3d any = std::abs(baseline.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
    const Eigen::Vector3d e1 = baseline.cross(any).normalized();
    const Eigen::Vector3d e2 = baseline.cross(e1);
    across_.col(0) = e1;
    across_.col(1) = e2;
    by_track_.assign(points->size(), {});
    for (size_t i = 0; i < obs->size(); ++i)
      if ((*use)[i]) by_track_[static_cast<size_t>((*obs)[i].track)].push_back(static_cast<int>(i));
  }

  double Cost(const std::vector<Pose>& poses, const std::vector<Eigen::Vector3d>& points) const {
    double cost = 0;
    for (size_t i = 0; i < obs_->size(); ++i) {
      if (!(*use_)[i]) continue;
      const Observation& o = (*obs_)[i];
      const Pose& p = poses[static_cast<size_t>(o.keyframe)];
      const Eigen::Vector3d x = p.rotation.transpose() * (points[static_cast<size_t>(o.track)] - p.centre);
      if (!(x.z() > 1e-9)) {
        cost += Huber(1e3, options_.huber_px);
        continue;
      }
      cost += Huber((Project(x) - o.pixel).norm(), options_.huber_px);
    }
    return cost;
  }

  // Returns the iterations run.
  int Solve() {
    double cost = Cost(*poses_, *points_);
    double lambda = 1e-4;
    int it = 0;
    for (; it < options_.max_iterations; ++it) {
      Linearise();
      bool accepted = false;
      while (!accepted) {
        std::vector<Pose> trial_poses;
        std::vector<Eigen::Vector3d> trial_points;
        if (!Step(lambda, &trial_poses, &trial_points)) return it;
        const double trial = Cost(trial_poses, trial_points);
        if (trial < cost) {
          const double decrease = (cost - trial) / std::max(cost, 1e-300);
          *poses_ = std::move(trial_poses);
          *points_ = std::move(trial_points);
          cost = trial;
          lambda = std::max(1e-10, lambda / 3);
          accepted = true;
          if (decrease < options_.function_tolerance) return it + 1;
        } else {
          lambda *= 5;
          if (lambda > 1e8) return it + 1;
        }
      }
    }
    return it;
  }

 private:
  Eigen::Vector2d Project(const Eigen::Vector3d& x) const {
    return Eigen::Vector2d(camera_.fx * x.x() / x.z() + camera_.cx, camera_.fy * x.y() / x.z() + camera_.cy);
  }

  // d residual / d (parameters of keyframe k): the right rotation perturbation and the centre, through the
  // keyframe's basis (keyframe 1: the centre across the baseline).
  Eigen::Matrix<double, 2, 6> PoseJacobian(const Eigen::Matrix<double, 2, 3>& d_proj, const Pose& p,
                                           const Eigen::Vector3d& x) const {
    Eigen::Matrix<double, 2, 6> j;
    j.leftCols<3>() = d_proj * Skew(x);
    j.rightCols<3>() = -d_proj * p.rotation.transpose();
    return j;
  }

  void Linearise() {
    hcc_ = Eigen::MatrixXd::Zero(dim_, dim_);
    bc_ = Eigen::VectorXd::Zero(dim_);
    const size_t np = points_->size();
    hpp_.assign(np, Eigen::Matrix3d::Zero());
    bp_.assign(np, Eigen::Vector3d::Zero());
    hcp_.assign(obs_->size(), Eigen::Matrix<double, 6, 3>::Zero());
    for (size_t t = 0; t < np; ++t) {
      for (int i : by_track_[t]) {
        const Observation& o = (*obs_)[static_cast<size_t>(i)];
        const Pose& p = (*poses_)[static_cast<size_t>(o.keyframe)];
        const Eigen::Vector3d x = p.rotation.transpose() * ((*points_)[t] - p.centre);
        if (!(x.z() > 1e-9)) continue;
        const Eigen::Vector2d r = Project(x) - o.pixel;
        const double e = r.norm();
        const double w = e <= options_.huber_px ? 1.0 : options_.huber_px / e;
        Eigen::Matrix<double, 2, 3> d_proj;
        d_proj << camera_.fx / x.z(), 0, -camera_.fx * x.x() / (x.z() * x.z()), 0, camera_.fy / x.z(),
            -camera_.fy * x.y() / (x.z() * x.z());
        const Eigen::Matrix<double, 2, 3> jx = d_proj * p.rotation.transpose();
        hpp_[t] += w * jx.transpose() * jx;
        bp_[t] += w * jx.transpose() * r;
        const int off = offset_[static_cast<size_t>(o.keyframe)];
        if (off < 0) continue;
        Eigen::Matrix<double, 2, 6> jc = PoseJacobian(d_proj, p, x);
        const int d = o.keyframe == 1 ? 5 : 6;
        if (o.keyframe == 1) {
          // The centre's two directions across the baseline.
          const Eigen::Matrix<double, 2, 2> across = jc.rightCols<3>() * across_;
          jc.middleCols<2>(3) = across;
          jc.col(5).setZero();
        }
        hcc_.block(off, off, d, d) += w * jc.leftCols(d).transpose() * jc.leftCols(d);
        bc_.segment(off, d) += w * jc.leftCols(d).transpose() * r;
        hcp_[static_cast<size_t>(i)].topRows(d) = w * jc.leftCols(d).transpose() * jx;
      }
    }
  }

  bool Step(double lambda, std::vector<Pose>* poses, std::vector<Eigen::Vector3d>* points) const {
    Eigen::MatrixXd s = hcc_;
    for (int d = 0; d < dim_; ++d) s(d, d) += lambda * std::max(1e-9, hcc_(d, d));
    Eigen::VectorXd g = bc_;
    const size_t np = points_->size();
    std::vector<Eigen::Matrix3d> hinv(np);
    for (size_t t = 0; t < np; ++t) {
      Eigen::Matrix3d h = hpp_[t];
      for (int d = 0; d < 3; ++d) h(d, d) += lambda * std::max(1e-9, hpp_[t](d, d)) + 1e-12;
      hinv[t] = h.inverse();
      const std::vector<int>& track = by_track_[t];
      for (int i : track) {
        const Observation& a = (*obs_)[static_cast<size_t>(i)];
        const int oa = offset_[static_cast<size_t>(a.keyframe)];
        if (oa < 0) continue;
        const int da = a.keyframe == 1 ? 5 : 6;
        const Eigen::Matrix<double, 6, 3> ta = hcp_[static_cast<size_t>(i)] * hinv[t];
        g.segment(oa, da) -= (ta * bp_[t]).head(da);
        for (int j : track) {
          const Observation& b = (*obs_)[static_cast<size_t>(j)];
          const int ob = offset_[static_cast<size_t>(b.keyframe)];
          if (ob < 0) continue;
          const int db = b.keyframe == 1 ? 5 : 6;
          s.block(oa, ob, da, db) -= (ta * hcp_[static_cast<size_t>(j)].transpose()).topLeftCorner(da, db);
        }
      }
    }
    const Eigen::LDLT<Eigen::MatrixXd> ldlt(s);
    if (ldlt.info() != Eigen::Success) return false;
    const Eigen::VectorXd dc = ldlt.solve(-g);
    if (!dc.allFinite()) return false;
    *poses = *poses_;
    for (size_t k = 1; k < poses->size(); ++k) {
      const int off = offset_[k];
      Pose& p = (*poses)[k];
      const Eigen::Vector3d w = dc.segment<3>(off);
      const Eigen::Vector3d dcentre =
          k == 1 ? Eigen::Vector3d(across_ * dc.segment<2>(off + 3)) : Eigen::Vector3d(dc.segment<3>(off + 3));
      p.rotation = p.rotation * ExpSo3(w).toRotationMatrix();
      p.centre += dcentre;
    }
    // The step moved keyframe 1 across the baseline only; its distance from keyframe 0 (the scale) is
    // kept exactly.
    const Eigen::Vector3d c0 = (*poses)[0].centre, d = (*poses)[1].centre - c0;
    (*poses)[1].centre = c0 + d * (baseline_length_ / d.norm());
    *points = *points_;
    for (size_t t = 0; t < np; ++t) {
      Eigen::Vector3d rhs = -bp_[t];
      for (int i : by_track_[t]) {
        const Observation& o = (*obs_)[static_cast<size_t>(i)];
        const int off = offset_[static_cast<size_t>(o.keyframe)];
        if (off < 0) continue;
        const int d = o.keyframe == 1 ? 5 : 6;
        rhs -= hcp_[static_cast<size_t>(i)].topRows(d).transpose() * dc.segment(off, d);
      }
      (*points)[t] += hinv[t] * rhs;
    }
    return true;
  }

  const PinholeCamera& camera_;
  const FeatureAdjustmentOptions& options_;
  std::vector<Pose>* poses_;
  std::vector<Eigen::Vector3d>* points_;
  const std::vector<Observation>* obs_;
  const std::vector<uint8_t>* use_;
  std::vector<int> offset_;  // per keyframe, its parameters' first index (-1: held)
  int dim_ = 0;
  Eigen::Matrix<double, 3, 2> across_;
  double baseline_length_ = 0;
  std::vector<std::vector<int>> by_track_;
  Eigen::MatrixXd hcc_;
  Eigen::VectorXd bc_;
  std::vector<Eigen::Matrix3d> hpp_;
  std::vector<Eigen::Vector3d> bp_;
  std::vector<Eigen::Matrix<double, 6, 3>> hcp_;  // per observation, its keyframe's rows (top 5 for keyframe 1)
};

// Reprojection errors of the used observations.
std::vector<double> Errors(const PinholeCamera& camera, const std::vector<Pose>& poses,
                           const std::vector<Eigen::Vector3d>& points, const std::vector<Observation>& obs,
                           const std::vector<uint8_t>& use) {
  std::vector<double> e;
  for (size_t i = 0; i < obs.size(); ++i) {
    if (!use[i]) continue;
    const Pose& p = poses[static_cast<size_t>(obs[i].keyframe)];
    const Eigen::Vector3d x = p.rotation.transpose() * (points[static_cast<size_t>(obs[i].track)] - p.centre);
    e.push_back(x.z() > 1e-9
                    ? (Eigen::Vector2d(camera.fx * x.x() / x.z() + camera.cx, camera.fy * x.y() / x.z() + camera.cy) -
                       obs[i].pixel)
                          .norm()
                    : 1e3);
  }
  return e;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return v[v.size() / 2];
}

double Rms(const std::vector<double>& v) {
  if (v.empty()) return 0;
  double s = 0;
  for (double x : v) s += x * x;
  return std::sqrt(s / static_cast<double>(v.size()));
}

}  // namespace

StatusOr<FeatureTracks> BuildFeatureTracks(const PinholeCamera& camera, const FeatureAdjustmentOptions& options,
                                           const std::vector<FeatureImage>& images,
                                           const std::vector<Sim3d>& world_from_keyframe, ThreadPool* pool,
                                           const std::function<bool(int, int)>& pair_filter) {
  PRISM_RETURN_IF_ERROR(options.Check());
  const int n = static_cast<int>(images.size());
  if (n < 3) return InvalidArgumentError("BuildFeatureTracks: needs at least 3 keyframes");
  if (world_from_keyframe.size() != images.size())
    return InvalidArgumentError("BuildFeatureTracks: one pose per image");
  for (const FeatureImage& k : images)
    if (k.grey_j.type() != CV_32F || k.local_mean.type() != CV_32F || k.grey_j.cols != camera.width ||
        k.grey_j.rows != camera.height || k.local_mean.size() != k.grey_j.size())
      return InvalidArgumentError("BuildFeatureTracks: J and its local mean must be CV_32F of the camera's size");

  std::vector<KeyframeFeatures> features(static_cast<size_t>(n));
  auto detect = [&](std::ptrdiff_t k) {
    features[static_cast<size_t>(k)] = DetectFeatures(images[static_cast<size_t>(k)], options);
  };
  if (pool) pool->ParallelFor(0, n, detect);
  else
    for (int k = 0; k < n; ++k) detect(k);

  std::vector<std::pair<int, int>> pairs;
  const double min_axis_cos = std::cos(options.max_pair_angle_deg * M_PI / 180);
  for (int a = 0; a < n; ++a)
    for (int b = a + 1; b < n; ++b) {
      const Eigen::Vector3d za = world_from_keyframe[static_cast<size_t>(a)].rotation * Eigen::Vector3d::UnitZ();
      const Eigen::Vector3d zb = world_from_keyframe[static_cast<size_t>(b)].rotation * Eigen::Vector3d::UnitZ();
      if (za.dot(zb) >= min_axis_cos && (!pair_filter || pair_filter(a, b))) pairs.emplace_back(a, b);
    }
  std::vector<std::vector<std::pair<int, int>>> matches(pairs.size());
  auto match = [&](std::ptrdiff_t i) {
    const auto [a, b] = pairs[static_cast<size_t>(i)];
    matches[static_cast<size_t>(i)] =
        MatchPair(features[static_cast<size_t>(a)], features[static_cast<size_t>(b)], options);
  };
  if (pool) pool->ParallelFor(0, static_cast<std::ptrdiff_t>(pairs.size()), match);
  else
    for (size_t i = 0; i < pairs.size(); ++i) match(static_cast<std::ptrdiff_t>(i));

  FeatureTracks out;
  out.num_keyframes = n;
  out.pairs_tried = static_cast<int>(pairs.size());
  std::vector<int> first(static_cast<size_t>(n) + 1, 0);
  for (int k = 0; k < n; ++k)
    first[static_cast<size_t>(k) + 1] =
        first[static_cast<size_t>(k)] + static_cast<int>(features[static_cast<size_t>(k)].points.size());
  out.features = first.back();
  // Union-find over all features: a match joins two; each set's smallest index is its root.
  std::vector<int> parent(static_cast<size_t>(first.back()));
  std::iota(parent.begin(), parent.end(), 0);
  for (size_t i = 0; i < pairs.size(); ++i) {
    if (matches[i].empty()) continue;
    ++out.pairs_matched;
    const auto [a, b] = pairs[i];
    for (const auto& [fa, fb] : matches[i]) {
      const int ra = Find(parent, first[static_cast<size_t>(a)] + fa);
      const int rb = Find(parent, first[static_cast<size_t>(b)] + fb);
      if (ra != rb) parent[static_cast<size_t>(std::max(ra, rb))] = std::min(ra, rb);
    }
  }
  // The sets with two features or more, in keyframe order; one with two features in one keyframe is
  // ambiguous and left out.
  std::vector<int> set_of_root(parent.size(), -1);
  std::vector<std::vector<FeatureTracks::Observation>> sets;
  for (int k = 0; k < n; ++k)
    for (int f = 0; f < first[static_cast<size_t>(k) + 1] - first[static_cast<size_t>(k)]; ++f) {
      const int root = Find(parent, first[static_cast<size_t>(k)] + f);
      int& t = set_of_root[static_cast<size_t>(root)];
      if (t < 0) {
        t = static_cast<int>(sets.size());
        sets.emplace_back();
      }
      const cv::Point2f& p = features[static_cast<size_t>(k)].points[static_cast<size_t>(f)];
      sets[static_cast<size_t>(t)].push_back({k, p.x, p.y});
    }
  for (std::vector<FeatureTracks::Observation>& t : sets) {
    if (t.size() < 2) continue;
    bool repeated = false;
    for (size_t i = 1; i < t.size(); ++i) repeated |= t[i].keyframe == t[i - 1].keyframe;
    if (!repeated) out.tracks.push_back(std::move(t));
  }
  return out;
}

StatusOr<FeatureAdjustmentSummary> AdjustKeyframesByFeatures(const PinholeCamera& camera,
                                                             const FeatureAdjustmentOptions& options,
                                                             const FeatureTracks& tracks,
                                                             std::vector<Sim3d>* world_from_keyframe) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (camera.HasDistortion()) return InvalidArgumentError("AdjustKeyframesByFeatures: the camera has distortion");
  const int n = static_cast<int>(world_from_keyframe->size());
  if (n < 3 || n != tracks.num_keyframes)
    return InvalidArgumentError("AdjustKeyframesByFeatures: needs the tracks' keyframes' poses (at least 3)");
  if (!((*world_from_keyframe)[1].translation - (*world_from_keyframe)[0].translation).allFinite() ||
      ((*world_from_keyframe)[1].translation - (*world_from_keyframe)[0].translation).norm() <= 1e-12)
    return FailedPreconditionError("AdjustKeyframesByFeatures: keyframes 0 and 1 coincide (no scale gauge)");
  FeatureAdjustmentSummary summary;
  summary.features = tracks.features;
  summary.pairs_matched = tracks.pairs_matched;

  std::vector<Pose> poses(static_cast<size_t>(n));
  for (int k = 0; k < n; ++k) {
    const Sim3d& s = (*world_from_keyframe)[static_cast<size_t>(k)];
    poses[static_cast<size_t>(k)] = {s.rotation.toRotationMatrix(), s.translation};
  }
  std::vector<Observation> obs;
  std::vector<Eigen::Vector3d> points;
  const double min_angle_cos = std::cos(options.min_triangulation_angle_deg * M_PI / 180);
  for (const std::vector<FeatureTracks::Observation>& t : tracks.tracks) {
    std::vector<Observation> track_obs;
    const int track = static_cast<int>(points.size());
    bool valid = true;
    for (const FeatureTracks::Observation& o : t) {
      valid &= o.keyframe >= 0 && o.keyframe < n;
      track_obs.push_back({o.keyframe, track, Eigen::Vector2d(o.u, o.v)});
    }
    if (!valid) return InvalidArgumentError("AdjustKeyframesByFeatures: a track's keyframe is out of range");
    std::vector<const Observation*> ptrs;
    for (const Observation& o : track_obs) ptrs.push_back(&o);
    const Eigen::Vector3d x = Triangulate(camera, poses, ptrs);
    if (!x.allFinite()) continue;
    // In front of every camera, and rays spanning at least the minimum angle.
    bool in_front = true;
    double widest = 1.0;
    for (const Observation& o : track_obs) {
      const Pose& p = poses[static_cast<size_t>(o.keyframe)];
      in_front &= (p.rotation.transpose() * (x - p.centre)).z() > 0;
      for (const Observation& q : track_obs)
        widest = std::min(
            widest, (x - p.centre).normalized().dot((x - poses[static_cast<size_t>(q.keyframe)].centre).normalized()));
    }
    if (!in_front || widest > min_angle_cos) continue;
    points.push_back(x);
    obs.insert(obs.end(), track_obs.begin(), track_obs.end());
  }
  constexpr int kMinTracks = 30;
  if (static_cast<int>(points.size()) < kMinTracks)
    return FailedPreconditionError("AdjustKeyframesByFeatures: " + std::to_string(points.size()) +
                                   " tracks triangulated, fewer than " + std::to_string(kMinTracks));
  // The start's errors may be several pixels on long tracks (that is what the adjustment corrects): the
  // first solve keeps every observation within ten outlier thresholds, the second those within one after
  // the first; a track left with fewer than two observations is left out.
  std::vector<uint8_t> use(obs.size(), 1);
  auto keep_within = [&](double limit) {
    const std::vector<double> all = Errors(camera, poses, points, obs, std::vector<uint8_t>(obs.size(), 1));
    std::vector<int> count(points.size(), 0);
    for (size_t i = 0; i < obs.size(); ++i) {
      use[i] = all[i] <= limit;
      count[static_cast<size_t>(obs[i].track)] += use[i];
    }
    for (size_t i = 0; i < obs.size(); ++i)
      if (count[static_cast<size_t>(obs[i].track)] < 2) use[i] = 0;
  };
  // Tracks with at least two observations in use.
  auto tracks_in_use = [&]() {
    std::vector<uint8_t> used(points.size(), 0);
    for (size_t i = 0; i < obs.size(); ++i)
      if (use[i]) used[static_cast<size_t>(obs[i].track)] = 1;
    return static_cast<int>(std::count(used.begin(), used.end(), 1));
  };
  auto too_few = [&](const char* when) {
    return FailedPreconditionError("AdjustKeyframesByFeatures: " + std::to_string(tracks_in_use()) + " tracks " + when +
                                   ", fewer than " + std::to_string(kMinTracks));
  };
  const std::vector<Pose> start_poses = poses;
  const std::vector<Eigen::Vector3d> start_points = points;
  keep_within(10 * options.outlier_px);
  if (tracks_in_use() < kMinTracks) return too_few("within ten outlier thresholds at the start");
  for (int solve = 0; solve < 2; ++solve) {
    Solver solver(camera, options, &poses, &points, &obs, &use);
    summary.iterations += solver.Solve();
    if (solve == 0) {
      keep_within(options.outlier_px);
      if (tracks_in_use() < kMinTracks) return too_few("within the outlier threshold after the first solve");
    }
  }
  // The start's and the end's errors over the same observations: those of the final solve.
  {
    const std::vector<double> e0 = Errors(camera, start_poses, start_points, obs, use);
    summary.initial_rms_px = Rms(e0);
    summary.initial_median_px = Median(e0);
  }
  const std::vector<double> e = Errors(camera, poses, points, obs, use);
  summary.final_rms_px = Rms(e);
  summary.final_median_px = Median(e);
  summary.observations = static_cast<int>(e.size());
  std::vector<uint8_t> track_used(points.size(), 0);
  summary.observations_by_keyframe.assign(static_cast<size_t>(n), {});
  for (size_t i = 0; i < obs.size(); ++i) {
    if (!use[i]) continue;
    track_used[static_cast<size_t>(obs[i].track)] = 1;
    const Pose& p = poses[static_cast<size_t>(obs[i].keyframe)];
    const Eigen::Vector3d x = p.rotation.transpose() * (points[static_cast<size_t>(obs[i].track)] - p.centre);
    summary.observations_by_keyframe[static_cast<size_t>(obs[i].keyframe)].push_back(
        {static_cast<float>(obs[i].pixel.x()), static_cast<float>(obs[i].pixel.y()), x.z()});
  }
  summary.tracks = static_cast<int>(std::count(track_used.begin(), track_used.end(), 1));
  summary.mean_track_length = summary.tracks ? static_cast<double>(summary.observations) / summary.tracks : 0.0;
  for (int k = 1; k < n; ++k) {
    Sim3d& s = (*world_from_keyframe)[static_cast<size_t>(k)];
    s.rotation = Eigen::Quaterniond(poses[static_cast<size_t>(k)].rotation).normalized();
    s.translation = poses[static_cast<size_t>(k)].centre;
  }
  return summary;
}

}  // namespace prism
