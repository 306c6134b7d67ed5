#include "libccmd/backend/loop_verification.h"

#include <gtest/gtest.h>

#include "libccmd/util/random.h"
#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

Descriptor RandomDescriptor(Rng* rng) {
  Descriptor d;
  for (auto& b : d) b = static_cast<std::uint8_t>(rng->Next());
  return d;
}

Descriptor FlipBits(Descriptor d, int bits, Rng* rng) {
  for (int i = 0; i < bits; ++i) {
    const int bit = rng->UniformInt(0, 255);
    d[bit / 8] ^= static_cast<std::uint8_t>(1 << (bit % 8));
  }
  return d;
}

PinholeCamera Camera() {
  PinholeCamera c;
  c.fx = c.fy = 525;
  c.cx = 319.5;
  c.cy = 239.5;
  return c;
}

// A candidate keyframe at the origin observing 400 points on a wall 2-4 m away, in `map`; its
// map points lie at the true points plus `point_error` metres per axis (normal).
struct Wall {
  ServerKeyframe* candidate = nullptr;
  std::vector<Eigen::Vector3d> world, estimated;
  std::vector<Descriptor> descriptors;
};
Wall MakeWall(const PinholeCamera& camera, double point_error, Rng* rng, ServerMap* map) {
  Wall wall;
  auto candidate = std::make_unique<ServerKeyframe>();
  candidate->id = {AgentId(1), KeyframeId(0)};
  for (int j = 0; j < 400; ++j) {
    wall.world.emplace_back(rng->Uniform(-1.5, 1.5), rng->Uniform(-1, 1), rng->Uniform(2, 4));
    wall.descriptors.push_back(RandomDescriptor(rng));
    const Eigen::Vector2d uv = camera.Project(wall.world.back());
    candidate->AppendKeypoint(
        {cv::Point2f(uv.x(), uv.y()), 0, static_cast<float>(wall.world.back().z())},
        wall.descriptors.back());
  }
  wall.candidate = map->AddKeyframe(std::move(candidate));
  for (int j = 0; j < 400; ++j) {
    Eigen::Vector3d p = wall.world[j];
    if (point_error > 0) {
      p += point_error * Eigen::Vector3d(rng->Normal(), rng->Normal(), rng->Normal());
    }
    wall.estimated.push_back(p);
    ServerMapPoint* point = map->AddPoint(std::make_unique<ServerMapPoint>(
        GlobalMapPointId{AgentId(1), MapPointId(j)}, wall.candidate, p, wall.descriptors[j]));
    map->AddObservation(point, wall.candidate, j);
  }
  return wall;
}

void ExpectQueryPoseRecovered(const PinholeCamera& camera) {
  Rng rng(41);
  ServerMap map(MapId(1));
  const Wall wall = MakeWall(camera, 0, &rng, &map);
  ServerKeyframe* cand = wall.candidate;
  const std::vector<Eigen::Vector3d>& world = wall.world;
  const std::vector<Descriptor>& descriptors = wall.descriptors;
  // Query: another agent's keyframe at a known pose, seeing the same points (noisy pixels and
  // depth, descriptors with a few flipped bits); a third of its keypoints are unrelated.
  Pose T_map_query = Pose::Identity();
  T_map_query.linear() =
      Eigen::AngleAxisd(0.15, Eigen::Vector3d(0.2, 1, 0).normalized()).toRotationMatrix();
  T_map_query.translation() = Eigen::Vector3d(0.3, -0.1, 0.2);
  ServerKeyframe query;
  query.id = {AgentId(2), KeyframeId(7)};
  int true_matches = 0;
  for (int j = 0; j < 400; ++j) {
    const Eigen::Vector3d pc = T_map_query.inverse() * world[j];
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv) || j % 3 == 0) {
      query.AppendKeypoint({cv::Point2f(rng.Uniform(0, 640), rng.Uniform(0, 480)), 0,
                            static_cast<float>(rng.Uniform(1, 4))},
                           RandomDescriptor(&rng));
      continue;
    }
    query.AppendKeypoint({cv::Point2f(uv.x() + 0.5 * rng.Normal(), uv.y() + 0.5 * rng.Normal()), 0,
                          static_cast<float>(pc.z() + 0.004 * rng.Normal())},
                         FlipBits(descriptors[j], 10, &rng));
    ++true_matches;
  }
  auto match = VerifyLoop(&query, camera, cand, map);
  ASSERT_TRUE(match.has_value());
  EXPECT_LT(TranslationDistance(match->T_candidate_map_query, T_map_query), 0.01);
  EXPECT_LT(RotationDistance(match->T_candidate_map_query, T_map_query), 0.5 * M_PI / 180);
  EXPECT_GE(match->inliers, 0.9 * true_matches);
  EXPECT_LE(match->inliers, true_matches);
  for (const auto& [keypoint, point] : match->matches) {
    EXPECT_EQ(point->id.point.value(),
              static_cast<std::uint32_t>(keypoint));  // keypoint j saw point j
  }
}

