#include "libccmd/system/link_report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <sstream>

#include "libccmd/eval/plot.h"
#include "libccmd/system/report_format.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {
namespace {

using report::FindAgentTraffic;
using report::Fmt;
using report::Num;
using report::Str;

// The server's record of one keyframe.
struct Arrival {
  int received = 0;
  double received_ms = -1;  // the first delivery
  double dense_ms = -1;
  bool fused = false;
};
using ArrivalMap = std::map<std::pair<std::string, long long>, Arrival>;

StatusOr<ArrivalMap> ReadArrivals(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path));
  ArrivalMap arrivals;
  for (const std::string& line : Split(text, '\n')) {
    if (line.empty() || line[0] == '#') continue;
    const std::vector<std::string> f = Split(line, ',');
    if (f.size() != 4) return Corrupt(path + ": bad line '" + line + "'");
    auto id = ParseInt(f[1]);
    auto ms = ParseDouble(f[3]);
    if (!id.ok() || !ms.ok()) return Corrupt(path + ": bad line '" + line + "'");
    Arrival& a = arrivals[{f[0], *id}];
    if (f[2] == "received") {
      if (a.received++ == 0) a.received_ms = *ms;
    } else {
      a.dense_ms = *ms;
      a.fused = f[2] == "dense_fused";
    }
  }
  return arrivals;
}

// Message bytes per second between the agent's first and last message at the server.
double AgentRateBytesPerSecond(const Json* traffic) {
  if (!traffic) return 0;
  const Json* messages = traffic->Get("messages");
  const double bytes = Num(messages ? messages->Get("keyframe") : nullptr, "bytes") +
                       Num(messages ? messages->Get("pose_update") : nullptr, "bytes");
  // The first message's bytes went out before its arrival opened the span.
  const double span = Num(traffic, "last_message_s") - Num(traffic, "first_message_s");
  if (span >= 1.0) return (bytes - Num(traffic, "first_message_bytes")) / span;
  return Num(traffic, "average_traffic_bytes_per_s");
}

void PlotBudget(const Json& server_stats,
                const std::vector<std::pair<std::string, double>>& budgets,
                const std::string& path) {
  std::vector<PlotSeries> series;
  const double bucket = Num(server_stats.Get("transport"), "bucket_seconds", 1.0);
  for (std::size_t i = 0; i < budgets.size(); ++i) {
    const Json* traffic = FindAgentTraffic(server_stats, budgets[i].first);
    if (!traffic || !traffic->Get("per_bucket") || traffic->Get("per_bucket")->size() == 0)
      continue;
    std::map<long, double> kBps;
    for (const Json& b : traffic->Get("per_bucket")->array()) {
      kBps[std::lround(Num(&b, "t") / bucket)] = Num(&b, "bytes") / 1e3 / bucket;
    }
    PlotSeries raw, mean;
    raw.label = budgets[i].first + " (1 s)";
    mean.label = budgets[i].first + " (5 s mean)";
    raw.color = mean.color = SeriesColor(static_cast<int>(i));
    raw.thickness = 1;
    mean.thickness = 3;
    const long first = kBps.begin()->first, last = kBps.rbegin()->first;
    const int window = std::max(1, static_cast<int>(std::lround(5.0 / bucket)));
    for (long k = first; k <= last; ++k) {
      const double v = kBps.count(k) ? kBps[k] : 0.0;
      raw.x.push_back(k * bucket);
      raw.y.push_back(v);
      if (k - first + 1 >= window) {
        double sum = 0;
        for (long j = k - window + 1; j <= k; ++j) sum += kBps.count(j) ? kBps[j] : 0.0;
        mean.x.push_back((k - (window - 1) / 2.0) * bucket);
        mean.y.push_back(sum / window);
      }
    }
    series.push_back(raw);
    if (!mean.x.empty()) series.push_back(mean);
    if (budgets[i].second > 0) {
      PlotSeries line;
      line.label = budgets[i].first + " budget";
      line.color = SeriesColor(static_cast<int>(i)) * 0.5;
      line.thickness = 2;
      line.x = {first * bucket, (last + 1) * bucket};
      line.y = {budgets[i].second, budgets[i].second};
      series.push_back(line);
    }
  }
  PlotOptions o;
  o.title = "Message bytes per second per agent against its budget";
  o.x_label = "seconds since the server started";
  o.y_label = "kB/s";
  WritePng(PlotLines(series, o), path).IgnoreError();
}

}  // namespace

