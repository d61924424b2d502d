#include "core/slam/pose_graph.h"

#include <cmath>
#include <iostream>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace prism {
namespace {

// A ring of keyframes around a circle (radius 1), camera looking at the centre, as in an orbit.
std::vector<Sim3d> Ring(int n) {
  std::vector<Sim3d> poses;
  for (int i = 0; i < n; ++i) {
    const double a = 2 * M_PI * i / n;
    const Eigen::Quaterniond r(Eigen::AngleAxisd(a, Eigen::Vector3d::UnitY()));
    poses.emplace_back(1.0, r, Eigen::Vector3d(std::sin(a), 0, -std::cos(a)));
  }
  return poses;
}

Sim3d Relative(const Sim3d& world_from_i, const Sim3d& world_from_j) { return world_from_i.Inverse() * world_from_j; }

double MaxPositionError(const std::vector<Sim3d>& a, const std::vector<Sim3d>& b) {
  double e = 0;
  for (size_t i = 0; i < a.size(); ++i) e = std::max(e, (a[i].translation - b[i].translation).norm());
  return e;
}

TEST(PoseGraphTest, RecoversExactPosesFromPerturbedStart) {
  const std::vector<Sim3d> truth = Ring(20);
  std::vector<PoseGraphEdge> edges;
  for (int i = 0; i < 20; ++i) {
    PoseGraphEdge e;
    e.from = i;
    e.to = (i + 1) % 20;
    e.from_from_to = Relative(truth[static_cast<size_t>(e.from)], truth[static_cast<size_t>(e.to)]);
    edges.push_back(e);
  }
  std::vector<Sim3d> nodes = truth;
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0, 0.02);
  for (size_t i = 1; i < nodes.size(); ++i) {
    nodes[i].translation += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    nodes[i].rotation = nodes[i].rotation * Eigen::Quaterniond(Eigen::AngleAxisd(noise(rng), Eigen::Vector3d::UnitX()));
    nodes[i].scale *= std::exp(noise(rng));
  }
  StatusOr<PoseGraphSummary> s = OptimisePoseGraph(edges, PoseGraphOptions(), &nodes);
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_LT(s->final_cost, 1e-12);
  EXPECT_LT(MaxPositionError(nodes, truth), /*max_position_error=*/1e-6);
  for (size_t i = 0; i < nodes.size(); ++i) EXPECT_NEAR(nodes[i].scale, 1.0, 1e-6) << i;
}

// Monocular scale drift: the true size of a keyframe's depth unit shrinks by 2% per keyframe, but
// odometry measures each step in the previous keyframe's units with scale 1 (what tracking sees), and
// turns slightly too little. Chained, the ring does not close. One loop edge from the last keyframe
// to the first, measured by direct alignment (relative pose in the last keyframe's units and the
// ratio of the two keyframes' units), pulls the whole ring back into shape.
TEST(PoseGraphTest, LoopEdgeCorrectsScaleDrift) {
  const int n = 24;
  const std::vector<Sim3d> truth = Ring(n);
  std::vector<double> unit(n);
  for (int i = 0; i < n; ++i) unit[static_cast<size_t>(i)] = std::pow(0.98, i);
  std::vector<PoseGraphEdge> edges;
  std::vector<Sim3d> chained = {truth[0]};
  for (int i = 0; i + 1 < n; ++i) {
    const Sim3d rel = Relative(truth[static_cast<size_t>(i)], truth[static_cast<size_t>(i + 1)]);
    PoseGraphEdge e;
    e.from = i;
    e.to = i + 1;
    e.from_from_to = Sim3d(1.0, rel.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(-0.003, Eigen::Vector3d::UnitY())),
                           rel.translation / unit[static_cast<size_t>(i)]);
    e.log_scale_sigma = 0.02;
    edges.push_back(e);
    chained.push_back(chained.back() * e.from_from_to);
  }
  const double open_error = MaxPositionError(chained, truth);
  const Sim3d rel = Relative(truth[static_cast<size_t>(n - 1)], truth[0]);
  const double last_unit = unit[static_cast<size_t>(n - 1)];
  PoseGraphEdge loop;
  loop.from = n - 1;
  loop.to = 0;
  loop.from_from_to = Sim3d(1.0 / last_unit, rel.rotation, rel.translation / last_unit);
  edges.push_back(loop);
  std::vector<Sim3d> nodes = chained;
  StatusOr<PoseGraphSummary> s = OptimisePoseGraph(edges, PoseGraphOptions(), &nodes);
  ASSERT_TRUE(s.ok()) << s.status();
  const double closed_error = MaxPositionError(nodes, truth);
  std::cout << "open chain max position error " << open_error << ", after the loop edge " << closed_error << " (cost "
            << s->initial_cost << " -> " << s->final_cost << ", " << s->iterations << " iterations)\n";
  EXPECT_GT(open_error, 0.2);
  EXPECT_LT(closed_error, /*max_fraction_of_open_error=*/0.2 * open_error);
  EXPECT_LT(s->final_cost, s->initial_cost);
}

// Nodes marked fixed keep their values; the others follow the edges.
TEST(PoseGraphTest, FixedNodesStay) {
  const std::vector<Sim3d> truth = Ring(6);
  std::vector<PoseGraphEdge> edges;
  for (int i = 0; i + 1 < 6; ++i) {
    PoseGraphEdge e;
    e.from = i;
    e.to = i + 1;
    e.from_from_to = Relative(truth[static_cast<size_t>(i)], truth[static_cast<size_t>(i + 1)]);
    edges.push_back(e);
  }
  std::vector<Sim3d> nodes = truth;
  nodes[3].translation += Eigen::Vector3d(0.1, 0, 0);  // fixed and wrong: the chain bends to it
  nodes[5].translation += Eigen::Vector3d(0, 0.1, 0);  // free: pulled back
  const std::vector<bool> fixed = {true, false, false, true, false, false};
  ASSERT_TRUE(OptimisePoseGraph(edges, PoseGraphOptions(), &nodes, fixed).ok());
  EXPECT_EQ((nodes[3].translation - truth[3].translation - Eigen::Vector3d(0.1, 0, 0)).norm(), 0.0);
  EXPECT_EQ((nodes[0].translation - truth[0].translation).norm(), 0.0);
  // Node 5 hangs off node 4, which hangs off the moved node 3: it follows node 3's error.
  EXPECT_LT((nodes[5].translation - truth[5].translation).norm(), 0.2);
  EXPECT_FALSE(OptimisePoseGraph(edges, PoseGraphOptions(), &nodes, std::vector<bool>(3, false)).ok());
}

TEST(PoseGraphTest, BadInputIsAnError) {
  std::vector<Sim3d> nodes = Ring(3);
  PoseGraphEdge e;
  e.from = 0;
  e.to = 5;
  EXPECT_FALSE(OptimisePoseGraph({e}, PoseGraphOptions(), &nodes).ok());
  e.to = 1;
  e.rotation_sigma = 0;
  EXPECT_FALSE(OptimisePoseGraph({e}, PoseGraphOptions(), &nodes).ok());
  e.rotation_sigma = 0.01;
  e.from_from_to.scale = -1;
  EXPECT_FALSE(OptimisePoseGraph({e}, PoseGraphOptions(), &nodes).ok());
  std::vector<Sim3d> none;
  EXPECT_FALSE(OptimisePoseGraph({}, PoseGraphOptions(), &none).ok());
  PoseGraphOptions bad;
  bad.max_iterations = 0;
  EXPECT_FALSE(OptimisePoseGraph({}, bad, &nodes).ok());
}

}  // namespace
}  // namespace prism
