#pragma once

// Trajectories in the TUM format: one line per pose, "timestamp tx ty tz qx qy qz qw",
// T_world_cam, '#' comments. Readable by evo and the TUM benchmark tools.

#include <optional>
#include <string>
#include <vector>

#include "libccmd/geometry/pose.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct StampedPose {
  double timestamp = 0.0;
  Pose T_world_cam = Pose::Identity();
};

using Trajectory = std::vector<StampedPose>;

// Parses a TUM trajectory. Lines must have 8 numbers; the result is sorted by time.
StatusOr<Trajectory> ReadTumTrajectory(const std::string& path);
StatusOr<Trajectory> ParseTumTrajectory(const std::string& text, const std::string& name);

// Writes atomically, full double precision for timestamps (microseconds survive).
Status WriteTumTrajectory(const Trajectory& trajectory, const std::string& path,
                          const std::string& comment = "");
std::string FormatTumTrajectory(const Trajectory& trajectory, const std::string& comment = "");

// The poses of another camera on the same rig: T_world_other = T_world_cam * T_cam_other.
Trajectory TrajectoryOfCamera(const Trajectory& trajectory, const Pose& T_cam_other);

// The pose at `t`, interpolated between the two samples around it, if both lie within
// `max_gap` seconds of t. Requires a time-sorted trajectory.
std::optional<Pose> InterpolateTrajectory(const Trajectory& trajectory, double t, double max_gap);

}  // namespace ccmd
