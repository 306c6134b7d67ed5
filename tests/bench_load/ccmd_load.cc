// ccmd_load: a load generator for ccmd_server. Replays recorded keyframe streams (a run's
// journals) as N concurrent agents over TCP, each with its own name and rigid offset, at a
// chosen keyframe rate for a bounded time, and reports what was sent, acknowledged and lost,
// and, from the server's statistics file, its intake latency, memory, CPU and backlog.
//
//   ccmd_server --listen 127.0.0.1:7420 --journal run/journal --out run/results
//       --psk-file key --stats-interval 1 &
//   ccmd_load --server 127.0.0.1:7420 --journals recorded/journal --agents 8 --rate 5.5
//       --seconds 600 --psk-file key --server-stats run/results/server_stats.json
//       --json load.json --plots plots/
//
// scripts/load_test.sh runs both (docs/benchmarks/server_load.md).

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>

#include "libccmd/eval/plot.h"
#include "libccmd/net/psk.h"
#include "libccmd/util/file_util.h"
#include "tests/bench_load/load_run.h"

namespace {

using namespace ccmd;
using namespace ccmd::load;

// One chart of some sample fields over time (negative values: not measured, left out).
Status Chart(
    const LoadResult& r, const std::string& path, const std::string& title,
    const std::string& y_label,
    const std::vector<std::pair<std::string, std::function<double(const LoadSample&)>>>& fields) {
  std::vector<PlotSeries> series;
  for (std::size_t f = 0; f < fields.size(); ++f) {
    PlotSeries s;
    s.label = fields[f].first;
    s.color = SeriesColor(static_cast<int>(f));
    for (const LoadSample& sample : r.series) {
      const double y = fields[f].second(sample);
      if (y < 0) continue;
      s.x.push_back(sample.time_s);
      s.y.push_back(y);
    }
    if (!s.x.empty()) series.push_back(std::move(s));
  }
  if (series.empty()) return Status::Ok();
  PlotOptions options;
  options.title = title;
  options.x_label = "time (s)";
  options.y_label = y_label;
  return WritePng(PlotLines(series, options), path);
}

Status WritePlots(const LoadResult& r, const std::string& dir) {
  CCMD_RETURN_IF_ERROR(MakeDirectories(dir));
  const std::string n = std::to_string(r.agents) + " agents";
  CCMD_RETURN_IF_ERROR(Chart(r, JoinPath(dir, "memory.png"), "server memory, " + n, "resident MB",
                             {{"RSS", [](const LoadSample& s) { return s.rss_mb; }}}));
  CCMD_RETURN_IF_ERROR(
      Chart(r, JoinPath(dir, "intake.png"), "intake latency over the last minute, " + n, "ms",
            {{"in the map, p50", [](const LoadSample& s) { return s.intake_p50_ms; }},
             {"in the map, p99", [](const LoadSample& s) { return s.intake_p99_ms; }},
             {"in the dense map, p50", [](const LoadSample& s) { return s.dense_p50_ms; }},
             {"in the dense map, p99", [](const LoadSample& s) { return s.dense_p99_ms; }}}));
  CCMD_RETURN_IF_ERROR(
      Chart(r, JoinPath(dir, "backlog.png"), "backlog, " + n, "items",
            {{"keyframes not yet stored (agents)",
              [](const LoadSample& s) { return static_cast<double>(s.unacked); }},
             {"ingest queue", [](const LoadSample& s) { return s.ingest_backlog; }},
             {"loop queue", [](const LoadSample& s) { return s.loop_backlog; }},
             {"dense queue", [](const LoadSample& s) { return s.dense_backlog; }}}));
  // CPU: the server's CPU seconds per second, as a share of one core.
  LoadResult cpu = r;
  for (std::size_t i = 0; i < cpu.series.size(); ++i) {
    const LoadSample& a = r.series[i > 0 ? i - 1 : 0];
    const LoadSample& b = r.series[i];
    const double dt = b.time_s - a.time_s;
    cpu.series[i].cpu_seconds =
        (i > 0 && dt > 0 && a.cpu_seconds >= 0) ? 100 * (b.cpu_seconds - a.cpu_seconds) / dt : -1;
  }
  return Chart(cpu, JoinPath(dir, "cpu.png"), "server CPU, " + n, "% of one core",
               {{"server", [](const LoadSample& s) { return s.cpu_seconds; }}});
}

void PrintSummary(const Json& j) {
  std::printf(
      "agents %d, %.1f keyframes/s each for %.0f s: sent %.0f, acknowledged %.0f, lost %.0f\n",
      static_cast<int>(j.Get("agents")->number()), j.Get("rate")->number(),
      j.Get("seconds")->number(), j.Get("keyframes_sent")->number(),
      j.Get("keyframes_acked")->number(), j.Get("lost")->number());
  std::printf(
      "acknowledged in p50 %.1f ms, p99 %.1f ms; server intake over the last minute: p50 %.1f ms, "
      "p99 %.1f ms "
      "(dense map p50 %.1f, p99 %.1f ms); server peak memory %.0f MB, CPU %.0f %% of a core\n",
      j.Get("ack_p50_ms")->number(), j.Get("ack_p99_ms")->number(),
      j.Get("intake_p50_ms")->number(-1), j.Get("intake_p99_ms")->number(-1),
      j.Get("dense_intake_p50_ms")->number(-1), j.Get("dense_intake_p99_ms")->number(-1),
      j.Get("server_peak_rss_mb")->number(-1), j.Get("server_cpu_percent")->number(-1));
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"ccmd_load: replays recorded keyframe streams as N agents against a ccmd_server"};
  LoadOptions options;
  std::string journals, psk_file, json_path, plots;
  app.add_option("--server", options.server, "HOST:PORT of the server")->required();
  app.add_option("--journals", journals,
                 "A run's journal folder (agent_*.journal): the streams to replay")
      ->required();
  app.add_option("--agents", options.agents, "Concurrent agents (streams are shared round robin)")
      ->capture_default_str();
  app.add_option("--rate", options.rate, "Keyframes per second per agent")->capture_default_str();
  app.add_option("--seconds", options.seconds, "Sending time")->capture_default_str();
  app.add_option("--psk-file", psk_file,
                 "Pre-shared key file (else $CCMD_PSK; without either: no key)");
  app.add_option("--json", json_path, "Write the figures as JSON");
  app.add_option(
      "--server-stats", options.server_stats,
      "The server's server_stats.json (its --out folder; run it with --stats-interval 1): intake, "
      "memory, CPU and backlog");
  app.add_option("--plots", plots, "Folder for memory, intake, CPU and backlog charts (PNG)");
  app.add_option("--name-prefix", options.name_prefix, "Agent names: PREFIX-1, PREFIX-2, ...")
      ->capture_default_str();
  app.add_option("--spill-dir", options.spill_dir, "Resend buffers past their memory limit");
  app.add_option("--drain-timeout", options.drain_timeout_s,
                 "Seconds to wait for acknowledgements and intake at the end")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  auto psk = ResolvePsk(psk_file);
  if (!psk.ok()) {
    std::fprintf(stderr, "ccmd_load: %s\n", psk.status().ToString().c_str());
    return 2;
  }
  options.psk = *psk;
  if (const Status s = options.Validate(); !s.ok()) {
    std::fprintf(stderr, "ccmd_load: %s\n", s.ToString().c_str());
    return 2;
  }
  auto streams = ReadJournalStreams(journals);
  if (!streams.ok()) {
    std::fprintf(stderr, "ccmd_load: %s\n", streams.status().ToString().c_str());
    return 2;
  }
  std::printf(
      "ccmd_load: %zu streams from %s (%zu keyframes in the first); %d agents at %.1f keyframes/s "
      "for %.0f s\n",
      streams->size(), journals.c_str(), (*streams)[0].keyframes, options.agents, options.rate,
      options.seconds);
  std::fflush(stdout);
  auto result = RunLoad(options, *streams);
  if (!result.ok()) {
    std::fprintf(stderr, "ccmd_load: %s\n", result.status().ToString().c_str());
    return 1;
  }
  for (const std::string& e : result->errors) std::fprintf(stderr, "ccmd_load: %s\n", e.c_str());
  const Json j = LoadResultJson(*result);
  PrintSummary(j);
  if (!json_path.empty()) {
    if (const Status s = WriteJsonFile(j, json_path); !s.ok()) {
      std::fprintf(stderr, "ccmd_load: %s\n", s.ToString().c_str());
      return 1;
    }
  }
  if (!plots.empty()) {
    if (const Status s = WritePlots(*result, plots); !s.ok())
      std::fprintf(stderr, "ccmd_load: plots: %s\n", s.ToString().c_str());
  }
  return result->errors.empty() ? 0 : 1;
}
