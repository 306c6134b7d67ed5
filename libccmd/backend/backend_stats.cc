// The back-end's statistics: counters, latency percentiles, stage backlogs, memory by part.

#include <algorithm>

#include "libccmd/backend/backend.h"
#include "libccmd/util/percentile.h"

namespace ccmd {
namespace {

// The samples taken at or after `since` (times in the same order as the samples).
std::vector<double> Since(const std::vector<double>& samples, const std::vector<double>& at,
                          double since) {
  const auto first = std::lower_bound(at.begin(), at.end(), since);
  return std::vector<double>(samples.begin() + (first - at.begin()), samples.end());
}

constexpr double kRecentSeconds = 60;

}  // namespace

BackendStats Backend::stats() {
  BackendStats s;
  std::vector<double> intake, during, recent, dense, dense_recent;
  const double recent_since = Now() - kRecentSeconds;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    s = stats_;
    intake = timings_.intake_ms;
    for (std::size_t i = 0; i < intake.size(); ++i) {
      if (timings_.intake_during_gba[i]) during.push_back(intake[i]);
    }
    recent = Since(timings_.intake_ms, timings_.intake_at_s, recent_since);
    dense = timings_.dense_ms;
    dense_recent = Since(timings_.dense_ms, timings_.dense_at_s, recent_since);
  }
  s.intake_ms_median = Percentile(intake, 0.5);
  s.intake_ms_p99 = Percentile(intake, 0.99);
  s.intake_ms_max = intake.empty() ? 0 : *std::max_element(intake.begin(), intake.end());
  s.intake_last_minute_ms_median = Percentile(recent, 0.5);
  s.intake_last_minute_ms_p99 = Percentile(recent, 0.99);
  s.dense_intake_ms_median = Percentile(dense, 0.5);
  s.dense_intake_ms_p99 = Percentile(dense, 0.99);
  s.dense_intake_last_minute_ms_median = Percentile(dense_recent, 0.5);
  s.dense_intake_last_minute_ms_p99 = Percentile(dense_recent, 0.99);
  s.intake_during_gba_count = during.size();
  s.intake_during_gba_ms_median = Percentile(during, 0.5);
  s.intake_during_gba_ms_max = during.empty() ? 0 : *std::max_element(during.begin(), during.end());
  s.ingest_backlog = ingest_stage_.backlog();
  s.loop_backlog = loop_stage_.backlog();
  s.dense_backlog = dense_stage_.backlog();
  s.agents = maps_.Agents().size();
  s.maps = maps_.Maps().size();
  for (MapId id : maps_.Maps()) {
    MapManager::Guard guard = maps_.CheckOut(id);
    if (!guard) continue;
    s.keyframes += guard->keyframes().size() + guard->num_culled();
    s.map_points += guard->num_points();
    s.segments_unplaced += guard->num_unplaced_segments();
  }
  return s;
}

SparseMemory Backend::SparseMemoryUsage() {
  SparseMemory total;
  for (MapId id : maps_.Maps()) {
    MapManager::Guard guard = maps_.CheckOut(id);
    if (guard) total.Add(MeasureSparseMemory(*guard));
  }
  // The place index belongs to the loop stage: it is read when that stage is idle.
  total.place_bytes = place_bytes_.load();
  return total;
}

std::vector<LoopEvent> Backend::loop_events() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return loop_events_;
}

BackendTimings Backend::timings() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return timings_;
}

namespace {

// The statistics file is rewritten every few seconds: it lists the most recent events only.
constexpr std::size_t kLoopEventsInJson = 1000;

Json LoopEventsJson(const std::vector<LoopEvent>& loop_events) {
  Json events = Json::MakeArray();
  const std::size_t first =
      loop_events.size() > kLoopEventsInJson ? loop_events.size() - kLoopEventsInJson : 0;
  for (std::size_t i = first; i < loop_events.size(); ++i) {
    const LoopEvent& e = loop_events[i];
    Json x;
    x["time_s"] = e.server_time;
    x["query_agent"] = e.query.agent.value();
    x["query_keyframe"] = e.query.keyframe.value();
    x["candidate_agent"] = e.candidate.agent.value();
    x["candidate_keyframe"] = e.candidate.keyframe.value();
    x["inliers"] = e.inliers;
    x["fusion"] = e.fusion;
    x["already_closed"] = e.already_closed;
    x["placed_segment"] = e.placed_segment;
    x["map"] = e.map.value();
    events.Push(x);
  }
  return events;
}

}  // namespace

