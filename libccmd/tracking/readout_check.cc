#include "libccmd/tracking/readout_check.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "libccmd/geometry/pose.h"
#include "libccmd/tracking/frontend.h"

namespace ccmd {

std::optional<double> ChooseReadout(const std::vector<ReadoutTrial>& trials, double min_gain) {
  std::vector<const ReadoutTrial*> valid;
  for (const ReadoutTrial& t : trials)
    if (t.consistency.pairs > 0) valid.push_back(&t);
  std::sort(valid.begin(), valid.end(),
            [](const ReadoutTrial* a, const ReadoutTrial* b) { return a->readout < b->readout; });
  if (valid.empty() || valid.front()->readout != 0) return std::nullopt;
  const auto rotation = [&](std::size_t i) { return valid[i]->consistency.rotation_median_rad; };
  std::size_t best = 0;
  for (std::size_t i = 1; i < valid.size(); ++i)
    if (rotation(i) < rotation(best)) best = i;
  if (best == 0) return 0.0;
  if (rotation(best) > (1 - min_gain) * rotation(0)) return std::nullopt;
  if (best + 1 == valid.size()) return valid[best]->readout;
  // Between the candidates: the vertex of the parabola through the best and its neighbours.
  const double x1 = valid[best - 1]->readout, x2 = valid[best]->readout,
               x3 = valid[best + 1]->readout;
  const double f1 = rotation(best - 1), f2 = rotation(best), f3 = rotation(best + 1);
  const double num = (x2 - x1) * (x2 - x1) * (f2 - f3) - (x2 - x3) * (x2 - x3) * (f2 - f1);
  const double den = (x2 - x1) * (f2 - f3) - (x2 - x3) * (f2 - f1);
  if (!(std::abs(den) > 0)) return x2;
  return std::clamp(x2 - 0.5 * num / den, x1, x3);
}

int GapForRotation(const Trajectory& trajectory, double rotation_rad) {
  constexpr int kMin = 2, kMax = 30;
  std::vector<double> turns;
  for (int gap = kMin; gap < kMax; ++gap) {
    turns.clear();
    for (std::size_t i = 0; i + gap < trajectory.size(); ++i) {
      const Eigen::Matrix3d R =
          trajectory[i].T_world_cam.linear().transpose() * trajectory[i + gap].T_world_cam.linear();
      turns.push_back(AngleAxisFromRotation(R).norm());
    }
    if (turns.empty()) break;  // too short to turn that much
    const auto middle = turns.begin() + turns.size() / 2;
    std::nth_element(turns.begin(), middle, turns.end());
    if (*middle >= rotation_rad) return gap;
  }
  return kMax;
}

StatusOr<ReadoutCheck> CheckReadout(const std::vector<RgbdFrame>& frames,
                                    const PinholeCamera& camera, TrackingOptions tracking,
                                    const ReadoutCheckOptions& options,
                                    const std::function<void(const ReadoutTrial&)>& progress) {
  std::vector<double> candidates = options.candidates;
  candidates.push_back(0);
  std::sort(candidates.begin(), candidates.end());
  candidates.erase(std::unique(candidates.begin(), candidates.end()), candidates.end());
  for (double c : candidates) {
    if (!(c >= 0) || !std::isfinite(c) || c > 0.2)
      return InvalidArgument("a candidate readout must be 0..0.2 s, not " + std::to_string(c));
  }
  constexpr std::size_t kFewest = 60;  // 2 s at 30 Hz: the automatic gap's largest twice
  if (frames.size() < kFewest) {
    return InvalidArgument(std::to_string(frames.size()) +
                           " frames are too few to read a readout from (at least " +
                           std::to_string(kFewest) + ")");
  }
  DepthConsistencyOptions consistency = options.consistency;
  consistency.UseSensorOf(tracking);
  tracking.synchronous_mapping = true;  // deterministic: the trials differ by the readout only
  tracking.cpu_budget = 0;
  ReadoutCheck out;
  for (double readout : candidates) {  // 0 first
    tracking.rolling_shutter_readout = readout;
    CCMD_ASSIGN_OR_RETURN(std::unique_ptr<Frontend> frontend,
                          Frontend::Create(camera, tracking, nullptr));
    for (const RgbdFrame& frame : frames) frontend->ProcessFrame(frame);
    frontend->Finish();
    const Trajectory trajectory = frontend->FrameTrajectory();
    if (consistency.gap <= 0) {
      consistency.gap = GapForRotation(trajectory, options.pair_rotation_deg * M_PI / 180);
    }
    ReadoutTrial trial;
    trial.readout = readout;
    trial.lost_frames = frontend->stats().lost_frames;
    if (auto measured = MeasureDepthConsistency(frames, trajectory, camera, consistency))
      trial.consistency = *measured;
    if (progress) progress(trial);
    out.trials.push_back(trial);
  }
  out.gap = consistency.gap;
  out.readout = ChooseReadout(out.trials, options.min_gain);
  return out;
}

}  // namespace ccmd
