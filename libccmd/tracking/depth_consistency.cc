#include "libccmd/tracking/depth_consistency.h"

#include <algorithm>
#include <cmath>

#include "libccmd/geometry/pose.h"
#include "libccmd/tracking/depth_alignment.h"

namespace ccmd {
namespace {

// The trajectory's pose at `timestamp` (within 1 ms); `sorted` is ordered by time.
const Pose* PoseAt(const Trajectory& sorted, double timestamp) {
  const auto it = std::lower_bound(sorted.begin(), sorted.end(), timestamp - 1e-3,
                                   [](const StampedPose& p, double t) { return p.timestamp < t; });
  if (it == sorted.end() || std::abs(it->timestamp - timestamp) > 1e-3) return nullptr;
  return &it->T_world_cam;
}

double Median(std::vector<double> values) {
  const auto middle = values.begin() + values.size() / 2;
  std::nth_element(values.begin(), middle, values.end());
  return *middle;
}

double Mean(const std::vector<double>& values) {
  double sum = 0;
  for (double v : values) sum += v;
  return sum / values.size();
}

}  // namespace

std::optional<DepthConsistency> MeasureDepthConsistency(const std::vector<RgbdFrame>& frames,
                                                        const Trajectory& trajectory,
                                                        const PinholeCamera& camera,
                                                        const DepthConsistencyOptions& options) {
  Trajectory sorted = trajectory;
  std::sort(sorted.begin(), sorted.end(),
            [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  DepthConsistency out;
  std::vector<double> translations, rotations;
  const std::size_t gap = std::max(1, options.gap);
  for (std::size_t i = 0; i + gap < frames.size(); i += std::max(1, options.stride)) {
    const RgbdFrame& a = frames[i];
    const RgbdFrame& b = frames[i + gap];
    const Pose* T_world_a = PoseAt(sorted, a.timestamp);
    const Pose* T_world_b = PoseAt(sorted, b.timestamp);
    if (!T_world_a || !T_world_b || a.depth_mm.empty() || b.depth_mm.empty()) {
      ++out.failed;
      continue;
    }
    const DepthModel source = DepthModel::FromDepth(a.depth_mm, camera, options.cell,
                                                    options.min_depth, options.max_depth);
    const DepthModel target = DepthModel::FromDepth(b.depth_mm, camera, options.cell,
                                                    options.min_depth, options.max_depth);
    const Pose T_b_a = T_world_b->inverse() * *T_world_a;
    const auto aligned = AlignDepth(source, target, T_b_a, options.noise);
    if (!aligned || !StaysNearStart(*aligned, T_b_a)) {
      ++out.failed;
      continue;
    }
    const Pose correction = aligned->T_target_source * T_b_a.inverse();
    translations.push_back(correction.translation().norm());
    rotations.push_back(AngleAxisFromRotation(correction.linear()).norm());
  }
  if (translations.empty()) return std::nullopt;
  out.pairs = static_cast<int>(translations.size());
  out.translation_median_m = Median(translations);
  out.translation_mean_m = Mean(translations);
  out.rotation_median_rad = Median(rotations);
  out.rotation_mean_rad = Mean(rotations);
  return out;
}

}  // namespace ccmd
