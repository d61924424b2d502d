// The only translation unit of prism that includes PCL's registration headers (they take ~20 s to
// compile); keep it that way.
// GCC 12 reports -Warray-bounds false positives inside Eigen's SSE loads of 3-vectors, inlined from
// PCL's SVD / point-to-plane estimators (the location is a system header, the check runs after
// inlining, so -isystem does not silence it). Off for this file only, before any include
// (the pragma state is looked up at the warning's location, inside <xmmintrin.h>).
#pragma GCC diagnostic ignored "-Warray-bounds"
#include "core/mapping/icp.h"

#include <algorithm>
#include <cmath>
#include <exception>
#include <limits>
#include <memory>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <utility>
#include <vector>

#include <Eigen/Eigenvalues>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/registration/gicp.h>
#include <pcl/registration/icp.h>
#include <pcl/search/kdtree.h>

namespace prism {
namespace {

using PclPoint = pcl::PointNormal;  // one point type for every method: the kd-tree uses x y z only
using PclCloud = pcl::PointCloud<PclPoint>;
using PclTree = pcl::search::KdTree<PclPoint>;
using Gicp = pcl::GeneralizedIterativeClosestPoint<PclPoint, PclPoint>;
using Covariances = Gicp::MatricesVector;

// GICP's BFGS stopping gradient (translation and rotation), see AlignIcp.
constexpr double kGicpGradientTolerance = 1e-7;

// Exposes what PCL keeps protected: the iteration count and GICP's covariance computation.
template <typename Base>
class Instrumented : public Base {
 public:
  int iterations() const { return this->nr_iterations_; }
};

class GicpInstrumented : public Instrumented<Gicp> {
 public:
  using Gicp::computeCovariances;
};

bool IsFinite(const Eigen::Vector3f& v) { return std::isfinite(v.x()) && std::isfinite(v.y()) && std::isfinite(v.z()); }

bool HasValidNormal(const Eigen::Vector3f& n) { return IsFinite(n) && n.squaredNorm() > 0.25f; }

std::string OptionError(const char* field, double value, const char* rule) {
  std::ostringstream s;
  s << field << " = " << value << "; violated: " << rule;
  return s.str();
}

PclPoint ToPcl(const Eigen::Vector3f& p, const Eigen::Vector3f& n) {
  PclPoint q;
  q.getVector3fMap() = p;
  q.data[3] = 1.0f;
  q.getNormalVector3fMap() = n;
  q.data_n[3] = 0.0f;
  q.curvature = 0.0f;
  return q;
}

// Finite source positions, voxel-downsampled (centroid per voxel, in first-seen order) when
// source_voxel_m > 0, then a seeded random subset of at most max_source_points (0 = all), in input
// order.
std::vector<Eigen::Vector3f> SelectSourcePoints(const PointCloud& source, const IcpOptions& options) {
  std::vector<Eigen::Vector3f> points;
  if (options.source_voxel_m > 0.0) {
    points.reserve(source.size());
    // Cell indices must stay exact in int64; farther points are dropped like non-finite ones.
    const double inv = 1.0 / options.source_voxel_m;
    constexpr double kMaxCell = 4e18;
    struct Cell {
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      int count = 0;
    };
    struct KeyHash {
      size_t operator()(const Eigen::Matrix<int64_t, 3, 1>& k) const {
        uint64_t h = static_cast<uint64_t>(k.x()) * 0x9E3779B97F4A7C15ull;
        h ^= static_cast<uint64_t>(k.y()) * 0xC2B2AE3D27D4EB4Full + (h << 6) + (h >> 2);
        h ^= static_cast<uint64_t>(k.z()) * 0x165667B19E3779F9ull + (h << 6) + (h >> 2);
        return static_cast<size_t>(h);
      }
    };
    std::unordered_map<Eigen::Matrix<int64_t, 3, 1>, size_t, KeyHash> index;
    std::vector<Cell> cells;
    for (const Eigen::Vector3f& p : source.positions) {
      if (!IsFinite(p)) continue;
      const Eigen::Vector3d c = (p.cast<double>() * inv).array().floor();
      if (c.cwiseAbs().maxCoeff() > kMaxCell) continue;
      const auto [it, inserted] = index.emplace(c.cast<int64_t>(), cells.size());
      if (inserted) cells.emplace_back();
      Cell& cell = cells[it->second];
      cell.sum += p.cast<double>();
      ++cell.count;
    }
    for (const Cell& cell : cells) points.push_back((cell.sum / cell.count).cast<float>());
  } else if (options.max_source_points > 0 && source.size() > static_cast<size_t>(options.max_source_points)) {
    // Floyd's sampling of distinct indices: O(max_points), not O(cloud size); non-finite picks are
    // dropped, so a few points fewer may remain.
    const size_t m = static_cast<size_t>(options.max_source_points);
    const size_t n = source.size();
    std::mt19937 rng(options.seed);
    std::unordered_set<size_t> picked;
    picked.reserve(2 * m);
    for (size_t j = n - m; j < n; ++j) {
      const size_t t = std::uniform_int_distribution<size_t>(0, j)(rng);
      picked.insert(picked.count(t) ? j : t);
    }
    std::vector<size_t> order(picked.begin(), picked.end());
    std::sort(order.begin(), order.end());  // memory order: cache-friendlier queries
    for (size_t i : order) {
      if (IsFinite(source.positions[i])) points.push_back(source.positions[i]);
    }
    return points;
  } else {
    points.reserve(source.size());
    for (const Eigen::Vector3f& p : source.positions) {
      if (IsFinite(p)) points.push_back(p);
    }
  }
  const size_t max_points = static_cast<size_t>(options.max_source_points);
  if (max_points > 0 && points.size() > max_points) {
    // Partial Fisher-Yates over indices, then back to input order (cache-friendlier queries).
    std::vector<uint32_t> order(points.size());
    std::iota(order.begin(), order.end(), 0u);
    std::mt19937 rng(options.seed);
    for (size_t i = 0; i < max_points; ++i) {
      std::uniform_int_distribution<size_t> pick(i, order.size() - 1);
      std::swap(order[i], order[pick(rng)]);
    }
    order.resize(max_points);
    std::sort(order.begin(), order.end());
    std::vector<Eigen::Vector3f> subset;
    subset.reserve(max_points);
    for (uint32_t i : order) subset.push_back(points[i]);
    points = std::move(subset);
  }
  return points;
}

}  // namespace

const char* IcpMethodName(IcpMethod method) {
  switch (method) {
    case IcpMethod::kPointToPoint:
      return "point-to-point";
    case IcpMethod::kPointToPlane:
      return "point-to-plane";
    case IcpMethod::kGeneralized:
      return "generalized";
  }
  return "unknown";
}

Status IcpOptions::Check() const {
  if (method != IcpMethod::kPointToPoint && method != IcpMethod::kPointToPlane && method != IcpMethod::kGeneralized) {
    return InvalidArgumentError(OptionError("IcpOptions.method", static_cast<int>(method), "a known IcpMethod"));
  }
  if (!(max_correspondence_distance_m > 0.0) || !std::isfinite(max_correspondence_distance_m)) {
    return InvalidArgumentError(
        OptionError("IcpOptions.max_correspondence_distance_m", max_correspondence_distance_m, "in (0, inf)"));
  }
  if (max_iterations < 1) {
    return InvalidArgumentError(OptionError("IcpOptions.max_iterations", max_iterations, ">= 1"));
  }
  if (!(refine_correspondence_distance_m >= 0.0 && refine_correspondence_distance_m <= max_correspondence_distance_m)) {
    return InvalidArgumentError(OptionError("IcpOptions.refine_correspondence_distance_m",
                                            refine_correspondence_distance_m, "in [0, max_correspondence_distance_m]"));
  }
  if (!(transformation_epsilon >= 0.0) || !std::isfinite(transformation_epsilon)) {
    return InvalidArgumentError(OptionError("IcpOptions.transformation_epsilon", transformation_epsilon, ">= 0"));
  }
  if (!(euclidean_fitness_epsilon >= 0.0) || !std::isfinite(euclidean_fitness_epsilon)) {
    return InvalidArgumentError(OptionError("IcpOptions.euclidean_fitness_epsilon", euclidean_fitness_epsilon, ">= 0"));
  }
  if (!(source_voxel_m >= 0.0) || !std::isfinite(source_voxel_m)) {
    return InvalidArgumentError(OptionError("IcpOptions.source_voxel_m", source_voxel_m, ">= 0"));
  }
  if (max_source_points < 0) {
    return InvalidArgumentError(OptionError("IcpOptions.max_source_points", max_source_points, ">= 0"));
  }
  if (gicp_k_neighbors < 3 || gicp_k_neighbors > 100) {
    return InvalidArgumentError(OptionError("IcpOptions.gicp_k_neighbors", gicp_k_neighbors, "in [3, 100]"));
  }
  return Status::Ok();
}

Status NormalEstimationOptions::Check() const {
  if (k_neighbors < 3 || k_neighbors > 100) {
    return InvalidArgumentError(OptionError("NormalEstimationOptions.k_neighbors", k_neighbors, "in [3, 100]"));
  }
  if (!(max_radius_m > 0.0) || !std::isfinite(max_radius_m)) {
    return InvalidArgumentError(OptionError("NormalEstimationOptions.max_radius_m", max_radius_m, "in (0, inf)"));
  }
  return Status::Ok();
}

struct IcpTarget::Impl {
  // The cloud is stored relative to its centroid: ICP then rotates about the data rather than about
  // a far-away origin (better conditioned steps, esp. for GICP's BFGS) and float coordinates stay small.
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  IcpMethod method = IcpMethod::kPointToPlane;
  int gicp_k_neighbors = 0;
  size_t dropped = 0;
  PclCloud::Ptr cloud;
  PclTree::Ptr tree;
  // kGeneralized only. Read-only after Create (GICP reads target covariances, never writes them).
  std::shared_ptr<Covariances> covariances;
};

StatusOr<IcpTarget> IcpTarget::Create(const PointCloud& target, const IcpOptions& options) {
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!target.IsConsistent()) {
    return InvalidArgumentError("ICP target: attribute arrays do not match the number of positions");
  }
  if (target.empty()) return InvalidArgumentError("ICP target: empty cloud");
  const bool need_normals = options.method == IcpMethod::kPointToPlane;
  if (need_normals && !target.HasNormals()) {
    return InvalidArgumentError("ICP target: point-to-plane ICP needs target normals, the cloud has none");
  }