TEST(LoopVerificationTest, RecoversTheQueryPoseDespiteOutliers) {
  ExpectQueryPoseRecovered(Camera());
}

// The PnP RANSAC and the refinement take the signed focal length: a camera with fy < 0 finds
// the same pose, not its mirror image.
TEST(LoopVerificationTest, NegativeFocalLengthGivesTheSamePose) {
  ExpectQueryPoseRecovered(testing::IclNuimCamera());
}

// A precise sensor (0.5 mm, rendered depth) against another map whose points carry errors of
// a few millimetres: the loop holds with every true match (the first pass weighs depth no
// stricter than a structured-light sensor), and only the matches that agree to the sensor's
// precision are handed on to be merged.
TEST(LoopVerificationTest, APreciseSensorsLoopHoldsAndOnlyPreciseMatchesAreMerged) {
  Rng rng(43);
  const PinholeCamera camera = Camera();
  ServerMap map(MapId(1));
  const Wall wall = MakeWall(camera, 0.003, &rng, &map);  // the other map's points: 3 mm off
  ServerKeyframe* cand = wall.candidate;
  const std::vector<Eigen::Vector3d>& world = wall.world;
  const std::vector<Eigen::Vector3d>& estimated = wall.estimated;
  const std::vector<Descriptor>& descriptors = wall.descriptors;
  Pose T_map_query = Pose::Identity();
  T_map_query.linear() = Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T_map_query.translation() = Eigen::Vector3d(0.2, 0.05, 0.1);
  ServerKeyframe query;
  query.id = {AgentId(2), KeyframeId(3)};
  int true_matches = 0;
  for (int j = 0; j < 400; ++j) {
    const Eigen::Vector3d pc = T_map_query.inverse() * world[j];
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv)) {
      query.AppendKeypoint({cv::Point2f(rng.Uniform(0, 640), rng.Uniform(0, 480)), 0, 2.0f},
                           RandomDescriptor(&rng));
      continue;
    }
    query.AppendKeypoint({cv::Point2f(uv.x() + 0.3 * rng.Normal(), uv.y() + 0.3 * rng.Normal()), 0,
                          static_cast<float>(pc.z() + 0.0002 * rng.Normal())},
                         FlipBits(descriptors[j], 8, &rng));
    ++true_matches;
  }
  LoopVerificationOptions options;
  options.depth_noise.sigma_0 = 0.0005;
  options.depth_noise.sigma_2 = 0;
  const auto match = VerifyLoop(&query, camera, cand, map, options);
  ASSERT_TRUE(match.has_value());
  EXPECT_GE(match->inliers, 0.9 * true_matches);  // the first pass keeps every true match
  EXPECT_LT(TranslationDistance(match->T_candidate_map_query, T_map_query), 0.003);
  EXPECT_LT(RotationDistance(match->T_candidate_map_query, T_map_query), 0.1 * M_PI / 180);
  // Merged: only points whose depth from the query agrees within 3 sigma (1.5 mm) and some
  // more for the pose's own error; most of the 3 mm-per-axis points do not.
  ASSERT_GT(match->matches.size(), 20u);
  EXPECT_LT(match->matches.size(), 0.7 * match->inliers);
  for (const auto& [keypoint, point] : match->matches) {
    EXPECT_EQ(point->id.point.value(), static_cast<std::uint32_t>(keypoint));
    const double depth_error =
        (T_map_query.inverse() * estimated[keypoint]).z() - query.keypoints[keypoint].depth;
    EXPECT_LT(std::abs(depth_error), 0.003) << keypoint;
  }
}

