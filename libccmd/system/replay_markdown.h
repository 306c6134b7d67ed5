#pragma once

// report.md of a split replay, written from its figures alone (results.json as EvaluateReplay
// makes it): maps and trajectories, the dense map, bandwidth, CPU.

#include <cstddef>
#include <string>

#include "libccmd/system/replay_report.h"
#include "libccmd/util/json.h"

namespace ccmd {

// The report's sections up to and including CPU; `map_plots` says whether plots/map_top.png
// and plots/map_view.png were written.
std::string ReplayMarkdown(const Json& results, const ReplayRunInfo& info,
                           std::size_t dataset_frames, bool map_plots);

}  // namespace ccmd