  auto impl = std::make_shared<Impl>();
  impl->method = options.method;
  impl->gicp_k_neighbors = options.gicp_k_neighbors;
  impl->cloud.reset(new PclCloud);
  impl->cloud->reserve(target.size());
  const Eigen::Vector3f zero = Eigen::Vector3f::Zero();
  for (size_t i = 0; i < target.size(); ++i) {
    const Eigen::Vector3f& p = target.positions[i];
    if (!IsFinite(p)) continue;
    if (need_normals) {
      const Eigen::Vector3f& n = target.normals[i];
      if (!HasValidNormal(n)) continue;
      impl->cloud->push_back(ToPcl(p, n.normalized()));
    } else {
      impl->cloud->push_back(ToPcl(p, target.HasNormals() && IsFinite(target.normals[i]) ? target.normals[i] : zero));
    }
  }
  impl->dropped = target.size() - impl->cloud->size();
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const PclPoint& q : *impl->cloud) sum += q.getVector3fMap().cast<double>();
  if (!impl->cloud->empty()) impl->origin = sum / static_cast<double>(impl->cloud->size());
  const Eigen::Vector3f origin = impl->origin.cast<float>();
  impl->origin = origin.cast<double>();  // exactly what is subtracted below
  for (PclPoint& q : *impl->cloud) q.getVector3fMap() -= origin;
  if (impl->cloud->empty()) {
    return InvalidArgumentError(need_normals ? "ICP target: no finite point with a valid normal"
                                             : "ICP target: no finite point");
  }
  if (options.method == IcpMethod::kGeneralized &&
      impl->cloud->size() < static_cast<size_t>(options.gicp_k_neighbors)) {
    return InvalidArgumentError(
        "ICP target: generalized ICP needs at least gicp_k_neighbors = " + std::to_string(options.gicp_k_neighbors) +
        " finite points, got " + std::to_string(impl->cloud->size()));
  }
  impl->cloud->is_dense = true;
  try {
    impl->tree.reset(new PclTree);
    impl->tree->setInputCloud(impl->cloud);
    if (options.method == IcpMethod::kGeneralized) {
      GicpInstrumented gicp;
      gicp.setCorrespondenceRandomness(options.gicp_k_neighbors);
      impl->covariances = std::make_shared<Covariances>(impl->cloud->size());
      gicp.computeCovariances<PclPoint>(impl->cloud, impl->tree, *impl->covariances);
    }
  } catch (const std::exception& e) {
    return InternalError(std::string("ICP target: PCL failed: ") + e.what());
  }
  return IcpTarget(std::move(impl));
}

