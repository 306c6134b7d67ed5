#pragma once

// The server's brain. Messages of all agents go through four stages (util/stage.h: a bounded
// queue and one owned thread each, joined at shutdown; each stage knows when it is idle):
//   ingest  — keyframes and pose updates into the agents' maps (RGB-D decoded here);
//   loops   — the LoopCloser (loop_closer.h) for each new keyframe: place recognition,
//             verification and consistency, then loop closure inside a map or fusion of two
//             maps; the back-end passes what moved to the dense map and schedules a global BA;
//   global BA — on the whole map, in the background, abandoned when newer loop work arrives
//             (only the newest request waits);
//   dense   — the dense point store, fed with keyframes of the primary map (the first agent's
//             map and everything fused into it) and every pose change of those keyframes.
// The Backend only schedules: the work of each stage is in the functions it calls.

#include <atomic>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "libccmd/backend/loop_closer.h"
#include "libccmd/backend/map_manager.h"
#include "libccmd/backend/map_optimization.h"
#include "libccmd/backend/place_index.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/json.h"
#include "libccmd/util/stage.h"
#include "proto/messages.h"

namespace ccmd {

struct BackendOptions {
  LoopCloserOptions loops;
  bool global_ba = true;
  int global_ba_iterations = 10;
  DepthNoise depth_noise;
  bool dense = true;
  DenseMapOptions dense_options;
  PlaceIndexOptions place;
  std::size_t queue_capacity = 64;      // per stage

  Status Validate() const;
};

struct BackendStats {
  std::size_t agents = 0, maps = 0, keyframes = 0, map_points = 0;
  std::size_t keyframes_received = 0, pose_updates_received = 0;
  int loops = 0, fusions = 0;
  int global_ba_runs = 0, global_ba_aborted = 0;
  double global_ba_seconds = 0;
  std::size_t dense_keyframes = 0;
  // Time from submission to insertion in the map (the intake latency), over all keyframes and
  // over those that arrived while a global BA was running.
  double intake_ms_median = 0, intake_ms_p99 = 0, intake_ms_max = 0;
  double intake_during_gba_ms_median = 0, intake_during_gba_ms_max = 0;
  std::size_t intake_during_gba_count = 0;
};

// The samples behind the intake and global BA figures of BackendStats, for benchmarks that
// need other percentiles or compare intake with and without a global BA running.
struct BackendTimings {
  std::vector<double> intake_ms;          // per keyframe, in intake order
  std::vector<char> intake_during_gba;    // per intake_ms entry: a global BA was running
  std::vector<double> global_ba_seconds;  // per global BA run, abandoned ones included
  std::vector<char> global_ba_applied;    // per run: the result was written to the map
};

class Backend {
 public:
  static StatusOr<std::unique_ptr<Backend>> Create(const BackendOptions& options);
  ~Backend();
  Backend(const Backend&) = delete;
  Backend& operator=(const Backend&) = delete;

  // An agent's camera (from its handshake); needed before its first keyframe.
  Status RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera);
  // Queue work (blocks while the ingest queue is full: back-pressure towards the network).
  Status SubmitKeyframe(AgentId agent, KeyframeMessage message);
  Status SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message);

  // Returns when everything submitted so far has gone through every stage (and a global BA it
  // caused has finished).
  void WaitIdle();
  // Stops the stages (queued work is finished first). Idempotent.
  void Shutdown();

  // Keyframe trajectories (TUM): an agent's in the frame of the map it is in (the world frame
  // once it is fused into the primary map), and every keyframe of the primary map.
  Trajectory AgentTrajectory(AgentId agent);
  Trajectory FusedTrajectory();
  std::optional<MapId> PrimaryMap() const { return maps_.primary(); }
  std::vector<MapId> Maps() const { return maps_.Maps(); }
  std::vector<AgentId> Agents() const { return maps_.Agents(); }
  bool AgentInPrimaryMap(AgentId agent) const;

  DenseMap* dense() { return dense_.get(); }
  Status ExportDenseMap(const std::string& path);

  BackendStats stats();
  std::vector<LoopEvent> loop_events() const;
  BackendTimings timings() const;
  Json StatsJson();

 private:
  struct IngestItem {
    AgentId agent;
    // Exactly one is set. Held by pointer: queue moves stay cheap.
    std::unique_ptr<KeyframeMessage> keyframe;
    std::unique_ptr<PoseUpdateMessage> pose_update;
    double submitted = 0;
  };
  struct DenseTask {
    enum class Kind { kAdd, kUpdate, kLoopUpdate, kGlobalUpdate, kMergeMaps } kind = Kind::kAdd;
    DenseKeyframe keyframe;                 // kAdd
    std::vector<KeyframePose> poses;        // updates
    MapId from, to;                         // kMergeMaps
  };

  explicit Backend(const BackendOptions& options);
  // Stage handlers, each on its stage's thread.
  void Ingest(IngestItem item);
  void DetectLoops(const GlobalKeyframeId& id);
  void RunGlobalBa(AgentId agent);
  void UpdateDense(DenseTask task);

  // The dense-map work of an accepted loop (its map still checked out), then a global BA.
  void AfterLoop(LoopClosure closure);
  void RequestGlobalBa(AgentId agent);
  // Dense work for keyframes that entered the primary map, and pose changes of keyframes in it.
  void QueueDenseAdds(ServerMap* map, const std::vector<ServerKeyframe*>& keyframes);
  void QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind);
  PinholeCamera CameraOf(AgentId agent) const;
  double Now() const;

  const BackendOptions options_;
  MapManager maps_;
  std::unique_ptr<DenseMap> dense_;
  const double start_time_;
  LoopCloser loop_closer_;  // loop stage only

  mutable std::mutex cameras_mutex_;
  std::map<AgentId, PinholeCamera> cameras_;
  std::map<AgentId, std::string> names_;

  // A newer loop or fusion abandons a running global BA; shutdown abandons it too.
  std::atomic<bool> gba_abort_{false};
  std::atomic<bool> gba_running_{false};
  std::atomic<bool> stopping_{false};

  mutable std::mutex stats_mutex_;
  BackendStats stats_;
  BackendTimings timings_;
  std::vector<LoopEvent> loop_events_;

  // Declared last: stopped (joined) before anything their handlers use is destroyed.
  Stage<IngestItem> ingest_stage_;
  Stage<GlobalKeyframeId> loop_stage_;
  Stage<AgentId> gba_stage_;  // the newest request replaces one still waiting
  Stage<DenseTask> dense_stage_;
  bool shut_down_ = false;
};

}  // namespace ccmd