void Backend::RecordArrival(const KeyframeArrival& arrival) {
  // Bounded: a server running for days must not grow with its keyframe count here.
  if (arrivals_.size() < kMaxArrivals) {
    arrivals_.push_back(arrival);
  } else {
    ++arrivals_not_recorded_;
  }
}

std::vector<KeyframeArrival> Backend::keyframe_arrivals() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return arrivals_;
}

Json Backend::StatsJson() {
  const BackendStats s = stats();
  Json j;
  j["agents"] = s.agents;
  j["maps"] = s.maps;
  j["keyframes"] = s.keyframes;
  j["map_points"] = s.map_points;
  j["keyframes_received"] = s.keyframes_received;
  j["pose_updates_received"] = s.pose_updates_received;
  j["pose_updates_of_culled"] = s.pose_updates_of_culled;
  j["loops"] = s.loops;
  j["loops_already_closed"] = s.loops_already_closed;
  j["loops_at_agent_stop"] = s.loops_at_agent_stop;
  j["segments_restarted"] = s.segments_restarted;
  j["segments_placed"] = s.segments_placed;
  j["segments_unplaced"] = s.segments_unplaced;
  j["fusions"] = s.fusions;
  j["global_ba_runs"] = s.global_ba_runs;
  j["global_ba_windowed"] = s.global_ba_windowed;
  j["global_ba_final"] = s.global_ba_final;
  j["global_ba_final_skipped"] = s.global_ba_final_skipped;
  j["global_ba_idle"] = s.global_ba_idle;
  j["culling_checked"] = s.culling_checked;
  j["keyframes_culled"] = s.keyframes_culled;
  j["culled_points"] = s.culled_points;
  j["global_ba_abandoned"] = s.global_ba_aborted;
  j["global_ba_seconds"] = s.global_ba_seconds;
  j["dense_keyframes"] = s.dense_keyframes;
  j["intake_ms_median"] = s.intake_ms_median;
  j["intake_ms_p99"] = s.intake_ms_p99;
  j["intake_ms_max"] = s.intake_ms_max;
  j["intake_last_minute_ms_median"] = s.intake_last_minute_ms_median;
  j["intake_last_minute_ms_p99"] = s.intake_last_minute_ms_p99;
  j["dense_intake_ms_median"] = s.dense_intake_ms_median;
  j["dense_intake_ms_p99"] = s.dense_intake_ms_p99;
  j["dense_intake_last_minute_ms_median"] = s.dense_intake_last_minute_ms_median;
  j["dense_intake_last_minute_ms_p99"] = s.dense_intake_last_minute_ms_p99;
  j["intake_during_gba_count"] = s.intake_during_gba_count;
  j["intake_during_gba_ms_median"] = s.intake_during_gba_ms_median;
  j["intake_during_gba_ms_max"] = s.intake_during_gba_ms_max;
  j["ingest_backlog"] = s.ingest_backlog;
  j["loop_backlog"] = s.loop_backlog;
  j["dense_backlog"] = s.dense_backlog;
  j["loop_events"] = LoopEventsJson(loop_events());
  return j;
}

Json Backend::MemoryJson() {
  Json j;
  j["sparse"] = SparseMemoryUsage().ToJson();
  if (dense_) {
    const DenseMapStats d = dense_->Stats();
    Json dense;
    dense["keyframes"] = d.keyframes;
    dense["compact_keyframes"] = d.compact_keyframes;
    dense["points"] = d.points;
    dense["compact_points"] = d.compact_points;
    dense["released_keyframes"] = d.released_keyframes;
    dense["released_points"] = d.released_points;
    dense["absent_updates"] = d.absent_updates;
    dense["held_bytes"] = d.held_bytes;
    dense["bytes"] = d.memory_bytes;
    dense["bytes_per_point"] = d.points ? static_cast<double>(d.memory_bytes) / d.points : 0.0;
    j["dense"] = dense;
  }
  return j;
}

}  // namespace ccmd