double Percentile(std::vector<double> values, double q) {
  if (values.empty()) return 0;
  std::sort(values.begin(), values.end());
  const double position = std::clamp(q, 0.0, 1.0) * (values.size() - 1);
  const std::size_t below = static_cast<std::size_t>(std::floor(position));
  const std::size_t above = std::min(values.size() - 1, below + 1);
  return values[below] + (position - below) * (values[above] - values[below]);
}

namespace {

// Keyframe delivery and latencies over all agents.
struct Latencies {
  std::vector<double> to_server, to_dense, to_dense_direct;
  std::vector<double> on_agent, on_link;  // creation -> hand-over -> the server's back-end
  int sent = 0, missing = 0, duplicated = 0, fused_in = 0, rgbd = 0;
};

// Matches one agent's keyframe log with the server's arrivals. Returns its keyframe and
// RGB-D counts.
std::pair<int, int> MatchKeyframes(const std::string& name, const Json* log,
                                   const ArrivalMap& arrivals, Latencies* out) {
  int keyframes = 0, rgbd = 0;
  if (!log) return {0, 0};
  for (const Json& k : log->array()) {
    if (k.size() < 5) continue;
    ++keyframes;
    const double created_ms = k.at(1).number(), handed_ms = k.at(2).number();
    rgbd += k.at(4).number() > 0;
    out->on_agent.push_back((handed_ms - created_ms) / 1e3);
    const auto it = arrivals.find({name, static_cast<long long>(k.at(0).number())});
    if (it == arrivals.end() || it->second.received == 0) {
      ++out->missing;
      continue;
    }
    if (it->second.received > 1) ++out->duplicated;
    out->to_server.push_back((it->second.received_ms - created_ms) / 1e3);
    out->on_link.push_back((it->second.received_ms - handed_ms) / 1e3);
    if (it->second.dense_ms < 0) continue;
    const double latency = (it->second.dense_ms - created_ms) / 1e3;
    out->to_dense.push_back(latency);
    if (it->second.fused) {
      ++out->fused_in;
    } else {
      out->to_dense_direct.push_back(latency);
    }
  }
  out->sent += keyframes;
  out->rgbd += rgbd;
  return {keyframes, rgbd};
}

// One agent's rate and budget figures into its results entry `a`, and its report row.
std::string AgentRow(const std::string& run_dir, const StatusOr<Json>& server_stats,
                     const ArrivalMap& arrivals, Json* a, Latencies* latencies,
                     double* budget_kBps) {
  const std::string name = Str(a, "name");
  const double rate = server_stats.ok()
                          ? AgentRateBytesPerSecond(FindAgentTraffic(*server_stats, name)) / 1e3
                          : 0.0;
  (*a)["kBps"] = rate;
  auto stats = ReadJsonFile(JoinPath(run_dir, "agents/" + name + "_stats.json"));
  const Json* link = stats.ok() ? stats->Get("link") : nullptr;
  const Json* budget = link ? link->Get("budget") : nullptr;
  *budget_kBps = Num(budget, "budget_kBps");
  if (budget) {
    (*a)["budget_kBps"] = *budget_kBps;
    (*a)["kBps_over_budget"] = *budget_kBps > 0 ? rate / *budget_kBps : 0.0;
    (*a)["queue_max_s"] = Num(budget, "queue_max_s");
    (*a)["queue_bound_s"] = Num(budget, "queue_bound_s");
    (*a)["rgbd_withheld_for_queue"] = Num(budget, "shed_keyframes");
    if (const Json* levels = budget->Get("keyframes_per_level"))
      (*a)["keyframes_per_level"] = *levels;
  }
  const auto [keyframes, rgbd] =
      MatchKeyframes(name, link ? link->Get("keyframe_log") : nullptr, arrivals, latencies);
  std::ostringstream md;
  md << "| " << name << " | " << (budget ? Fmt("%.0f", *budget_kBps) : "-") << " | "
     << Fmt("%.1f", rate) << " | "
     << (budget && *budget_kBps > 0 ? Fmt("%.3f", rate / *budget_kBps) : "-") << " | " << keyframes
     << " | " << rgbd << " | " << (budget ? Fmt("%.2f", Num(budget, "queue_max_s")) : "-") << " | "
     << (budget ? Fmt("%.0f", Num(budget, "shed_keyframes")) : "-") << " |\n";
  return md.str();
}

void AddLatencyResults(const Latencies& l, Json* results) {
  (*results)["keyframes_logged"] = l.sent;
  (*results)["keyframes_missing"] = l.missing;
  (*results)["keyframes_duplicated"] = l.duplicated;
  (*results)["keyframes_delivered_once"] = l.sent > 0 && l.missing == 0 && l.duplicated == 0;
  (*results)["keyframe_latency_p50_s"] = Percentile(l.to_server, 0.5);
  (*results)["keyframe_latency_p95_s"] = Percentile(l.to_server, 0.95);
  (*results)["keyframe_on_agent_p50_s"] = Percentile(l.on_agent, 0.5);
  (*results)["keyframe_on_agent_p95_s"] = Percentile(l.on_agent, 0.95);
  (*results)["keyframe_on_link_p50_s"] = Percentile(l.on_link, 0.5);
  (*results)["keyframe_on_link_p95_s"] = Percentile(l.on_link, 0.95);
  // The map latency proper counts keyframes whose map was in the world frame when they
  // arrived; the others' wait for their map's fusion is reported beside it ("_all").
  (*results)["map_latency_keyframes"] = static_cast<int>(l.to_dense_direct.size());
  (*results)["map_latency_p50_s"] = Percentile(l.to_dense_direct, 0.5);
  (*results)["map_latency_p95_s"] = Percentile(l.to_dense_direct, 0.95);
  (*results)["map_latency_max_s"] = Percentile(l.to_dense_direct, 1.0);
  (*results)["map_latency_all_keyframes"] = static_cast<int>(l.to_dense.size());
  (*results)["map_latency_all_p50_s"] = Percentile(l.to_dense, 0.5);
  (*results)["map_latency_all_p95_s"] = Percentile(l.to_dense, 0.95);
  (*results)["map_latency_after_fusion_keyframes"] = l.fused_in;
}

std::string LatencySection(const Latencies& l) {
  std::ostringstream md;
  const bool once = l.sent > 0 && l.missing == 0 && l.duplicated == 0;
  md << "Keyframes: " << l.sent << " sent, " << (l.sent - l.missing) << " received, " << l.missing
     << " missing, " << l.duplicated << " received more than once"
     << (once ? " (every keyframe exactly once)" : "") << ".\n\n";
  md << "| latency | keyframes | median (s) | 95 % (s) | max (s) |\n|---|---:|---:|---:|---:|\n";
  auto row = [&](const std::string& what, const std::vector<double>& v) {
    md << "| " << what << " | " << v.size() << " | " << Fmt("%.3f", Percentile(v, 0.5)) << " | "
       << Fmt("%.3f", Percentile(v, 0.95)) << " | " << Fmt("%.3f", Percentile(v, 1.0)) << " |\n";
  };
  row("creation -> handed to the link (the agent's local mapping, selection, coding)", l.on_agent);
  row("handed to the link -> received by the server's back-end (queue, link, journal)", l.on_link);
  row("creation on the agent -> received by the server's back-end", l.to_server);
  row("**creation -> points in the dense map (map latency)**", l.to_dense_direct);
  row("the same with keyframes that waited for their map's fusion", l.to_dense);
  md << "\n"
     << l.rgbd << " keyframes carried RGB-D; " << l.to_dense.size()
     << " have points in the dense map, " << l.fused_in
     << " of them came in with a map fusion. The dense map holds only maps in the world frame (the "
        "primary map and what is fused into it): a keyframe of another map waits for that fusion, "
        "which depends on when the agents' views first overlap, not on the link; the map latency "
        "counts "
        "the keyframes whose map was already in the world frame.\n";
  return md.str();
}

}  // namespace

