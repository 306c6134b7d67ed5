#include "libccmd/optim/pose_graph.h"

#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

Pose CirclePose(int i, int n) {
  const double a = 2 * M_PI * i / n;
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(a + M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(2 * std::cos(a), 2 * std::sin(a), 0.2 * std::sin(3 * a));
  return T;
}

TEST(PoseGraphTest, ClosesADriftedLoop) {
  // Ground truth: 40 poses on a circle. Odometry edges carry a small systematic error, so
  // chaining them drifts; one loop edge (exact) ties the last pose to the first.
  const int n = 40;
  std::vector<Pose> truth;
  for (int i = 0; i < n; ++i) truth.push_back(CirclePose(i, n));
  Pose bias = Pose::Identity();
  bias.linear() =
      Eigen::AngleAxisd(0.004, Eigen::Vector3d(0.3, 0.1, 1).normalized()).toRotationMatrix();
  bias.translation() = Eigen::Vector3d(0.004, -0.002, 0.001);
  std::vector<PoseGraphEdge> edges;
  std::vector<PoseGraphNode> nodes(n);
  nodes[0].T_world_node = truth[0];
  nodes[0].fixed = true;
  for (int i = 1; i < n; ++i) {
    PoseGraphEdge e;
    e.a = i - 1;
    e.b = i;
    e.T_a_b = truth[i - 1].inverse() * truth[i] * bias;
    edges.push_back(e);
    nodes[i].T_world_node = nodes[i - 1].T_world_node * e.T_a_b;  // dead reckoning
  }
  const double drift_before = TranslationDistance(nodes[n - 1].T_world_node, truth[n - 1]);
  ASSERT_GT(drift_before, 0.1);
  PoseGraphEdge loop;
  loop.a = n - 1;
  loop.b = 0;
  loop.T_a_b = truth[n - 1].inverse() * truth[0];
  loop.sqrt_info_rotation = loop.sqrt_info_translation = 10.0;  // trusted more than odometry
  edges.push_back(loop);
  auto summary = OptimizePoseGraph(&nodes, edges);
  ASSERT_TRUE(summary.ok()) << summary.status().ToString();
  double worst = 0;
  for (int i = 0; i < n; ++i)
    worst = std::max(worst, TranslationDistance(nodes[i].T_world_node, truth[i]));
  // The error left is the odometry bias spread around the loop, a fraction of the drift.
  EXPECT_LT(worst, 0.2 * drift_before);
  EXPECT_LT(TranslationDistance(nodes[n - 1].T_world_node, truth[n - 1]), 0.02);
  EXPECT_LT(summary->final_cost, summary->initial_cost);
  EXPECT_LT(TranslationDistance(nodes[0].T_world_node, truth[0]), 1e-12);  // fixed
}

TEST(PoseGraphTest, ConsistentMeasurementsLeaveTheGraphAlone) {
  const int n = 10;
  std::vector<PoseGraphNode> nodes(n);
  std::vector<PoseGraphEdge> edges;
  for (int i = 0; i < n; ++i) nodes[i].T_world_node = CirclePose(i, n);
  nodes[0].fixed = true;
  for (int i = 1; i < n; ++i) {
    edges.push_back({i - 1, i, CirclePose(i - 1, n).inverse() * CirclePose(i, n)});
  }
  ASSERT_TRUE(OptimizePoseGraph(&nodes, edges).ok());
  for (int i = 0; i < n; ++i)
    EXPECT_LT(TranslationDistance(nodes[i].T_world_node, CirclePose(i, n)), 1e-9);
}

TEST(PoseGraphTest, NeedsAFixedNodeAndValidEdges) {
  std::vector<PoseGraphNode> nodes(2);
  EXPECT_FALSE(OptimizePoseGraph(&nodes, {{0, 1}}).ok());
  nodes[0].fixed = true;
  EXPECT_FALSE(OptimizePoseGraph(&nodes, {{0, 5}}).ok());
}

}  // namespace
}  // namespace ccmd
