#pragma once

// The server's brain. Messages of all agents go through four stages, each one owned thread
// joined at shutdown, linked by bounded queues:
//   ingest  — keyframes and pose updates into the agents' maps (RGB-D decoded here);
//   loops   — place recognition for each new keyframe, geometric verification, consistency
//             over consecutive keyframes, then loop closure (pose graph) inside a map or
//             fusion of two maps; both schedule a global BA;
//   global BA — on the whole map, in the background, abandoned when newer loop work arrives;
//   dense   — the dense point store, fed with keyframes of the primary map (the first agent's
//             map and everything fused into it) and every pose change of those keyframes.

#include <atomic>
#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/backend/loop_verification.h"
#include "libccmd/backend/map_manager.h"
#include "libccmd/backend/map_observer.h"
#include "libccmd/backend/map_optimization.h"
#include "libccmd/backend/place_index.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/bounded_queue.h"
#include "libccmd/util/json.h"
#include "proto/messages.h"

namespace ccmd {

struct BackendOptions {
  LoopVerificationOptions verification;
  int loop_candidates = 4;              // verified per query, best score first
  int loop_consistency = 2;             // consecutive confirming keyframes needed
  double consistency_translation = 0.05;  // metres between confirming map-to-map transforms
  double consistency_rotation_deg = 3.0;
  int exclude_recent_keyframes = 25;    // same-agent neighbours in id that never count as loops
  int loop_cooldown_keyframes = 10;     // after a loop, the agent's next keyframes seek no loop in their own map
  MapPoseGraphOptions pose_graph;
  bool global_ba = true;
  int global_ba_iterations = 10;
  DepthNoise depth_noise;
  bool dense = true;
  DenseMapOptions dense_options;
  PlaceIndexOptions place;
  std::size_t queue_capacity = 64;      // per stage

  Status Validate() const;
};

struct LoopEvent {
  double server_time = 0;  // seconds since the back-end started
  GlobalKeyframeId query, candidate;
  int inliers = 0;
  // What verification measured: the query's camera in the candidate's camera frame (the loop
  // edge), so that a benchmark can check the transform against ground truth.
  Pose T_candidate_query = Pose::Identity();
  bool fusion = false;     // two maps fused (else a loop inside a map)
  MapId map;               // the map after the event
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
  // `observer` (optional) is told about every change of the maps; it must outlive the back-end.
  static StatusOr<std::unique_ptr<Backend>> Create(const BackendOptions& options,
                                                   MapObserver* observer = nullptr);
  ~Backend();
  Backend(const Backend&) = delete;
  Backend& operator=(const Backend&) = delete;

  // An agent's camera (from its handshake); needed before its first keyframe.
  Status RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera);
  // Queue work (blocks while the ingest queue is full: back-pressure towards the network).
  // `arrived_s`: MonotonicSeconds() when the message reached the server (0: now); the
  // observer gets it with the change the message causes.
  Status SubmitKeyframe(AgentId agent, KeyframeMessage message, double arrived_s = 0);
  Status SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message, double arrived_s = 0);

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
  std::optional<MapId> MapOf(AgentId agent) const { return maps_.MapOfAgent(agent); }

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
    double arrived = 0;  // MonotonicSeconds()
  };
  struct DenseTask {
    enum class Kind { kAdd, kUpdate, kLoopUpdate, kGlobalUpdate, kMergeMaps } kind = Kind::kAdd;
    DenseKeyframe keyframe;                 // kAdd
    std::vector<KeyframePose> poses;        // updates
    MapId from, to;                         // kMergeMaps
  };

  explicit Backend(const BackendOptions& options);
  void IngestLoop();
  void LoopDetectionLoop();
  void GlobalBaLoop();
  void DenseLoop();

  void Ingest(IngestItem item);
  // `stored`: the keyframe is already in the place index (a late query after the vocabulary
  // was trained online), so only the query runs.
  void DetectLoop(const GlobalKeyframeId& id, bool stored);
  void RequestGlobalBa(AgentId agent);
  // Dense work for keyframes that entered the primary map, and pose changes of keyframes in it.
  void QueueDenseAdds(ServerMap* map, const std::vector<ServerKeyframe*>& keyframes);
  void QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind);
  void FinishedWork();
  double Now() const;
  // Tells the observer (if any) that `moved` have new poses in `map`.
  void NotifyPoses(PoseSource source, MapId map, const std::vector<ServerKeyframe*>& moved, double arrived_s);

  const BackendOptions options_;
  MapObserver* observer_ = nullptr;  // set before the stages start, never changed
  PlaceIndex place_;  // loop stage only
  MapManager maps_;
  std::unique_ptr<DenseMap> dense_;
  const double start_time_;

  mutable std::mutex cameras_mutex_;
  std::map<AgentId, PinholeCamera> cameras_;
  std::map<AgentId, std::string> names_;

  BoundedQueue<IngestItem> ingest_queue_;
  BoundedQueue<GlobalKeyframeId> loop_queue_;
  std::vector<GlobalKeyframeId> late_queries_;  // loop stage only
  BoundedQueue<DenseTask> dense_queue_;

  // Work accounting for WaitIdle: every queued item (and a pending global BA) counts once.
  std::mutex work_mutex_;
  std::condition_variable work_cv_;
  long outstanding_ = 0;

  // Global BA requests: the agent whose map should be optimised.
  std::mutex gba_mutex_;
  std::condition_variable gba_cv_;
  std::optional<AgentId> gba_request_;
  bool gba_stop_ = false;
  std::atomic<bool> gba_abort_{false};
  std::atomic<bool> gba_running_{false};

  // Loop detection state (loop thread only).
  struct PendingLoop {
    MapId candidate_map;
    Pose T_candidate_map_query_map;
    KeyframeId last_query;
    int count = 0;
  };
  std::map<AgentId, PendingLoop> pending_loops_;
  std::map<AgentId, KeyframeId> loop_cooldown_until_;

  mutable std::mutex stats_mutex_;
  BackendStats stats_;
  BackendTimings timings_;
  std::vector<LoopEvent> loop_events_;

  std::thread ingest_thread_, loop_thread_, gba_thread_, dense_thread_;
  bool shut_down_ = false;
};

}  // namespace ccmd