StatusOr<std::string> AddLinkFigures(const std::string& run_dir, const LinkRunInfo& info,
                                     Json* results) {
  (*results)["link"] = info.link.empty() ? std::string("loopback") : info.link;
  if (!info.link_stats.is_null()) (*results)["link_stats"] = info.link_stats;
  const auto server_stats = ReadJsonFile(JoinPath(run_dir, "server_stats.json"));
  const auto arrivals = ReadArrivals(JoinPath(run_dir, "keyframe_arrivals.csv"));
  std::ostringstream md;
  md << "\n## Link, budget and map latency\n\n";
  md << "Link: "
     << (info.link.empty()
             ? "loopback (no shaping)"
             : "`" + info.link + "` (network namespaces, tbf rate, delay/jitter/loss stage)")
     << ".\n\n";
  if (!arrivals.ok()) {
    md << "No keyframe_arrivals.csv from the server (" << arrivals.status().ToString()
       << "): no latency figures.\n";
    return md.str();
  }
  Latencies latencies;
  std::vector<std::pair<std::string, double>> budgets;
  Json::Array agents = results->Get("agents") ? results->Get("agents")->array() : Json::Array{};
  md << "| agent | budget (kB/s) | rate (kB/s) | rate / budget | keyframes | RGB-D | queue max (s) "
        "| RGB-D withheld "
        "(queue) |\n|---|---:|---:|---:|---:|---:|---:|---:|\n";
  for (Json& a : agents) {
    double budget_kBps = 0;
    md << AgentRow(run_dir, server_stats, *arrivals, &a, &latencies, &budget_kBps);
    budgets.emplace_back(Str(&a, "name"), budget_kBps);
  }
  (*results)["agents"] = Json(agents);
  AddLatencyResults(latencies, results);
  md << "\nRate: message bytes the server received from the agent between its first and last "
        "message, per second. "
        "Queue: bytes handed to the link and not yet acknowledged, in seconds at the rate the link "
        "gave.\n\n";
  md << LatencySection(latencies);
  const bool any_budget =
      std::any_of(budgets.begin(), budgets.end(), [](const auto& b) { return b.second > 0; });
  if (any_budget && server_stats.ok()) {
    PlotBudget(*server_stats, budgets, JoinPath(run_dir, "plots/budget.png"));
    md << "\n![budget](plots/budget.png)\n";
  }
  return md.str();
}

