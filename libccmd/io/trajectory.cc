#include "libccmd/io/trajectory.h"

#include <algorithm>
#include <cstdio>

#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

StatusOr<Trajectory> ParseTumTrajectory(const std::string& text, const std::string& name) {
  Trajectory trajectory;
  CCMD_RETURN_IF_ERROR(ForEachDataLine(text, name, [&](const auto& fields) -> Status {
    if (fields.size() != 8)
      return Corrupt("expected 8 numbers, found " + std::to_string(fields.size()));
    double v[8];
    for (int i = 0; i < 8; ++i) {
      CCMD_ASSIGN_OR_RETURN(v[i], ParseDouble(fields[i]));
    }
    const Eigen::Quaterniond raw(v[7], v[4], v[5], v[6]);
    if (raw.norm() < 1e-6) return Corrupt("zero quaternion");
    // Scaled by its largest component before normalising: the norm of components near 1e200
    // overflows, and dividing by it gave zeros, read as the identity.
    const Eigen::Quaterniond q(Eigen::Vector4d(raw.coeffs() / raw.coeffs().cwiseAbs().maxCoeff()));
    trajectory.push_back({v[0], PoseFromTranslationQuaternion({v[1], v[2], v[3]}, q)});
    return Status::Ok();
  }));
  std::stable_sort(
      trajectory.begin(), trajectory.end(),
      [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  return trajectory;
}

StatusOr<Trajectory> ReadTumTrajectory(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path));
  return ParseTumTrajectory(text, path);
}

std::string FormatTumTrajectory(const Trajectory& trajectory, const std::string& comment) {
  std::string out;
  out.reserve(trajectory.size() * 96 + comment.size() + 64);
  if (!comment.empty()) out += "# " + comment + "\n";
  out += "# timestamp tx ty tz qx qy qz qw\n";
  // Room for the longest finite doubles (%.9f prints up to 320 characters): a line cut
  // short would lose its pose and run into the next one.
  char line[8 * 330];
  for (const StampedPose& sample : trajectory) {
    const Eigen::Vector3d t = sample.T_world_cam.translation();
    const Eigen::Quaterniond q = QuaternionOf(sample.T_world_cam);
    std::snprintf(line, sizeof(line), "%.6f %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n", sample.timestamp,
                  t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w());
    out += line;
  }
  return out;
}

Status WriteTumTrajectory(const Trajectory& trajectory, const std::string& path,
                          const std::string& comment) {
  return WriteFileAtomic(path, FormatTumTrajectory(trajectory, comment));
}

Trajectory TrajectoryOfCamera(const Trajectory& trajectory, const Pose& T_cam_other) {
  Trajectory out = trajectory;
  for (StampedPose& p : out) p.T_world_cam = p.T_world_cam * T_cam_other;
  return out;
}

std::optional<Pose> InterpolateTrajectory(const Trajectory& trajectory, double t, double max_gap) {
  if (trajectory.empty()) return std::nullopt;
  const auto after = std::lower_bound(
      trajectory.begin(), trajectory.end(), t,
      [](const StampedPose& sample, double time) { return sample.timestamp < time; });
  if (after != trajectory.end() && after->timestamp == t) return after->T_world_cam;
  if (after == trajectory.begin() || after == trajectory.end()) {
    // Outside the sampled interval: accept the nearest end only if it is (almost) at t.
    const StampedPose& end = after == trajectory.end() ? trajectory.back() : trajectory.front();
    if (std::abs(end.timestamp - t) <= 1e-6) return end.T_world_cam;
    return std::nullopt;
  }
  const StampedPose& before = *(after - 1);
  if (t - before.timestamp > max_gap || after->timestamp - t > max_gap) return std::nullopt;
  const double alpha = (t - before.timestamp) / (after->timestamp - before.timestamp);
  return InterpolatePose(before.T_world_cam, after->T_world_cam, alpha);
}

}  // namespace ccmd
