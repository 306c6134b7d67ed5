#pragma once

// The network side of a split-replay run, for its report: the link it ran on, each agent's
// rate against its bandwidth budget (plots/budget.png), whether every keyframe reached the
// server exactly once, and the map latency: from a keyframe's creation on its agent to its
// points in the server's dense map. Agents and server share one machine's wall clock, so the
// agents' keyframe logs (agents/<name>_stats.json, link.keyframe_log) and the server's
// keyframe_arrivals.csv match by (agent, keyframe id).

#include <string>
#include <vector>

#include "libccmd/util/json.h"
#include "libccmd/util/status.h"

namespace ccmd {

// Linear-interpolated percentile (q in [0, 1]) of unsorted values; 0 for none.
double Percentile(std::vector<double> values, double q);

struct LinkRunInfo {
  std::string link;  // the --link spec, "" = loopback
  Json link_stats;   // the shaped link's own counters (NetnsLink::ToJson), null on loopback
  int agents = 0;
};

// Adds "link", "map_latency_p50_s", "map_latency_p95_s" and the other link figures to
// `results` (and "kBps", "budget_kBps" to each entry of results["agents"]), writes
// plots/budget.png when an agent had a budget, and returns the report's section (markdown).
StatusOr<std::string> AddLinkFigures(const std::string& run_dir, const LinkRunInfo& info,
                                     Json* results);

// One run of a budget sweep: the same replay with every agent under `budget_kBps` (0: none).
struct BudgetRow {
  double budget_kBps = 0;
  std::string run_dir;  // relative to the main run's folder
  Json results;         // that run's results.json
};

// Appends the sweep to the main run's report.md and results.json ("budget_sweep"): a table
// of rate, keyframes, RGB-D, map latency, reconstruction error, completeness and ATE per
// budget, and plots/budget_sweep.png (reconstruction error and completeness against budget).
Status AppendBudgetSweep(const std::string& run_dir, const std::vector<BudgetRow>& rows);

// One run of the knob-cost measurement: the same replay with one RGB-D setting changed.
struct KnobRow {
  std::string knob;     // "JPEG quality 50", ...; the first row is the agents' defaults
  std::string run_dir;  // relative to the main run's folder
  Json results;
};

// What each RGB-D knob saves and what it costs the dense map, against the first row:
// RGB-D bytes per keyframe, map points, completeness, mean error, fused ATE, and the
// completeness lost per kB saved per keyframe. Appended to report.md and results.json
// ("knob_costs"); the budget's ladder gives way in the order of these costs.
Status AppendKnobCosts(const std::string& run_dir, const std::vector<KnobRow>& rows);

}  // namespace ccmd
