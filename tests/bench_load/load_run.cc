#include "tests/bench_load/load_run.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <memory>
#include <mutex>
#include <thread>

#include "libccmd/net/agent_link.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/percentile.h"
#include "libccmd/util/timer.h"

namespace ccmd::load {
namespace {

struct Agent {
  int index = 0;
  const JournalStream* stream = nullptr;
  Pose offset = Pose::Identity();
  std::unique_ptr<AgentLink> link;
  std::size_t next_message = 0;
  std::uint32_t lap = 0;
  double next_due = 0;
  std::uint64_t keyframes_sent = 0;

  std::mutex mutex;  // guards what follows: the link thread acknowledges
  std::deque<std::pair<std::uint64_t, double>> pending;  // keyframes' link numbers, send times
  std::uint64_t acked = 0;
  std::vector<double> ack_ms;
};

void OnAcked(Agent* agent, std::uint64_t last) {
  const double now = MonotonicSeconds();
  std::lock_guard<std::mutex> lock(agent->mutex);
  while (!agent->pending.empty() && agent->pending.front().first <= last) {
    agent->ack_ms.push_back((now - agent->pending.front().second) * 1e3);
    agent->pending.pop_front();
    agent->acked++;
  }
}

// Sends the pose updates before the agent's next keyframe, then the keyframe.
Status SendNext(Agent* agent, LoadResult* result) {
  while (true) {
    const StreamMessage& m = agent->stream->messages[agent->next_message];
    const std::uint32_t lap = agent->lap;
    if (++agent->next_message == agent->stream->messages.size()) {
      agent->next_message = 0;
      agent->lap++;
    }
    if (m.pose_update) {
      CCMD_ASSIGN_OR_RETURN(
          std::vector<std::uint8_t> bytes,
          SerializePoseUpdate(LapPoseUpdate(*agent->stream, *m.pose_update, lap, agent->offset)));
      result->bytes_sent += bytes.size();
      CCMD_RETURN_IF_ERROR(agent->link->Send(MessageType::kPoseUpdate, std::move(bytes)).status());
      result->pose_updates_sent++;
      continue;
    }
    CCMD_ASSIGN_OR_RETURN(
        std::vector<std::uint8_t> bytes,
        SerializeKeyframe(LapKeyframe(*agent->stream, *m.keyframe, lap, agent->offset)));
    result->bytes_sent += bytes.size();
    std::lock_guard<std::mutex> lock(agent->mutex);  // the acknowledgement must find it pending
    CCMD_ASSIGN_OR_RETURN(const std::uint64_t number,
                          agent->link->Send(MessageType::kKeyframe, std::move(bytes)));
    agent->pending.emplace_back(number, MonotonicSeconds());
    agent->keyframes_sent++;
    result->keyframes_sent++;
    return Status::Ok();
  }
}

double Number(const Json* j, const char* key) {
  const Json* v = j ? j->Get(key) : nullptr;
  return v && v->is_number() ? v->number() : -1;
}

// The server's statistics file, if it reads.
std::optional<Json> ReadServerStats(const std::string& path) {
  if (path.empty()) return std::nullopt;
  auto text = ReadFileToString(path, 256u << 20);
  if (!text.ok()) return std::nullopt;
  auto json = Json::Parse(*text);
  if (!json.ok()) return std::nullopt;  // caught between rewrites (they are atomic, but be safe)
  return std::move(json).value();
}

LoadSample Sample(double time_s, const std::vector<std::unique_ptr<Agent>>& agents,
                  const std::optional<Json>& stats) {
  LoadSample s;
  s.time_s = time_s;
  for (const auto& a : agents) {
    std::lock_guard<std::mutex> lock(a->mutex);
    s.sent += a->keyframes_sent;
    s.acked += a->acked;
    s.unacked += a->pending.size();
  }
  if (!stats) return s;
  const Json* backend = stats->Get("backend");
  const Json* process = stats->Get("process");
  s.rss_mb = Number(process, "rss_mb");
  s.cpu_seconds = Number(process, "cpu_seconds");
  s.intake_p50_ms = Number(backend, "intake_last_minute_ms_median");
  s.intake_p99_ms = Number(backend, "intake_last_minute_ms_p99");
  s.dense_p50_ms = Number(backend, "dense_intake_last_minute_ms_median");
  s.dense_p99_ms = Number(backend, "dense_intake_last_minute_ms_p99");
  s.keyframes = Number(backend, "keyframes");
  s.ingest_backlog = Number(backend, "ingest_backlog");
  s.loop_backlog = Number(backend, "loop_backlog");
  s.dense_backlog = Number(backend, "dense_backlog");
  return s;
}

double ServerReceived(const std::optional<Json>& stats) {
  return stats ? Number(stats->Get("backend"), "keyframes_received") : -1;
}

StatusOr<std::vector<std::unique_ptr<Agent>>> Connect(const LoadOptions& options,
                                                      const std::vector<JournalStream>& streams) {
  std::vector<std::unique_ptr<Agent>> agents;
  for (int i = 0; i < options.agents; ++i) {
    auto agent = std::make_unique<Agent>();
    agent->index = i;
    agent->stream = &streams[i % streams.size()];
    agent->offset = AgentOffset(i);
    AgentLinkOptions link;
    link.server = options.server;
    link.name = options.name_prefix + "-" + std::to_string(i + 1);
    link.camera = agent->stream->camera;
    link.psk = options.psk;
    if (!options.spill_dir.empty()) link.spill_dir = JoinPath(options.spill_dir, link.name);
    link.jitter_seed = static_cast<std::uint64_t>(i + 1);
    Agent* raw = agent.get();
    link.on_acked = [raw](std::uint64_t, std::uint64_t last) { OnAcked(raw, last); };
    CCMD_ASSIGN_OR_RETURN(agent->link, AgentLink::Create(std::move(link)));
    agents.push_back(std::move(agent));
  }
  return agents;
}

// Sends on every agent's schedule for options.seconds, sampling once a second.
Status Send(const LoadOptions& options, const std::vector<std::unique_ptr<Agent>>& agents,
            LoadResult* result) {
  const double t0 = MonotonicSeconds() + 0.2;
  const double period = 1.0 / options.rate;
  for (const auto& a : agents)
    a->next_due = t0 + period * a->index / agents.size();  // spread over one period
  double next_sample = t0;
  while (true) {
    Agent* due = std::min_element(agents.begin(), agents.end(), [](const auto& a, const auto& b) {
                   return a->next_due < b->next_due;
                 })->get();
    const double when = std::min(due->next_due, next_sample);
    if (when - t0 >= options.seconds) break;
    std::this_thread::sleep_until(
        std::chrono::steady_clock::now() +
        std::chrono::duration<double>(std::max(0.0, when - MonotonicSeconds())));
    if (next_sample <= due->next_due) {
      result->series.push_back(
          Sample(next_sample - t0, agents, ReadServerStats(options.server_stats)));
      if (result->series.size() % 30 == 0) {
        const LoadSample& s = result->series.back();
        std::printf(
            "%5.0f s  sent %llu  acked %llu  server: %.0f keyframes, %.0f MB, intake p99 %.0f ms "
            "(last minute)\n",
            s.time_s, static_cast<unsigned long long>(s.sent),
            static_cast<unsigned long long>(s.acked), s.keyframes, s.rss_mb, s.intake_p99_ms);
        std::fflush(stdout);
      }
      next_sample += 1.0;
      continue;
    }
    const Status sent = SendNext(due, result);
    if (!sent.ok())
      return sent.WithContext(options.name_prefix + "-" + std::to_string(due->index + 1));
    due->next_due += period;
  }
  result->end_of_sending =
      Sample(MonotonicSeconds() - t0, agents, ReadServerStats(options.server_stats));
  result->series.push_back(result->end_of_sending);
  return Status::Ok();
}

// Waits for every acknowledgement, then for the server to take in every keyframe.
void Drain(const LoadOptions& options, const std::vector<std::unique_ptr<Agent>>& agents,
           double received_before, LoadResult* result) {
  const double deadline = MonotonicSeconds() + options.drain_timeout_s;
  for (const auto& a : agents) {
    const Status s = a->link->Flush(std::max(1.0, deadline - MonotonicSeconds()));
    if (!s.ok())
      result->errors.push_back(a->link->stats().last_error.empty() ? s.ToString()
                                                                   : a->link->stats().last_error);
  }
  while (!options.server_stats.empty()) {
    const std::optional<Json> stats = ReadServerStats(options.server_stats);
    const double received = ServerReceived(stats);
    if (stats) result->server_final = *stats;
    if (received >= 0)
      result->server_keyframes_received = received - std::max(0.0, received_before);
    if (result->server_keyframes_received >= static_cast<double>(result->keyframes_sent) ||
        MonotonicSeconds() > deadline) {
      break;
    }
    std::this_thread::sleep_for(
        std::chrono::seconds(1));  // the server rewrites the file once a period
  }
}

}  // namespace

Status LoadOptions::Validate() const {
  if (server.empty()) return InvalidArgument("give the server as HOST:PORT");
  if (agents < 1 || agents > 255) return InvalidArgument("agents must be within [1, 255]");
  if (!(rate > 0 && rate <= 100))
    return InvalidArgument("the keyframe rate must be within (0, 100] per second");
  if (!(seconds > 0)) return InvalidArgument("seconds must be positive");
  if (!(drain_timeout_s > 0)) return InvalidArgument("the drain time-out must be positive");
  return Status::Ok();
}

StatusOr<LoadResult> RunLoad(const LoadOptions& options,
                             const std::vector<JournalStream>& streams) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (streams.empty()) return InvalidArgument("no keyframe streams");
  LoadResult result;
  result.agents = options.agents;
  result.streams = static_cast<int>(streams.size());
  result.rate = options.rate;
  result.seconds = options.seconds;
  const double received_before = ServerReceived(ReadServerStats(options.server_stats));
  CCMD_ASSIGN_OR_RETURN(std::vector<std::unique_ptr<Agent>> agents, Connect(options, streams));
  const Status sent = Send(options, agents, &result);
  if (!sent.ok()) result.errors.push_back(sent.ToString());
  Drain(options, agents, received_before, &result);
  for (const auto& a : agents) {
    std::lock_guard<std::mutex> lock(a->mutex);
    result.keyframes_acked += a->acked;
    result.ack_ms.insert(result.ack_ms.end(), a->ack_ms.begin(), a->ack_ms.end());
  }
  std::uint64_t keyframe_bytes = 0, keyframes = 0;
  for (const JournalStream& s : streams) {
    keyframe_bytes += s.keyframe_bytes;
    keyframes += s.keyframes;
  }
  result.mean_keyframe_bytes = keyframes ? static_cast<double>(keyframe_bytes) / keyframes : 0;
  for (auto& a : agents) a->link->Close();
  return result;
}

