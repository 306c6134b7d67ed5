#pragma once

// One load run of ccmd_load: N agents, each an AgentLink of its own (the project's agent
// transport, so that the run follows the protocol as it changes), replay keyframe streams at a
// fixed keyframe rate for a bounded time. The server's own view (intake latency, memory, CPU,
// backlog) is read once a second from the statistics file it rewrites.

#include <cstdint>
#include <string>
#include <vector>

#include "libccmd/util/json.h"
#include "libccmd/util/status.h"
#include "tests/bench_load/journal_stream.h"

namespace ccmd::load {

struct LoadOptions {
  std::string server;  // HOST:PORT
  std::string psk;     // "" for a keyless loopback server
  int agents = 8;
  double rate = 5.5;     // keyframes per second per agent (the paper's highest)
  double seconds = 600;  // sending time
  std::string name_prefix = "load";
  std::string spill_dir;         // resend buffers past their memory limit ("" = none)
  std::string server_stats;      // the server's server_stats.json ("" = no server figures)
  double drain_timeout_s = 300;  // after sending: acknowledgements, then the server's intake

  Status Validate() const;
};

// Once a second during the run.
struct LoadSample {
  double time_s = 0;                               // since the first keyframe
  std::uint64_t sent = 0, acked = 0, unacked = 0;  // keyframes, all agents
  // From the server's statistics (negative when not read).
  double rss_mb = -1, cpu_seconds = -1;
  double intake_p50_ms = -1, intake_p99_ms = -1;  // over the last minute
  double dense_p50_ms = -1, dense_p99_ms = -1;
  double keyframes = -1;  // in the server's maps
  double ingest_backlog = -1, loop_backlog = -1, dense_backlog = -1;
};

struct LoadResult {
  int agents = 0;
  int streams = 0;
  double rate = 0, seconds = 0;
  std::uint64_t keyframes_sent = 0, keyframes_acked = 0, pose_updates_sent = 0;
  std::uint64_t bytes_sent = 0;
  double mean_keyframe_bytes = 0;
  std::vector<double> ack_ms;  // per keyframe: Send to acknowledgement (stored by the server)
  std::vector<LoadSample> series;
  LoadSample end_of_sending;  // the sample taken when sending stopped
  Json server_final;          // the server's statistics after the drain
  double server_keyframes_received = -1;
  std::vector<std::string> errors;  // links that failed
};

StatusOr<LoadResult> RunLoad(const LoadOptions& options, const std::vector<JournalStream>& streams);

// The figures of a run (the interface of ccmd_load --json).
Json LoadResultJson(const LoadResult& result);

}  // namespace ccmd::load