Status AppendBudgetSweep(const std::string& run_dir, const std::vector<BudgetRow>& rows) {
  CCMD_ASSIGN_OR_RETURN(Json results, ReadJsonFile(JoinPath(run_dir, "results.json")));
  CCMD_ASSIGN_OR_RETURN(std::string report, ReadFileToString(JoinPath(run_dir, "report.md")));
  std::ostringstream md;
  md << "\n## Bandwidth budget sweep\n\n"
     << "Each row is a full run of the same replay with every agent under the budget (none: the "
        "agents' defaults, no "
        "budget). Rate: mean over agents of the bytes each sent per second between its first and "
        "last message.\n\n"
     << "| budget (kB/s) | rate (kB/s) | rate / budget | keyframes | with RGB-D | map latency p50 "
        "/ p95 (s) | "
        "recon mean (m) | completeness | fused ATE (m) | maps | run |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n";
  Json list = Json::MakeArray();
  PlotSeries error, completeness;
  error.label = "reconstruction mean error (mm)";
  completeness.label = "completeness (% of reference within 2 cm)";
  error.color = SeriesColor(0);
  completeness.color = SeriesColor(1);
  error.points = completeness.points = true;
  for (const BudgetRow& row : rows) {
    const Json& r = row.results;
    double rate = 0;
    int n = 0;
    if (const Json* agents = r.Get("agents")) {
      for (const Json& a : agents->array()) {
        rate += Num(&a, "kBps");
        ++n;
      }
    }
    rate = n ? rate / n : 0.0;
    Json e;
    e["budget_kBps"] = row.budget_kBps;
    e["run_dir"] = row.run_dir;
    e["kBps"] = rate;
    for (const char* key : {"keyframes_sent", "rgbd_keyframes", "map_latency_p50_s",
                            "map_latency_p95_s", "recon_mean_m", "recon_completeness", "ate_rmse_m",
                            "maps_after_fusion", "keyframes_delivered_once"}) {
      if (const Json* v = r.Get(key)) e[key] = *v;
    }
    list.Push(e);
    md << "| " << (row.budget_kBps > 0 ? Fmt("%.0f", row.budget_kBps) : "none") << " | "
       << Fmt("%.1f", rate) << " | "
       << (row.budget_kBps > 0 ? Fmt("%.3f", rate / row.budget_kBps) : "-") << " | "
       << Num(&r, "keyframes_sent") << " | " << Num(&r, "rgbd_keyframes") << " | "
       << Fmt("%.2f", Num(&r, "map_latency_p50_s")) << " / "
       << Fmt("%.2f", Num(&r, "map_latency_p95_s")) << " | "
       << (r.Has("recon_mean_m") ? Fmt("%.4f", Num(&r, "recon_mean_m")) : "-") << " | "
       << (r.Has("recon_completeness") ? Fmt("%.1f%%", 100 * Num(&r, "recon_completeness")) : "-")
       << " | " << (r.Has("ate_rmse_m") ? Fmt("%.4f", Num(&r, "ate_rmse_m")) : "-") << " | "
       << Num(&r, "maps_after_fusion", -1) << " | `" << row.run_dir << "` |\n";
    if (row.budget_kBps > 0 && r.Has("recon_mean_m")) {
      error.x.push_back(row.budget_kBps);
      error.y.push_back(1e3 * Num(&r, "recon_mean_m"));
      completeness.x.push_back(row.budget_kBps);
      completeness.y.push_back(100 * Num(&r, "recon_completeness"));
    }
  }
  results["budget_sweep"] = list;
  PlotOptions o;
  o.title = "Dense map against the bandwidth budget per agent";
  o.x_label = "budget per agent (kB/s)";
  o.y_label = "mm  /  %";
  std::vector<PlotSeries> series = {error, completeness};
  // The unbudgeted run as horizontal references.
  for (const BudgetRow& row : rows) {
    if (row.budget_kBps > 0 || !row.results.Has("recon_mean_m") || error.x.empty()) continue;
    const auto [lo, hi] = std::minmax_element(error.x.begin(), error.x.end());
    PlotSeries e, c;
    e.label = "mean error, no budget";
    c.label = "completeness, no budget";
    e.color = SeriesColor(0) * 0.5;
    c.color = SeriesColor(1) * 0.5;
    e.thickness = c.thickness = 1;
    e.x = c.x = {*lo, *hi};
    e.y = {1e3 * Num(&row.results, "recon_mean_m"), 1e3 * Num(&row.results, "recon_mean_m")};
    c.y = {100 * Num(&row.results, "recon_completeness"),
           100 * Num(&row.results, "recon_completeness")};
    series.push_back(e);
    series.push_back(c);
  }
  CCMD_RETURN_IF_ERROR(MakeDirectories(JoinPath(run_dir, "plots")));
  WritePng(PlotLines(series, o), JoinPath(run_dir, "plots/budget_sweep.png")).IgnoreError();
  md << "\n![budget sweep](plots/budget_sweep.png)\n";
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(run_dir, "report.md"), report + md.str()));
  return WriteJsonFile(results, JoinPath(run_dir, "results.json"));
}