Json LoadResultJson(const LoadResult& r) {
  Json j;
  j["agents"] = r.agents;
  j["streams"] = r.streams;
  j["rate"] = r.rate;
  j["seconds"] = r.seconds;
  j["keyframes_sent"] = r.keyframes_sent;
  j["keyframes_acked"] = r.keyframes_acked;
  j["lost"] = r.keyframes_sent - r.keyframes_acked;
  j["pose_updates_sent"] = r.pose_updates_sent;
  j["mean_keyframe_bytes"] = r.mean_keyframe_bytes;
  j["bytes_sent"] = r.bytes_sent;
  j["ack_p50_ms"] = Percentile(r.ack_ms, 0.5);
  j["ack_p99_ms"] = Percentile(r.ack_ms, 0.99);
  const auto optional = [](double v) { return v < 0 ? Json() : Json(v); };
  // The server's intake over the last minute of sending.
  j["intake_p50_ms"] = optional(r.end_of_sending.intake_p50_ms);
  j["intake_p99_ms"] = optional(r.end_of_sending.intake_p99_ms);
  j["dense_intake_p50_ms"] = optional(r.end_of_sending.dense_p50_ms);
  j["dense_intake_p99_ms"] = optional(r.end_of_sending.dense_p99_ms);
  j["server_keyframes_received"] = optional(r.server_keyframes_received);
  const Json* process = r.server_final.Get("process");
  const Json* peak = process ? process->Get("peak_rss_mb") : nullptr;
  j["server_peak_rss_mb"] = peak ? *peak : Json();
  // From the first sample that has the server's CPU (the first ones may precede its file).
  double cpu = -1;
  const auto first = std::find_if(r.series.begin(), r.series.end(),
                                  [](const LoadSample& s) { return s.cpu_seconds >= 0; });
  if (first != r.series.end() && r.end_of_sending.cpu_seconds >= 0 &&
      r.end_of_sending.time_s > first->time_s) {
    cpu = 100 * (r.end_of_sending.cpu_seconds - first->cpu_seconds) /
          (r.end_of_sending.time_s - first->time_s);
  }
  j["server_cpu_percent"] = optional(cpu);
  if (const Json* backend = r.server_final.Get("backend")) j["server_backend"] = *backend;
  if (const Json* memory = r.server_final.Get("memory")) j["server_memory"] = *memory;
  Json series = Json::MakeArray();
  for (const LoadSample& s : r.series) {
    Json x;
    x["t"] = s.time_s;
    x["sent"] = s.sent;
    x["acked"] = s.acked;
    x["unacked"] = s.unacked;
    x["rss_mb"] = optional(s.rss_mb);
    x["cpu_s"] = optional(s.cpu_seconds);
    x["intake_p50_ms"] = optional(s.intake_p50_ms);
    x["intake_p99_ms"] = optional(s.intake_p99_ms);
    x["dense_p99_ms"] = optional(s.dense_p99_ms);
    x["keyframes"] = optional(s.keyframes);
    x["ingest_backlog"] = optional(s.ingest_backlog);
    x["loop_backlog"] = optional(s.loop_backlog);
    x["dense_backlog"] = optional(s.dense_backlog);
    series.Push(x);
  }
  j["series"] = series;
  for (const std::string& e : r.errors) j["errors"].Push(Json(e));
  return j;
}

}  // namespace ccmd::load