TEST(LoopVerificationTest, UnrelatedViewsAreRejected) {
  Rng rng(42);
  const PinholeCamera camera = Camera();
  ServerMap map(MapId(1));
  auto candidate = std::make_unique<ServerKeyframe>();
  candidate->id = {AgentId(1), KeyframeId(0)};
  for (int j = 0; j < 300; ++j) {
    candidate->AppendKeypoint({cv::Point2f(rng.Uniform(0, 640), rng.Uniform(0, 480)), 0, 2.0f},
                              RandomDescriptor(&rng));
  }
  ServerKeyframe* cand = map.AddKeyframe(std::move(candidate));
  for (int j = 0; j < 300; ++j) {
    const cv::Point2f& pt = cand->keypoints[j].pt;
    ServerMapPoint* p = map.AddPoint(
        std::make_unique<ServerMapPoint>(GlobalMapPointId{AgentId(1), MapPointId(j)}, cand,
                                         camera.BackProject(pt.x, pt.y, 2.0), cand->descriptor(j)));
    map.AddObservation(p, cand, j);
  }
  ServerKeyframe query;
  query.id = {AgentId(2), KeyframeId(1)};
  for (int j = 0; j < 300; ++j) {
    query.AppendKeypoint({cv::Point2f(rng.Uniform(0, 640), rng.Uniform(0, 480)), 0, 2.0f},
                         RandomDescriptor(&rng));
  }
  EXPECT_FALSE(VerifyLoop(&query, camera, cand, map).has_value());
}

// Its own agent's recent keyframes are no loop candidates for a query (the same pass over the
// place), except those of an earlier segment: after a restart they share no points with the
// query's, and only a loop can join the two however close in time they are.
TEST(LoopCandidateRuleTest, AnEarlierSegmentsRecentKeyframesAreCandidates) {
  const auto Id = [](int agent, int keyframe) {
    return GlobalKeyframeId{AgentId(static_cast<std::uint16_t>(agent)),
                            KeyframeId(static_cast<std::uint32_t>(keyframe))};
  };
  LoopCandidateRule rule;
  rule.query = Id(1, 42);
  rule.exclude_recent = 25;
  rule.connected[Id(1, 41)] = 80;
  EXPECT_FALSE(rule.Allowed(Id(1, 30)));
  EXPECT_TRUE(rule.Allowed(Id(1, 10)));
  EXPECT_TRUE(rule.Allowed(Id(2, 40)));
  rule.segment = KeyframeId(35);  // the agent restarted at keyframe 35
  EXPECT_TRUE(rule.Allowed(Id(1, 30)));
  EXPECT_TRUE(rule.Allowed(Id(1, 34)));
  EXPECT_FALSE(rule.Allowed(Id(1, 35)));
  EXPECT_FALSE(rule.Allowed(Id(1, 41)));  // covisible
  EXPECT_FALSE(rule.Allowed(Id(1, 42)));  // itself

  ServerKeyframe query;
  query.id = Id(1, 42);
  query.segment = KeyframeId(35);
  PlaceIndex place{PlaceIndexOptions{}};
  EXPECT_EQ(MakeLoopCandidateRule(place, query.id, query, 25).segment, KeyframeId(35));
}

}  // namespace
}  // namespace ccmd
