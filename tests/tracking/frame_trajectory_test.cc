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

}  // namespace
}  // namespace ccmd
