// Optimisation of a whole server map on generated data: the pose graph spreads a loop's
// correction and leaves a consistent map alone; the global BA moves a perturbed keyframe back,
// carries keyframes that arrived during the solve along, and uses only points seen twice.

#include "libccmd/backend/map_optimization.h"

#include <gtest/gtest.h>

#include <algorithm>

#include "tests/backend/generated_map.h"

namespace ccmd {
namespace {

using testing::AddGeneratedKeyframe;
using testing::CirclePose;
using testing::GeneratedWorld;
using testing::MakeRingWorld;

constexpr double kDegree = M_PI / 180;

GlobalKeyframeId Kf(int keyframe) {
  return {AgentId(1), KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

// 0.2 degrees and 5 mm more per keyframe.
Pose Drift(int i) {
  Pose drift = Pose::Identity();
  drift.linear() =
      Eigen::AngleAxisd(0.2 * kDegree * i, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  drift.translation() = Eigen::Vector3d(0.005 * i, 0, 0.001 * i);
  return drift;
}

TEST(MapPoseGraphTest, ALoopEdgeSpreadsTheCorrectionAndTheOriginStays) {
  Rng rng(21);
  const GeneratedWorld world = MakeRingWorld(1500, &rng);
  constexpr int kSteps = 30;
  ServerMap map(MapId(1));
  for (int i = 0; i < kSteps; ++i) {
    AddGeneratedKeyframe(&map, world, AgentId(1), i, CirclePose(i, kSteps),
                         Drift(i) * CirclePose(i, kSteps), &rng);
  }
  // Keyframe 30 is where keyframe 0 is (the true relative pose is the identity); the agent
  // made new points there.
  AddGeneratedKeyframe(&map, world, AgentId(1), kSteps, CirclePose(0, kSteps),
                       Drift(kSteps) * CirclePose(0, kSteps), &rng, /*local_window=*/kSteps - 5);
  map.AddLoopEdge({Kf(0), Kf(kSteps), Pose::Identity()});
  const double before =
      TranslationDistance(map.keyframe(Kf(kSteps))->T_map_cam, CirclePose(0, kSteps));
  ASSERT_GT(before, 0.15);

  auto moved = OptimizeMapPoseGraph(&map);
  ASSERT_TRUE(moved.ok()) << moved.status().ToString();
  EXPECT_EQ(moved->size(), static_cast<std::size_t>(kSteps));  // all but the origin
  EXPECT_EQ(std::count(moved->begin(), moved->end(), map.keyframe(Kf(0))), 0);
  EXPECT_LT(TranslationDistance(map.keyframe(Kf(0))->T_map_cam, CirclePose(0, kSteps)), 1e-9);
  // The loop edge (sigma 5 mm) competes with about five covisibility edges per keyframe
  // (sigma 1 cm), measured on the drifted map: the graph removes most of the error at the
  // loop, not all of it (the global BA that follows a loop does the rest).
  const Pose end = map.keyframe(Kf(kSteps))->T_map_cam;
  EXPECT_LT(TranslationDistance(end, CirclePose(0, kSteps)), 0.5 * before);
  EXPECT_LT(RotationDistance(end, CirclePose(0, kSteps)),
            0.5 * RotationDistance(Drift(kSteps) * CirclePose(0, kSteps), CirclePose(0, kSteps)));
  // The second half, where the drift is largest, is closer to the truth than it was.
  double error_before = 0, error_after = 0;
  for (int i = kSteps / 2; i < kSteps; ++i) {
    error_before += TranslationDistance(Drift(i) * CirclePose(i, kSteps), CirclePose(i, kSteps));
    error_after += TranslationDistance(map.keyframe(Kf(i))->T_map_cam, CirclePose(i, kSteps));
  }
  EXPECT_LT(error_after, 0.8 * error_before);
}

TEST(MapPoseGraphTest, AConsistentMapIsLeftAlone) {
  Rng rng(22);
  const GeneratedWorld world = MakeRingWorld(1500, &rng);
  ServerMap map(MapId(1));
  for (int i = 0; i < 12; ++i) {
    AddGeneratedKeyframe(&map, world, AgentId(1), i, CirclePose(i, 30),
                         Drift(i) * CirclePose(i, 30), &rng);
  }
  // A loop edge that agrees with the map as it is.
  map.AddLoopEdge(
      {Kf(2), Kf(9), map.keyframe(Kf(2))->T_map_cam.inverse() * map.keyframe(Kf(9))->T_map_cam});
  auto moved = OptimizeMapPoseGraph(&map);
  ASSERT_TRUE(moved.ok());
  for (ServerKeyframe* kf : *moved) {
    const int i = static_cast<int>(kf->id.keyframe.value());
    EXPECT_LT(TranslationDistance(kf->T_map_cam, Drift(i) * CirclePose(i, 30)), 1e-6) << i;
  }
}

// An agent that lost tracking at keyframe 15 restarted there, 30 cm and 8 degrees off, with
// new points (a map segment of its own, rigid); keyframe 30, back where keyframe 0 is, closes
// a loop. Across the restart the two keyframes are tied only loosely, so the graph moves the
// gap and the segment comes back whole; tied as any consecutive pair (the flag ignored), the
// correction bends both segments and the second stays far off.
double RestartedSegmentErrorAfterLoop(bool flagged) {
  Rng rng(25);
  const GeneratedWorld world = MakeRingWorld(1500, &rng);
  constexpr int kSteps = 30, kRestart = 15;
  Pose off = Pose::Identity();
  off.linear() = Eigen::AngleAxisd(8 * kDegree, Eigen::Vector3d::UnitY()).toRotationMatrix();
  off.translation() = Eigen::Vector3d(0.3, 0.0, -0.1);
  ServerMap map(MapId(1));
  for (int i = 0; i <= kSteps; ++i) {
    const Pose truth = CirclePose(i % kSteps, kSteps);
    ServerKeyframe* kf =
        AddGeneratedKeyframe(&map, world, AgentId(1), i, truth, i < kRestart ? truth : off * truth,
                             &rng, i < kRestart ? std::nullopt : std::optional<int>(kRestart));
    kf->restart = flagged && i == kRestart;
    if (i == kRestart) kf->parent.reset();
  }
  map.AddLoopEdge({Kf(0), Kf(kSteps), Pose::Identity()});
  EXPECT_TRUE(OptimizeMapPoseGraph(&map).ok());
  double worst = 0;
  for (int i = kRestart; i <= kSteps; ++i) {
    worst = std::max(
        worst, TranslationDistance(map.keyframe(Kf(i))->T_map_cam, CirclePose(i % kSteps, kSteps)));
  }
  return worst;
}

TEST(MapPoseGraphTest, ALoopMovesARestartedSegmentWhole) {
  const double flagged = RestartedSegmentErrorAfterLoop(true);
  const double ignored = RestartedSegmentErrorAfterLoop(false);
  EXPECT_LT(flagged, 0.005) << "ignored: " << ignored;
  EXPECT_GT(ignored, 0.05);
}

// Before any loop nothing measures where a restarted segment lies: the global BA's loose tie
// holds it where the agent put it (no gauge freedom: the solve converges and moves nothing).
TEST(GlobalBaTest, ARestartedSegmentStaysWhereItsAgentPutIt) {
  Rng rng(26);
  const GeneratedWorld world = MakeRingWorld(2500, &rng);
  constexpr int kSteps = 40, kRestart = 5;
  Pose off = Pose::Identity();
  off.translation() = Eigen::Vector3d(0.2, 0.05, 0.0);
  ServerMap map(MapId(1));
  for (int i = 0; i < 10; ++i) {
    const Pose truth = CirclePose(i, kSteps);
    ServerKeyframe* kf =
        AddGeneratedKeyframe(&map, world, AgentId(1), i, truth, i < kRestart ? truth : off * truth,
                             &rng, i < kRestart ? std::nullopt : std::optional<int>(kRestart));
    kf->restart = i == kRestart;
  }
  std::map<AgentId, PinholeCamera> cameras = {{AgentId(1), testing::TestCamera()}};
  GlobalBaProblem problem = BuildGlobalBa(map, cameras, DepthNoise());
  ASSERT_EQ(problem.problem.relative_poses.size(), 1u);
  EXPECT_EQ(problem.problem.relative_poses[0].camera_a, 4);
  EXPECT_EQ(problem.problem.relative_poses[0].camera_b, 5);
  BaOptions ba;
  ba.solver = BaLinearSolver::kSparseSchur;
  ba.first_iterations = ba.second_iterations = 10;
  BundleAdjust(&problem.problem, ba);
  ApplyGlobalBa(&map, problem);
  for (int i = 0; i < 10; ++i) {
    const Pose placed = i < kRestart ? CirclePose(i, kSteps) : off * CirclePose(i, kSteps);
    EXPECT_LT(TranslationDistance(map.keyframe(Kf(i))->T_map_cam, placed), 0.002) << i;
  }
}

// Each agent's depths are weighed with its own sensor's noise (announced in its handshake),
// the others' with the fallback.
TEST(GlobalBaTest, DepthsAreWeighedWithTheirAgentsSensorNoise) {
  Rng rng(5);
  const GeneratedWorld world = MakeRingWorld(1500, &rng);
  constexpr int kSteps = 40;
  ServerMap map(MapId(1));
  for (int i = 0; i < 4; ++i) {
    const AgentId agent(i < 2 ? 1 : 2);
    AddGeneratedKeyframe(&map, world, agent, i, CirclePose(i, kSteps), CirclePose(i, kSteps), &rng);
  }
  const std::map<AgentId, PinholeCamera> cameras = {{AgentId(1), testing::TestCamera()},
                                                    {AgentId(2), testing::TestCamera()}};
  DepthNoise fallback;  // for agents that announced none, as agent 1 here: 1 mm + 2 mm z^2
  fallback.sigma_0 = 0.001;
  fallback.sigma_2 = 0.002;
  AgentDepthNoise noise(fallback);
  DepthNoise rendered;
  rendered.sigma_0 = 0.0005;
  rendered.sigma_2 = 0;
  noise.agents[AgentId(2)] = rendered;
  const GlobalBaProblem g = BuildGlobalBa(map, cameras, noise);
  int checked[3] = {0, 0, 0};
  for (const BaObservation& o : g.problem.observations) {
    if (o.depth <= 0) continue;
    const AgentId agent = g.keyframes[o.camera].agent;
    const double sigma = agent == AgentId(2) ? 0.0005 : 0.001 + 0.002 * o.depth * o.depth;
    EXPECT_NEAR(o.depth_information * sigma * sigma, 1.0, 1e-9);
    ++checked[agent.value()];
  }
  EXPECT_GT(checked[1], 50);
  EXPECT_GT(checked[2], 50);
}

TEST(GlobalBaTest, APerturbedKeyframeReturnsAndLateKeyframesFollowTheirNeighbour) {
  Rng rng(23);
  const GeneratedWorld world = MakeRingWorld(2500, &rng);
  constexpr int kSteps = 40;
  ServerMap map(MapId(1));
  for (int i = 0; i < 8; ++i)
    AddGeneratedKeyframe(&map, world, AgentId(1), i, CirclePose(i, kSteps), CirclePose(i, kSteps),
                         &rng);
  // Keyframe 5 is 4 cm and 1 degree off; its points were anchored with the true view, so
  // the ones only it sees move with it and are not in the problem.
  Pose error = Pose::Identity();
  error.linear() = Eigen::AngleAxisd(1.0 * kDegree, Eigen::Vector3d::UnitY()).toRotationMatrix();
  error.translation() = Eigen::Vector3d(0.03, -0.02, 0.02);
  ServerKeyframe* five = map.keyframe(Kf(5));
  five->T_map_cam = CirclePose(5, kSteps) * error;
  std::map<AgentId, PinholeCamera> cameras = {{AgentId(1), testing::TestCamera()}};

  GlobalBaProblem problem = BuildGlobalBa(map, cameras, DepthNoise());
  EXPECT_EQ(problem.keyframes.size(), 8u);
  std::size_t seen_twice = 0;
  for (const auto& [id, kf] : map.keyframes()) {
    for (ServerMapPoint* p : kf->points)
      seen_twice += p && p->anchor == kf.get() && p->observations.size() >= 2;
  }
  EXPECT_EQ(problem.points.size(), seen_twice);
  EXPECT_LT(problem.points.size(), map.num_points());
  EXPECT_TRUE(problem.problem.cameras[0].fixed);  // the origin

  // Keyframe 8 arrives while the problem is solved, placed relative to keyframe 7.
  ServerKeyframe* late = AddGeneratedKeyframe(&map, world, AgentId(1), 8, CirclePose(8, kSteps),
                                              CirclePose(8, kSteps), &rng);
  const Pose late_before = late->T_map_cam;
  BaOptions ba;
  ba.solver = BaLinearSolver::kSparseSchur;
  ba.first_iterations = ba.second_iterations = 10;
  BundleAdjust(&problem.problem, ba);
  const Pose seven_before = map.keyframe(Kf(7))->T_map_cam;

  const std::vector<ServerKeyframe*> moved = ApplyGlobalBa(&map, problem);
  EXPECT_EQ(moved.size(), 8u);  // the seven optimised (not the fixed origin) and the late one
  EXPECT_LT(TranslationDistance(five->T_map_cam, CirclePose(5, kSteps)), 0.003);
  EXPECT_LT(RotationDistance(five->T_map_cam, CirclePose(5, kSteps)), 0.1 * kDegree);
  const Pose correction = map.keyframe(Kf(7))->T_map_cam * seven_before.inverse();
  EXPECT_LT(TranslationDistance(late->T_map_cam, correction * late_before), 1e-9);
}

TEST(GlobalBaTest, AWindowAroundALoopOptimisesOnlyItsKeyframes) {
  Rng rng(24);
  const GeneratedWorld world = MakeRingWorld(4000, &rng);
  constexpr int kSteps = 60;
  ServerMap map(MapId(1));
  for (int i = 0; i < 30; ++i)
    AddGeneratedKeyframe(&map, world, AgentId(1), i, CirclePose(i, kSteps), CirclePose(i, kSteps),
                         &rng);
  const std::set<GlobalKeyframeId> window = SelectGlobalBaWindow(map, {Kf(15), Kf(16)}, 8);
  ASSERT_EQ(window.size(), 8u);
  EXPECT_TRUE(window.count(Kf(15)) && window.count(Kf(16)));
  for (const GlobalKeyframeId& id : window)
    EXPECT_LE(std::abs(static_cast<int>(id.keyframe.value()) - 15), 6);
  EXPECT_FALSE(window.count(Kf(0)));  // the origin is far away

  Pose error = Pose::Identity();
  error.translation() = Eigen::Vector3d(0.02, 0.01, -0.02);
  map.keyframe(Kf(15))->T_map_cam = CirclePose(15, kSteps) * error;
  std::map<AgentId, PinholeCamera> cameras = {{AgentId(1), testing::TestCamera()}};
  GlobalBaProblem problem = BuildGlobalBa(map, cameras, DepthNoise(), &window);
  int free = 0, fixed = 0;
  for (const BaCamera& c : problem.problem.cameras) (c.fixed ? fixed : free)++;
  EXPECT_EQ(free, 8);
  EXPECT_GT(fixed, 0);  // the neighbours that see the window's points hold the gauge
  BaOptions ba;
  ba.solver = BaLinearSolver::kSparseSchur;
  ba.first_iterations = ba.second_iterations = 10;
  BundleAdjust(&problem.problem, ba);
  std::map<GlobalKeyframeId, Pose> before;
  for (const auto& [id, kf] : map.keyframes()) before[id] = kf->T_map_cam;
  const std::vector<ServerKeyframe*> moved = ApplyGlobalBa(&map, problem);
  EXPECT_EQ(moved.size(), 8u);
  EXPECT_LT(TranslationDistance(map.keyframe(Kf(15))->T_map_cam, CirclePose(15, kSteps)), 0.003);
  for (const auto& [id, kf] : map.keyframes()) {
    if (window.count(id)) continue;
    EXPECT_EQ(kf->T_map_cam.matrix(), before[id].matrix()) << id.keyframe.value();
  }
}

}  // namespace
}  // namespace ccmd