Status AppendKnobCosts(const std::string& run_dir, const std::vector<KnobRow>& rows) {
  if (rows.empty()) return InvalidArgument("no knob rows");
  CCMD_ASSIGN_OR_RETURN(Json results, ReadJsonFile(JoinPath(run_dir, "results.json")));
  CCMD_ASSIGN_OR_RETURN(std::string report, ReadFileToString(JoinPath(run_dir, "report.md")));
  auto rgbd_per_keyframe = [](const Json& r) {
    return (Num(&r, "colour_bytes") + Num(&r, "depth_bytes")) /
           std::max(1.0, Num(&r, "keyframes_sent"));
  };
  const Json& base = rows.front().results;
  const double base_bytes = rgbd_per_keyframe(base),
               base_completeness = Num(&base, "recon_completeness");
  std::ostringstream md;
  md << "\n## What each RGB-D knob costs the map\n\n"
     << "Each row is a full run of the same replay with one RGB-D setting changed from the agents' "
        "defaults (first "
        "row). Bytes are colour and depth per keyframe sent (with or without RGB-D). Cost: "
        "completeness points lost "
        "per kB saved per keyframe; for a setting that spends more, points gained per kB spent. "
        "Completeness moves by "
        "several points between runs of one setting (the trajectories differ), so single runs rank "
        "only large "
        "effects; ccmd_knob_bench measures the same knobs at ground-truth poses.\n\n"
     << "| setting | RGB-D kB/keyframe | change | RGB-D keyframes | map points | completeness | "
        "change (pp) | "
        "recon mean (mm) | fused ATE (cm) | cost (pp per kB) | run |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n";
  Json list = Json::MakeArray();
  for (const KnobRow& row : rows) {
    const Json& r = row.results;
    const double bytes = rgbd_per_keyframe(r), completeness = Num(&r, "recon_completeness");
    const double saved_kB = (base_bytes - bytes) / 1e3,
                 lost_pp = 100 * (base_completeness - completeness);
    const bool reference = &row == &rows.front();
    Json e;
    e["knob"] = row.knob;
    e["run_dir"] = row.run_dir;
    e["rgbd_bytes_per_keyframe"] = bytes;
    e["map_points"] = Num(&r, "map_points");
    e["recon_completeness"] = completeness;
    e["recon_mean_m"] = Num(&r, "recon_mean_m");
    e["ate_rmse_m"] = Num(&r, "ate_rmse_m");
    e["maps_after_fusion"] = Num(&r, "maps_after_fusion", -1);
    const bool has_cost = !reference && std::fabs(saved_kB) > 0.05;
    if (has_cost) e["completeness_pp_per_kB"] = lost_pp / saved_kB;
    list.Push(e);
    md << "| " << row.knob << " | " << Fmt("%.2f", bytes / 1e3) << " | "
       << (reference ? std::string("-") : Fmt("%+.2f", -saved_kB)) << " | "
       << Num(&r, "rgbd_keyframes") << " of " << Num(&r, "keyframes_sent") << " | "
       << Fmt("%.0f", Num(&r, "map_points")) << " | " << Fmt("%.1f%%", 100 * completeness) << " | "
       << (reference ? std::string("-") : Fmt("%+.1f", -lost_pp)) << " | "
       << Fmt("%.1f", 1e3 * Num(&r, "recon_mean_m")) << " | "
       << Fmt("%.2f", 100 * Num(&r, "ate_rmse_m")) << " | "
       << (has_cost ? Fmt("%.2f", lost_pp / saved_kB) : std::string("-")) << " | `" << row.run_dir
       << "` |\n";
  }
  results["knob_costs"] = list;
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(run_dir, "report.md"), report + md.str()));
  return WriteJsonFile(results, JoinPath(run_dir, "results.json"));
}

}  // namespace ccmd