size_t IcpTarget::size() const { return impl_->cloud->size(); }
size_t IcpTarget::dropped_points() const { return impl_->dropped; }
IcpMethod IcpTarget::method() const { return impl_->method; }
int IcpTarget::gicp_k_neighbors() const { return impl_->gicp_k_neighbors; }

StatusOr<IcpSummary> AlignIcp(const PointCloud& source, const IcpTarget& target,
                              const Rigid3d& target_from_source_guess, const IcpOptions& options,
                              Rigid3d* target_from_source) {
  PRISM_CHECK(target_from_source != nullptr);
  PRISM_RETURN_IF_ERROR(options.Check());
  const IcpTarget::Impl& tgt = *target.impl_;
  if (tgt.method != options.method) {
    return InvalidArgumentError(std::string("ICP: the target was built for ") + IcpMethodName(tgt.method) +
                                " ICP, the options ask for " + IcpMethodName(options.method));
  }
  if (options.method == IcpMethod::kGeneralized && tgt.gicp_k_neighbors != options.gicp_k_neighbors) {
    return InvalidArgumentError("ICP: the target was built with another gicp_k_neighbors");
  }
  if (!source.IsConsistent()) {
    return InvalidArgumentError("ICP source: attribute arrays do not match the number of positions");
  }
  if (source.empty()) return InvalidArgumentError("ICP source: empty cloud");
  if (!target_from_source_guess.rotation.coeffs().allFinite() || !target_from_source_guess.translation.allFinite()) {
    return InvalidArgumentError("ICP: the initial guess is not finite");
  }

  std::vector<Eigen::Vector3f> points = SelectSourcePoints(source, options);
  if (points.empty()) return InvalidArgumentError("ICP source: no finite point");
  if (options.method == IcpMethod::kGeneralized && points.size() < static_cast<size_t>(options.gicp_k_neighbors)) {
    return InvalidArgumentError(
        "ICP source: generalized ICP needs at least gicp_k_neighbors = " + std::to_string(options.gicp_k_neighbors) +
        " points, got " + std::to_string(points.size()));
  }
  // The source is centred too (small float coordinates, exact enough covariances for GICP): ICP
  // estimates centred_target_from_centred_source = T(-target origin) * guess * T(source origin).
  Eigen::Vector3d source_sum = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3f& p : points) source_sum += p.cast<double>();
  const Eigen::Vector3f source_origin_f = (source_sum / static_cast<double>(points.size())).cast<float>();
  const Eigen::Vector3d source_origin = source_origin_f.cast<double>();
  for (Eigen::Vector3f& p : points) p -= source_origin_f;
  PclCloud::Ptr pcl_source(new PclCloud);
  pcl_source->reserve(points.size());
  for (const Eigen::Vector3f& p : points) pcl_source->push_back(ToPcl(p, Eigen::Vector3f::Zero()));
  pcl_source->is_dense = true;

  Eigen::Matrix4d centred_guess = target_from_source_guess.ToMatrix();
  centred_guess.topRightCorner<3, 1>() += centred_guess.topLeftCorner<3, 3>() * source_origin - tgt.origin;
  const Eigen::Matrix4f guess = centred_guess.cast<float>();
  IcpSummary summary;
  Eigen::Matrix4f result = guess;
  // One ICP run at a correspondence distance, from `result`, updating it and the summary.
  auto run_pass = [&](double max_distance_m) {
    PclCloud aligned;
    const Eigen::Matrix4f start = result;
    if (options.method == IcpMethod::kGeneralized) {
      GicpInstrumented gicp;
      gicp.setCorrespondenceRandomness(options.gicp_k_neighbors);
      gicp.setMaxCorrespondenceDistance(max_distance_m);
      gicp.setMaximumIterations(options.max_iterations);
      gicp.setTransformationEpsilon(std::sqrt(options.transformation_epsilon));
      gicp.setRotationEpsilon(std::sqrt(2.0 * options.transformation_epsilon));
      // PCL's covariances have unit (1 m^2) variance along the surface, so a tangential residual d
      // yields a gradient of ~d: the default BFGS tolerances (1e-2) stop at centimetre errors.
      gicp.setTranslationGradientTolerance(kGicpGradientTolerance);
      gicp.setRotationGradientTolerance(kGicpGradientTolerance);
      gicp.setSearchMethodTarget(tgt.tree, /*force_no_recompute=*/true);
      gicp.setInputTarget(tgt.cloud);
      gicp.setTargetCovariances(tgt.covariances);  // after setInputTarget, which resets them
      gicp.setInputSource(pcl_source);
      gicp.align(aligned, start);
      summary.iterations += gicp.iterations();
      summary.converged = gicp.hasConverged() && gicp.iterations() < options.max_iterations;
      result = gicp.getFinalTransformation();
      return;
    }
    using Icp = pcl::IterativeClosestPoint<PclPoint, PclPoint>;
    using IcpNormals = pcl::IterativeClosestPointWithNormals<PclPoint, PclPoint>;
    std::unique_ptr<Icp> icp;
    int (*iterations)(const Icp&) = nullptr;
    if (options.method == IcpMethod::kPointToPlane) {
      icp = std::make_unique<Instrumented<IcpNormals>>();
      iterations = [](const Icp& r) { return static_cast<const Instrumented<IcpNormals>&>(r).iterations(); };
    } else {
      icp = std::make_unique<Instrumented<Icp>>();
      iterations = [](const Icp& r) { return static_cast<const Instrumented<Icp>&>(r).iterations(); };
    }
    icp->setMaxCorrespondenceDistance(max_distance_m);
    icp->setMaximumIterations(options.max_iterations);
    icp->setTransformationEpsilon(options.transformation_epsilon);
    icp->setEuclideanFitnessEpsilon(options.euclidean_fitness_epsilon > 0.0 ? options.euclidean_fitness_epsilon
                                                                            : -std::numeric_limits<double>::max());
    icp->setSearchMethodTarget(tgt.tree, /*force_no_recompute=*/true);
    icp->setInputTarget(tgt.cloud);
    icp->setInputSource(pcl_source);
    icp->align(aligned, start);
    using Criteria = pcl::registration::DefaultConvergenceCriteria<float>;
    const Criteria::ConvergenceState state = icp->getConvergeCriteria()->getConvergenceState();
    summary.converged = icp->hasConverged() && (state == Criteria::CONVERGENCE_CRITERIA_TRANSFORM ||
                                                state == Criteria::CONVERGENCE_CRITERIA_ABS_MSE ||
                                                state == Criteria::CONVERGENCE_CRITERIA_REL_MSE);
    summary.iterations += iterations(*icp);
    result = icp->getFinalTransformation();
  };
  try {
    run_pass(options.max_correspondence_distance_m);
    // The refinement only makes sense from a converged first pass.
    if (options.refine_correspondence_distance_m > 0.0 && summary.converged) {
      run_pass(options.refine_correspondence_distance_m);
    }
  } catch (const std::exception& e) {
    return InternalError(std::string("ICP: PCL failed: ") + e.what());
  }
  if (!result.allFinite()) return InternalError("ICP: PCL returned a non-finite transformation");

  // Residuals at the result: one nearest-neighbour query per used source point.
  const double max_sq = options.max_correspondence_distance_m * options.max_correspondence_distance_m;
  double sum_sq = 0.0, inlier_sum_sq = 0.0;
  size_t inliers = 0;
  pcl::Indices nn_index(1);
  std::vector<float> nn_sq(1);
  const Eigen::Matrix3f r = result.topLeftCorner<3, 3>();
  const Eigen::Vector3f t = result.topRightCorner<3, 1>();
  for (const Eigen::Vector3f& p : points) {
    PclPoint q = ToPcl(r * p + t, Eigen::Vector3f::Zero());
    if (tgt.tree->nearestKSearch(q, 1, nn_index, nn_sq) < 1) continue;
    sum_sq += nn_sq[0];
    if (nn_sq[0] <= max_sq) {
      inlier_sum_sq += nn_sq[0];
      ++inliers;
    }
  }
  summary.source_points = points.size();
  summary.fitness_mean_sq_m2 = sum_sq / static_cast<double>(points.size());
  summary.inlier_fraction = static_cast<double>(inliers) / static_cast<double>(points.size());
  summary.inlier_rmse_m = inliers > 0 ? std::sqrt(inlier_sum_sq / static_cast<double>(inliers)) : 0.0;

  // Back from the centred frames, re-orthonormalising the float rotation.
  const Eigen::Matrix4d m = result.cast<double>();
  const Eigen::Quaterniond q = Eigen::Quaterniond(Eigen::Matrix3d(m.topLeftCorner<3, 3>())).normalized();
  *target_from_source = Rigid3d(q, m.topRightCorner<3, 1>() - q * source_origin + tgt.origin);
  return summary;
}

