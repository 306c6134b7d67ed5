#pragma once

// The split-replay report's pictures, written into the run folder's plots/: keyframe
// trajectories against the ground truth, traffic per agent, bytes per keyframe by kind, CPU per
// process, the server's memory, and the dense map from above and in perspective.

#include <optional>
#include <string>
#include <vector>

#include "libccmd/geometry/alignment.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/system/replay_report.h"
#include "libccmd/util/json.h"

namespace ccmd {

struct ReplayPlotInputs {
  const Json* server_stats = nullptr;  // server_stats.json
  const Json* results = nullptr;       // the figures so far (bytes_per_kind)
  const ReplayRunInfo* info = nullptr;
  Trajectory ground_truth;                     // at the dataset's frames; empty: no such plot
  std::vector<Trajectory> agent_trajectories;  // agent i + 1's keyframes, in its map's frame
  std::optional<Similarity3> alignment;        // map frame -> ground truth, when one was fitted
};

// Writes every plot it has data for into `plots_dir` (a plot that cannot be written is left
// out). True when the dense map's pictures were written (the server left a map).
bool WriteReplayPlots(const std::string& run_dir, const std::string& plots_dir,
                      const ReplayPlotInputs& in);

}  // namespace ccmd
