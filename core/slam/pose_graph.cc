#include "core/slam/pose_graph.h"

#include <cmath>
#include <string>

#include <Eigen/Geometry>
#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>

namespace prism {
namespace {

using Vector7d = Eigen::Matrix<double, 7, 1>;

Eigen::Vector3d LogSo3(const Eigen::Quaterniond& q) {
  const Eigen::AngleAxisd aa(q.normalized());
  double angle = aa.angle();
  Eigen::Vector3d axis = aa.axis();
  if (angle > M_PI) {  // the short way round
    angle = 2 * M_PI - angle;
    axis = -axis;
  }
  return angle * axis;
}

// T * Exp(delta), delta = (rotation, translation, log-scale).
Sim3d Retract(const Sim3d& t, const Vector7d& delta) {
  const Sim3d d(std::exp(delta(6)), ExpSo3(delta.head<3>()), delta.segment<3>(3));
  return t * d;
}

Vector7d EdgeResidual(const PoseGraphEdge& e, const Sim3d& world_from_i, const Sim3d& world_from_j) {
  const Sim3d err = e.from_from_to.Inverse() * (world_from_i.Inverse() * world_from_j);
  Vector7d r;
  r.head<3>() = LogSo3(err.rotation) / e.rotation_sigma;
  r.segment<3>(3) = err.translation / e.translation_sigma;
  r(6) = std::log(err.scale) / e.log_scale_sigma;
  return r;
}

double Cost(const std::vector<PoseGraphEdge>& edges, const std::vector<Sim3d>& nodes) {
  double c = 0;
  for (const PoseGraphEdge& e : edges)
    c += 0.5 * EdgeResidual(e, nodes[static_cast<size_t>(e.from)], nodes[static_cast<size_t>(e.to)]).squaredNorm();
  return c;
}

}  // namespace

Status PoseGraphOptions::Check() const {
  if (max_iterations < 1 || max_iterations > 1000)
    return InvalidArgumentError("PoseGraphOptions.max_iterations = " + std::to_string(max_iterations) +
                                "; violated: in [1, 1000]");
  if (!(relative_tolerance > 0 && relative_tolerance < 1))
    return InvalidArgumentError("PoseGraphOptions.relative_tolerance = " + std::to_string(relative_tolerance) +
                                "; violated: in (0, 1)");
  return Status::Ok();
}

StatusOr<PoseGraphSummary> OptimisePoseGraph(const std::vector<PoseGraphEdge>& edges, const PoseGraphOptions& options,
                                             std::vector<Sim3d>* world_from_node, const std::vector<bool>& fixed_in) {
  PRISM_RETURN_IF_ERROR(options.Check());
  std::vector<Sim3d>& nodes = *world_from_node;
  const int n = static_cast<int>(nodes.size());
  if (n == 0) return InvalidArgumentError("OptimisePoseGraph: no nodes");
  if (!fixed_in.empty() && static_cast<int>(fixed_in.size()) != n)
    return InvalidArgumentError("OptimisePoseGraph: `fixed` must be empty or have one flag per node");
  for (const Sim3d& t : nodes)
    if (!(t.scale > 0) || !std::isfinite(t.scale) || !t.translation.allFinite())
      return InvalidArgumentError("OptimisePoseGraph: node with a non-positive or non-finite scale or translation");
  for (const PoseGraphEdge& e : edges) {
    if (e.from < 0 || e.to < 0 || e.from >= n || e.to >= n || e.from == e.to)
      return InvalidArgumentError("OptimisePoseGraph: edge " + std::to_string(e.from) + " -> " + std::to_string(e.to) +
                                  " names a missing node (or itself); " + std::to_string(n) + " nodes");
    if (!(e.rotation_sigma > 0 && e.translation_sigma > 0 && e.log_scale_sigma > 0))
      return InvalidArgumentError("OptimisePoseGraph: edge sigmas must be > 0");
    if (!(e.from_from_to.scale > 0) || !std::isfinite(e.from_from_to.scale))
      return InvalidArgumentError("OptimisePoseGraph: edge scale must be finite and > 0");
  }
  std::vector<bool> fixed = fixed_in;
  if (fixed.empty()) {
    fixed.assign(static_cast<size_t>(n), false);
    fixed[0] = true;
  }
  // Column block of each free node, -1 when fixed.
  std::vector<int> block(static_cast<size_t>(n), -1);
  int free_nodes = 0;
  for (int i = 0; i < n; ++i)
    if (!fixed[static_cast<size_t>(i)]) block[static_cast<size_t>(i)] = free_nodes++;

  PoseGraphSummary summary;
  summary.initial_cost = summary.final_cost = Cost(edges, nodes);
  if (free_nodes == 0 || edges.empty()) return summary;
  const int dim = 7 * free_nodes;
  double lambda = 1e-4;
  constexpr double kStep = 1e-6;
  for (int iteration = 0; iteration < options.max_iterations; ++iteration) {
    std::vector<Eigen::Triplet<double>> triplets;
    Eigen::VectorXd g = Eigen::VectorXd::Zero(dim);
    for (const PoseGraphEdge& e : edges) {
      const int ends[2] = {e.from, e.to};
      const Sim3d& ti = nodes[static_cast<size_t>(e.from)];
      const Sim3d& tj = nodes[static_cast<size_t>(e.to)];
      const Vector7d r = EdgeResidual(e, ti, tj);
      // Numeric Jacobians (central differences) with respect to both ends' 7-vectors.
      Eigen::Matrix<double, 7, 7> jac[2];
      for (int side = 0; side < 2; ++side) {
        if (block[static_cast<size_t>(ends[side])] < 0) continue;
        for (int k = 0; k < 7; ++k) {
          Vector7d d = Vector7d::Zero();
          d(k) = kStep;
          const Vector7d plus = side == 0 ? EdgeResidual(e, Retract(ti, d), tj) : EdgeResidual(e, ti, Retract(tj, d));
          const Vector7d minus =
              side == 0 ? EdgeResidual(e, Retract(ti, -d), tj) : EdgeResidual(e, ti, Retract(tj, -d));
          jac[side].col(k) = (plus - minus) / (2 * kStep);
        }
      }
      for (int a = 0; a < 2; ++a) {
        const int ba = block[static_cast<size_t>(ends[a])];
        if (ba < 0) continue;
        g.segment<7>(7 * ba) += jac[a].transpose() * r;
        for (int b = 0; b < 2; ++b) {
          const int bb = block[static_cast<size_t>(ends[b])];
          if (bb < 0) continue;
          const Eigen::Matrix<double, 7, 7> h = jac[a].transpose() * jac[b];
          for (int x = 0; x < 7; ++x)
            for (int y = 0; y < 7; ++y) triplets.emplace_back(7 * ba + x, 7 * bb + y, h(x, y));
        }
      }
    }
    Eigen::SparseMatrix<double> h(dim, dim);
    h.setFromTriplets(triplets.begin(), triplets.end());
    const Eigen::VectorXd diagonal = h.diagonal();
    bool improved = false;
    for (int attempt = 0; attempt < 10 && !improved; ++attempt) {
      Eigen::SparseMatrix<double> damped = h;
      for (int i = 0; i < dim; ++i) damped.coeffRef(i, i) += lambda * std::max(diagonal(i), 1e-9) + 1e-12;
      Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(damped);
      if (solver.info() != Eigen::Success) {
        lambda *= 10;
        continue;
      }
      const Eigen::VectorXd step = solver.solve(-g);
      std::vector<Sim3d> candidate = nodes;
      for (int i = 0; i < n; ++i) {
        const int b = block[static_cast<size_t>(i)];
        if (b >= 0) candidate[static_cast<size_t>(i)] = Retract(nodes[static_cast<size_t>(i)], step.segment<7>(7 * b));
      }
      const double cost = Cost(edges, candidate);
      if (cost < summary.final_cost) {
        const double decrease = (summary.final_cost - cost) / std::max(summary.final_cost, 1e-300);
        nodes = std::move(candidate);
        summary.final_cost = cost;
        lambda = std::max(lambda / 10, 1e-9);
        improved = true;
        summary.iterations = iteration + 1;
        if (decrease < options.relative_tolerance) return summary;
      } else {
        lambda *= 10;
      }
    }
    if (!improved) break;
  }
  return summary;
}

}  // namespace prism