StatusOr<IcpSummary> AlignIcp(const PointCloud& source, const PointCloud& target,
                              const Rigid3d& target_from_source_guess, const IcpOptions& options,
                              Rigid3d* target_from_source) {
  PRISM_ASSIGN_OR_RETURN(const IcpTarget icp_target, IcpTarget::Create(target, options));
  return AlignIcp(source, icp_target, target_from_source_guess, options, target_from_source);
}

StatusOr<size_t> FillMissingNormals(const Eigen::Vector3d& viewpoint, const NormalEstimationOptions& options,
                                    PointCloud* cloud) {
  PRISM_CHECK(cloud != nullptr);
  PRISM_RETURN_IF_ERROR(options.Check());
  if (!cloud->IsConsistent()) {
    return InvalidArgumentError("FillMissingNormals: attribute arrays do not match the number of positions");
  }
  if (!viewpoint.allFinite()) return InvalidArgumentError("FillMissingNormals: viewpoint is not finite");
  if (cloud->empty()) return size_t{0};
  if (!cloud->HasNormals()) cloud->normals.assign(cloud->size(), Eigen::Vector3f::Zero());

  // Every finite point is a neighbour candidate; pcl_index maps back to the cloud.
  PclCloud::Ptr pcl_cloud(new PclCloud);
  std::vector<size_t> to_cloud;
  pcl_cloud->reserve(cloud->size());
  to_cloud.reserve(cloud->size());
  bool any_missing = false;
  for (size_t i = 0; i < cloud->size(); ++i) {
    if (!IsFinite(cloud->positions[i])) continue;
    pcl_cloud->push_back(ToPcl(cloud->positions[i], Eigen::Vector3f::Zero()));
    to_cloud.push_back(i);
    any_missing = any_missing || !HasValidNormal(cloud->normals[i]);
  }
  if (!any_missing) return size_t{0};
  pcl_cloud->is_dense = true;

  size_t filled = 0;
  try {
    PclTree tree;
    tree.setInputCloud(pcl_cloud);
    const float max_sq = static_cast<float>(options.max_radius_m * options.max_radius_m);
    pcl::Indices nn_index;
    std::vector<float> nn_sq;
    for (size_t j = 0; j < to_cloud.size(); ++j) {
      Eigen::Vector3f& normal = cloud->normals[to_cloud[j]];
      if (HasValidNormal(normal)) continue;
      normal.setZero();
      const int found = tree.nearestKSearch((*pcl_cloud)[j], options.k_neighbors, nn_index, nn_sq);
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      int count = 0;
      for (int k = 0; k < found; ++k) {
        if (nn_sq[k] > max_sq) continue;
        mean += (*pcl_cloud)[nn_index[k]].getVector3fMap().cast<double>();
        ++count;
      }
      if (count < 3) continue;
      mean /= count;
      Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
      for (int k = 0; k < found; ++k) {
        if (nn_sq[k] > max_sq) continue;
        const Eigen::Vector3d d = (*pcl_cloud)[nn_index[k]].getVector3fMap().cast<double>() - mean;
        cov += d * d.transpose();
      }
      const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(cov);
      Eigen::Vector3d n = eig.eigenvectors().col(0);  // smallest eigenvalue first
      // A line or a single repeated point has no plane: leave the normal missing.
      if (!(eig.eigenvalues()(1) > 1e-12 * std::max(1.0, eig.eigenvalues()(2))) || !n.allFinite()) continue;
      if (n.dot(viewpoint - cloud->positions[to_cloud[j]].cast<double>()) < 0.0) n = -n;
      normal = n.normalized().cast<float>();
      ++filled;
    }
  } catch (const std::exception& e) {
    return InternalError(std::string("FillMissingNormals: PCL failed: ") + e.what());
  }
  return filled;
}

}  // namespace prism
