#include "libccmd/system/replay_markdown.h"

#include <sstream>
#include <vector>

#include "libccmd/system/report_format.h"
#include "libccmd/tracking/depth_noise_ratio.h"

namespace ccmd {
namespace {

using report::Fmt;
using report::Num;
using report::Str;

std::string JoinNames(const std::vector<std::string>& names) {
  std::string out;
  for (const std::string& n : names) out += (out.empty() ? "" : ", ") + n;
  return out.empty() ? "none" : out;
}

std::vector<std::string> PrimaryAgents(const Json& results) {
  std::vector<std::string> names;
  if (const Json* primary = results.Get("primary_map_agents")) {
    for (const Json& n : primary->array()) names.push_back(n.string());
  }
  return names;
}

void WriteHeader(const Json& results, const ReplayRunInfo& info, std::size_t dataset_frames,
                 std::ostringstream& md) {
  md << "# Split-replay report\n\n";
  md << "- dataset: `" << info.dataset_dir << "` (" << dataset_frames << " frames)\n";
  md << "- agents: " << info.agents << ", pace: " << info.rate << ", wall time "
     << Fmt("%.1f", info.wall_seconds) << " s\n";
  md << "- command: `" << info.command << "`\n";
  if (!info.config.empty()) md << "- config: `" << info.config << "` (copied to config.yaml)\n";
  md << "\n## Maps and trajectories\n\n";
  md << "Maps left after fusion: " << Num(&results, "maps_after_fusion", -1) << " (loops "
     << Num(&results, "loops") << ", fusions " << Num(&results, "fusions") << ", global BA runs "
     << Num(&results, "global_ba_runs") << ")\n\n";
  if (const double restarted = Num(&results, "segments_restarted"); restarted > 0) {
    const double unplaced = Num(&results, "segments_unplaced");
    md << "Agents lost tracking and restarted " << restarted << " time(s) in a new map segment; "
       << (unplaced > 0 ? Fmt("%.0f", unplaced) +
                              " segment(s) no loop has placed are left out of the trajectories "
                              "and the dense map (the agents' own trajectories keep them).\n\n"
                        : std::string("loops placed every segment.\n\n"));
  }
}

// Which agents the fused trajectory and the dense map leave out, when not every map fused.
void WriteUnfused(const Json& results, std::ostringstream& md) {
  std::vector<std::string> others, unplaced;
  if (const Json* agents = results.Get("agents")) {
    for (const Json& a : agents->array()) {
      if (Str(&a, "map") == "unplaced") unplaced.push_back(Str(&a, "name"));
      if (Str(&a, "map") == "own") others.push_back(Str(&a, "name"));
    }
  }
  md << "**Not every map fused.** The fused trajectory and the dense map below are the primary "
        "map's, which holds "
     << JoinNames(PrimaryAgents(results));
  if (!others.empty()) {
    md << "; " << JoinNames(others)
       << (others.size() == 1
               ? " kept its own map: its server ATE in the table is in that map's frame"
               : " kept their own maps: each one's server ATE in the table is in its own map's "
                 "frame");
  }
  if (!unplaced.empty()) {
    md << "; the keyframes of " << JoinNames(unplaced)
       << " wait unplaced in it (they joined through a restarted segment no loop has placed)";
  }
  md << ".\n\n";
}

void WriteTrajectories(const Json& results, std::ostringstream& md) {
  md << "| agent | frames | map | server keyframes | ATE RMSE (server, m) | ATE RMSE (agent "
        "odometry, m) | its map points' mean error (m) | lost frames | restarts |\n"
        "|---|---|---|---|---|---|---|---|---|\n";
  auto metres = [](const Json& a, const std::string& key) {
    return a.Has(key) ? Fmt("%.4f", Num(&a, key)) : std::string("-");
  };
  for (const Json& a : results.Get("agents")->array()) {
    md << "| " << Str(&a, "name") << " | " << Num(&a, "first_frame") << "-" << Num(&a, "last_frame")
       << " | " << Str(&a, "map") << " | " << Num(&a, "keyframes") << " | "
       << metres(a, "ate_rmse_m") << " | " << metres(a, "agent_frames_ate_rmse_m") << " | "
       << metres(a, "map_mean_error_m") << " | " << Num(&a, "lost_frames") << " | "
       << Num(&a, "restarts") << " |\n";
  }
  // The agents' check of their config's depth-noise model (FrontendStats::depth_noise_ratio;
  // the agent warns where it does not fit).
  for (const Json& a : results.Get("agents")->array()) {
    const double ratio = Num(&a, "depth_noise_ratio");
    if (DepthNoiseModelFits(ratio)) continue;
    md << "\n"
       << Str(&a, "name") << "'s depth measured " << Fmt(ratio < 1 ? "%.2f" : "%.1f", ratio)
       << " times as noisy as its config's DepthNoise model: logs/" << Str(&a, "name")
       << ".log gives the keys that describe the camera (docs/cameras.md, checking a camera).\n";
  }
  if (results.Has("ate_rmse_m")) {
    md << "\nFused trajectory (every keyframe of the primary map: "
       << JoinNames(PrimaryAgents(results)) << "): ATE RMSE **"
       << Fmt("%.4f", Num(&results, "ate_rmse_m")) << " m** over "
       << Num(&results, "fused_keyframes") << " keyframes (max "
       << Fmt("%.4f", Num(&results, "ate_max_m")) << " m)"
       << (Str(&results, "ate_aligned_by") == "poses"
               ? ", aligned by whole keyframe poses: too few keyframes, or all within a centimetre "
                 "of a line, to align by positions"
               : "")
       << ".\n";
  } else {
    md << "\nNo fused ATE: the primary map has no keyframe matching the ground truth.\n";
  }
}

void WriteDenseMap(const Json& results, bool map_plots, std::ostringstream& md) {
  md << "\n![trajectories](plots/trajectories.png)\n\n## Dense map\n\n";
  if (results.Has("recon_mean_m")) {
    md << "| points | mean distance (m) | median (m) | 95% (m) | Hausdorff (m) | completeness (2 "
          "cm) |\n|---|---|---|---|---|---|\n";
    md << "| " << Fmt("%.0f", Num(&results, "map_points")) << " | "
       << Fmt("%.4f", Num(&results, "recon_mean_m")) << " | "
       << Fmt("%.4f", Num(&results, "recon_median_m")) << " | "
       << Fmt("%.4f", Num(&results, "recon_p95_m")) << " | "
       << Fmt("%.4f", Num(&results, "recon_hausdorff_m")) << " | "
       << Fmt("%.1f%%", 100 * Num(&results, "recon_completeness")) << " |\n\n";
    md << "Reference: " << Str(&results, "reference") << " (" << Num(&results, "reference_points")
       << " points). The map is aligned to it by the fit of the primary map's keyframe poses "
          "(centres, and orientations weighed at the "
       << Fmt("%.2f", Num(&results, "recon_viewing_distance_m"))
       << " m the keyframes see the map from) to the ground truth.";
    if (results.Has("recon_mean_after_icp_m")) {
      md << " Placed on the reference by ICP instead (as the paper aligns its maps): mean "
         << Fmt("%.4f", Num(&results, "recon_mean_after_icp_m")) << " m, the map turned by "
         << Fmt("%.3f", Num(&results, "recon_icp_turn_deg")) << " degrees and moved "
         << Fmt("%.4f", Num(&results, "recon_icp_shift_m")) << " m from the keyframes' fit.";
    }
    md << "\n";
  } else {
    md << "No dense map or no reference to compare with.\n";
  }
  if (map_plots)
    md << "\n![dense map, top view](plots/map_top.png)\n\n![dense map, "
          "perspective](plots/map_view.png)\n";
}

void WriteBandwidth(const Json& results, std::ostringstream& md) {
  md << "\n## Bandwidth\n\n| agent | ATPS (kB/s) | AKFS (kB) | AKFR (Hz) | keyframes with RGB-D | "
        "bytes |\n|---|---|---|---|---|---|\n";
  for (const Json& a : results.Get("agents")->array()) {
    md << "| " << Str(&a, "name") << " | " << Fmt("%.1f", Num(&a, "atps_kBps")) << " | "
       << Fmt("%.1f", Num(&a, "akfs_kB")) << " | " << Fmt("%.2f", Num(&a, "akfr_hz")) << " | "
       << Num(&a, "rgbd_keyframes") << " of " << Num(&a, "keyframes") << " | "
       << Fmt("%.0f", Num(&a, "bytes")) << " |\n";
  }
  md << "| mean | " << Fmt("%.1f", Num(&results, "atps_kBps")) << " | "
     << Fmt("%.1f", Num(&results, "akfs_kB")) << " | " << Fmt("%.2f", Num(&results, "akfr_hz"))
     << " | | |\n\n";
  md << "ATPS and AKFR are per second of connection (wall clock of this run); per second of the "
        "dataset's own time (what a robot moving at that speed would send): "
     << Fmt("%.1f", Num(&results, "atps_dataset_kBps")) << " kB/s and "
     << Fmt("%.2f", Num(&results, "akfr_dataset_hz")) << " keyframes/s per agent.\n\n";
  md << "Bytes per keyframe by kind, against an uncompressed format (4x4 float pose, 5 floats per "
        "keypoint, every descriptor, id + xyz per map point, full-resolution colour and float "
        "depth with every keyframe):\n\n";
  md << "| kind | sent (B/keyframe) | uncompressed (B/keyframe) | ratio |\n|---|---|---|---|\n";
  if (const Json* kinds = results.Get("bytes_per_kind")) {
    for (const Json& e : kinds->array()) {
      const double ours = Num(&e, "bytes_per_keyframe");
      const double naive = Num(&e, "uncompressed_bytes_per_keyframe");
      md << "| " << Str(&e, "kind") << " | " << Fmt("%.0f", ours) << " | " << Fmt("%.0f", naive)
         << " | " << (naive > 0 ? Fmt("%.3f", ours / naive) : "-") << " |\n";
    }
  }
  md << "\n![traffic](plots/traffic.png)\n\n![bytes per kind](plots/bytes_per_kind.png)\n";
}

void WriteCpu(const ReplayRunInfo& info, std::ostringstream& md) {
  md << "\n## CPU\n\n";
  md << "| process | CPU (s) | CPU (% of one core) | peak memory (MB) |\n|---|---|---|---|\n";
  for (const ReplayProcess& p : info.processes) {
    md << "| " << p.name << " | " << Fmt("%.1f", p.cpu_seconds) << " | "
       << Fmt("%.0f", p.wall_seconds > 0 ? 100 * p.cpu_seconds / p.wall_seconds : 0.0) << " | "
       << Fmt("%.0f", p.max_rss_mb) << " |\n";
  }
  md << "\n![cpu](plots/cpu.png)\n";
}

}  // namespace

std::string ReplayMarkdown(const Json& results, const ReplayRunInfo& info,
                           std::size_t dataset_frames, bool map_plots) {
  std::ostringstream md;
  WriteHeader(results, info, dataset_frames, md);
  const Json* all_fused = results.Get("all_maps_fused");
  if (all_fused && !all_fused->boolean()) WriteUnfused(results, md);
  WriteTrajectories(results, md);
  WriteDenseMap(results, map_plots, md);
  WriteBandwidth(results, md);
  WriteCpu(info, md);
  return md.str();
}

}  // namespace ccmd
