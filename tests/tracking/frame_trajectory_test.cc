// The frames' trajectory from the tracker's records: each keyframe's move after tracking
// placed it is spread over the frames since the keyframe before.

#include <gtest/gtest.h>

#include <cmath>
#include <map>

#include "libccmd/tracking/tracker.h"

namespace ccmd {
namespace {

// Records hold single precision: positions to about 1e-7 m here.

Pose At(double x, double yaw = 0) {
  Pose T = Pose::Identity();
  T.linear() = RotationFromAngleAxis({0, 0, yaw});
  T.translation() = Eigen::Vector3d(x, 0, 0);
  return T;
}

// Keyframe A at frame 0, frames 1-3 tracked against A 0.1 m apart along x, keyframe B made at
// frame 4 where tracking put it (0.4 m), frame 5 tracked against B; frame 6 tracked against a
// keyframe the map does not know.
struct Records {
  std::vector<Tracker::FrameRecord> frames;
  std::vector<Tracker::KeyframeRecord> keyframes;
  Records() {
    const KeyframeId a(0), b(1);
    for (int i = 0; i < 4; ++i) frames.emplace_back(i, a, At(0.1 * i));
    frames.emplace_back(4, b, Pose::Identity());
    frames.emplace_back(5, b, At(0.1));
    frames.emplace_back(6, KeyframeId(7), Pose::Identity());
    keyframes.push_back({a, false, 0, Tracker::FrameRecord(0, a, Pose::Identity())});
    keyframes.push_back({b, true, 4, Tracker::FrameRecord(4, a, At(0.4))});
  }
};

Trajectory FramesOf(const Records& r, const std::map<int, Pose>& keyframe_poses) {
  return FrameTrajectoryOf(r.frames, r.keyframes, [&](KeyframeId id) -> std::optional<Pose> {
    const auto it = keyframe_poses.find(static_cast<int>(id.value()));
    if (it == keyframe_poses.end()) return std::nullopt;
    return it->second;
  });
}

TEST(FrameTrajectoryTest, AKeyframesMoveIsSharedByTheFramesBeforeItInProportion) {
  const Records r;
  // Local BA moved B from 0.4 to 0.5 m: the frames before it take a quarter, half, three
  // quarters of that; the keyframes and the frame tracked against B follow B fully.
  const Trajectory t = FramesOf(r, {{0, Pose::Identity()}, {1, At(0.5)}});
  ASSERT_EQ(t.size(), 6u);  // frame 6's keyframe is unknown
  const double expected[6] = {0.0, 0.125, 0.25, 0.375, 0.5, 0.6};
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(t[i].timestamp, i);
    EXPECT_NEAR(t[i].T_world_cam.translation().x(), expected[i], 1e-6) << "frame " << i;
    EXPECT_NEAR(t[i].T_world_cam.translation().norm(), std::abs(expected[i]), 1e-6);
  }
}

TEST(FrameTrajectoryTest, AKeyframesTurnTurnsTheFramesBeforeItAboutTheKeyframe) {
  const Records r;
  // B turned by 0.1 rad about its own centre: frame 2, half-way, turns by 0.05 rad about B
  // (0.4 m), not about the world's origin.
  const double yaw = 0.1;
  const Trajectory t = FramesOf(r, {{0, Pose::Identity()}, {1, At(0.4, yaw)}});
  const Eigen::Vector3d p2 = t[2].T_world_cam.translation();
  EXPECT_NEAR(p2.x(), 0.4 - 0.2 * std::cos(yaw / 2), 1e-6);
  EXPECT_NEAR(p2.y(), -0.2 * std::sin(yaw / 2), 1e-6);
  EXPECT_NEAR(RotationAngle(t[2].T_world_cam), yaw / 2, 1e-6);
  EXPECT_NEAR(RotationAngle(t[4].T_world_cam), yaw, 1e-6);
  EXPECT_NEAR(RotationAngle(t[1].T_world_cam), yaw / 4, 1e-6);
}

TEST(FrameTrajectoryTest, AKeyframeAfterALossMovesNoFrameBeforeIt) {
  Records r;
  r.keyframes[1].continuous = false;  // a frame was lost between A and B
  const Trajectory t = FramesOf(r, {{0, Pose::Identity()}, {1, At(0.5)}});
  ASSERT_EQ(t.size(), 6u);
  for (int i = 0; i < 4; ++i) EXPECT_NEAR(t[i].T_world_cam.translation().x(), 0.1 * i, 1e-6);
  EXPECT_NEAR(t[4].T_world_cam.translation().x(), 0.5, 1e-6);
}

// Keyframe A at frame 0; the camera moves 0.1 m a frame along x (or turns 0.1 rad a frame about
// z), stands still for three frames, goes on, and tracking puts keyframe B at 0.4 m (0.4 rad) at
// frame 7. A frame takes the share of B's move of where it is on the way, not of its count.
Records StopAndGo(bool turn) {
  Records r;
  r.frames.clear();
  r.keyframes.clear();
  const KeyframeId a(0), b(1);
  const double along[] = {0, 0.1, 0.2, 0.2, 0.2, 0.2, 0.3};
  for (int i = 0; i < 7; ++i) r.frames.emplace_back(i, a, turn ? At(0, along[i]) : At(along[i]));
  r.frames.emplace_back(7, b, Pose::Identity());
  r.keyframes.push_back({a, false, 0, Tracker::FrameRecord(0, a, Pose::Identity())});
  r.keyframes.push_back({b, true, 7, Tracker::FrameRecord(7, a, turn ? At(0, 0.4) : At(0.4))});
  return r;
}

TEST(FrameTrajectoryTest, FramesOfACameraStandingStillTakeOneShareOfTheMove) {
  // B moved from 0.4 to 0.5 m: the frames at 0.2 m, half-way, take half of that, all four of
  // them; by count they would take 2/7 to 5/7 and drift apart while the camera stood still.
  const Trajectory t = FramesOf(StopAndGo(false), {{0, Pose::Identity()}, {1, At(0.5)}});
  ASSERT_EQ(t.size(), 8u);
  const double expected[8] = {0.0, 0.125, 0.25, 0.25, 0.25, 0.25, 0.375, 0.5};
  for (int i = 0; i < 8; ++i)
    EXPECT_NEAR(t[i].T_world_cam.translation().x(), expected[i], 1e-6) << "frame " << i;
}

TEST(FrameTrajectoryTest, FramesOfACameraTurningInPlaceShareTheMoveByTheAngleTurned) {
  // Turning on the spot, the way is the angle: B, tracked at 0.4 rad, is at 0.4 rad and 0.1 m
  // along x; the frames half-way round (0.2 rad) take half of the 0.1 m.
  const Trajectory t = FramesOf(StopAndGo(true), {{0, Pose::Identity()}, {1, At(0.1, 0.4)}});
  ASSERT_EQ(t.size(), 8u);
  for (int i = 2; i < 6; ++i) {
    EXPECT_NEAR(t[i].T_world_cam.translation().x(), 0.05, 1e-6) << "frame " << i;
    EXPECT_NEAR(RotationAngle(t[i].T_world_cam), 0.2, 1e-6) << "frame " << i;
  }
  EXPECT_NEAR(t[6].T_world_cam.translation().x(), 0.075, 1e-6);
}

}  // namespace
}  // namespace ccmd
