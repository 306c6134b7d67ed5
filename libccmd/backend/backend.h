#pragma once

// The server's brain. Messages of all agents go through four stages (util/stage.h: a bounded
// queue and one owned thread each, joined at shutdown; each stage knows when it is idle):
//   ingest  — keyframes and pose updates into the agents' maps (RGB-D decoded here);
//   loops   — the LoopCloser (loop_closer.h) for each new keyframe: place recognition,
//             verification and consistency, then loop closure inside a map or fusion of two
//             maps; the back-end passes what moved to the dense map and schedules a global BA;
//             then the keyframe culling (keyframe_culling.h) for the agent's keyframe that has
//             just left its recent window;
//   global BA — on the whole map, in the background, abandoned when newer loop work arrives
//             (only the newest request waits);
//   dense   — the dense point store, fed with keyframes of the primary map (the first agent's
//             map and everything fused into it) and every pose change of those keyframes.
// The Backend only schedules: the work of each stage is in the functions it calls.

#include <atomic>
#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "libccmd/backend/keyframe_culling.h"
#include "libccmd/backend/loop_closer.h"
#include "libccmd/backend/map_manager.h"
#include "libccmd/backend/map_memory.h"
#include "libccmd/backend/map_observer.h"
#include "libccmd/backend/map_optimization.h"
#include "libccmd/backend/place_index.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/stage.h"
#include "proto/messages.h"

namespace ccmd {

struct BackendOptions {
  LoopCloserOptions loops;
  KeyframeCullingOptions culling;
  bool global_ba = true;
  int global_ba_iterations = 10;
  // A map of more keyframes than this gets a global BA over a window of at most this many
  // keyframes (and observations) around the loop that asked for it, up to half as many of the
  // keyframes that see its points most held fixed, so that its time and memory do not grow
  // with the map or with passes over a place; a newer loop no longer abandons it (it stays
  // valid), and it runs at most `global_ba_duty` of the time.
  int global_ba_max_keyframes = 100;
  std::size_t global_ba_max_observations = 30000;  // of the window's keyframes
  double global_ba_duty = 0.5;
  // At the end of a run (FinishGlobalBa), a map whose latest loop or fusion no global BA of
  // the whole map has followed (it had outgrown the window, or newer work abandoned the run)
  // gets one, when it holds at most this many observations (about 1 kB each while it
  // solves); 0: never.
  std::size_t final_global_ba_max_observations = 200000;
  // While the server runs, a map none of whose agents has sent a keyframe for this many
  // seconds gets the same whole-map run (OptimiseIdleMaps, within the same limit), so that
  // the map a paused or finished mission shows is the one the run will write; 0: never.
  double idle_global_ba_seconds = 10.0;
  // An agent that has sent no keyframe for this many seconds gets its waiting loop confirmed
  // from the other side as at the end of its session (ConfirmIdleAgentsLoops); 0: never.
  double idle_loop_seconds = 10.0;
  DepthNoise depth_noise;
  bool dense = true;
  DenseMapOptions dense_options;
  PlaceIndexOptions place;
  std::size_t queue_capacity = 64;  // per stage

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct BackendStats {
  std::size_t agents = 0, maps = 0, keyframes = 0, map_points = 0;
  std::size_t keyframes_received = 0, pose_updates_received = 0;
  // Pose-update entries for keyframes the map does not keep (culled: their poses follow their
  // leaders'), skipped.
  std::size_t pose_updates_of_culled = 0;
  int loops = 0, fusions = 0;
  int global_ba_runs = 0, global_ba_aborted = 0;
  double global_ba_seconds = 0;
  std::size_t dense_keyframes = 0;
  int loops_already_closed = 0;  // verified loops that found the map consistent (no correction)
  // Loops and fusions (of the counts above) confirmed when their agent stopped
  // (LoopCloser::AgentStopped).
  int loops_at_agent_stop = 0;
  int global_ba_windowed = 0;  // runs over a window of a larger map
  // FinishGlobalBa: whole-map runs at the end, and maps left as their windows had them
  // (above final_global_ba_max_observations).
  int global_ba_final = 0, global_ba_final_skipped = 0;
  int global_ba_idle = 0;  // OptimiseIdleMaps: whole-map runs applied while the server ran
  // Agents' restarted segments received, loops that placed segments, and the segments
  // unplaced now (left out of the dense map and the trajectories: ServerMap::Placed).
  int segments_restarted = 0, segments_placed = 0;
  std::size_t segments_unplaced = 0;
  // Keyframe culling: keyframes looked at, culled (their poses kept), points removed with them.
  std::size_t culling_checked = 0, keyframes_culled = 0, culled_points = 0;
  // Intake latency: from receipt (the transport's arrival time, else the submission) to the
  // keyframe being in its map, over the samples kept (BackendTimings), and over the last
  // minute; the same to the keyframe being in the dense map (RGB-D keyframes of the primary
  // map). Also over the keyframes that arrived while a global BA was running.
  double intake_ms_median = 0, intake_ms_p99 = 0, intake_ms_max = 0;
  double intake_last_minute_ms_median = 0, intake_last_minute_ms_p99 = 0;
  double dense_intake_ms_median = 0, dense_intake_ms_p99 = 0;
  double dense_intake_last_minute_ms_median = 0, dense_intake_last_minute_ms_p99 = 0;
  double intake_during_gba_ms_median = 0, intake_during_gba_ms_max = 0;
  std::size_t intake_during_gba_count = 0;
  // Work waiting in each stage now.
  std::size_t ingest_backlog = 0, loop_backlog = 0, dense_backlog = 0;
};

// The samples behind the intake and global BA figures of BackendStats, for benchmarks that
// need other percentiles or compare intake with and without a global BA running. The most
// recent kMaxSamples of each kind are kept (memory must not grow with the run's length).
struct BackendTimings {
  static constexpr std::size_t kMaxSamples = 1 << 17;
  std::vector<double> intake_ms;        // per keyframe, in intake order
  std::vector<double> intake_at_s;      // when it entered its map (back-end clock)
  std::vector<char> intake_during_gba;  // per intake_ms entry: a global BA was running
  std::vector<double> dense_ms;         // per RGB-D keyframe: receipt to in the dense map
  std::vector<double> dense_at_s;
  std::vector<double> global_ba_seconds;  // per global BA run, abandoned ones included
  std::vector<char> global_ba_applied;    // per run: the result was written to the map
};

// When a keyframe reached the back-end (once per delivery: a duplicate would show twice) and
// the dense map (wall clock, Unix seconds): an evaluation matches these with the agents'
// creation times for the map latency.
struct KeyframeArrival {
  enum class Stage { kReceived, kDense };
  GlobalKeyframeId id;
  Stage stage = Stage::kReceived;
  double wall_s = 0;
  bool after_fusion = false;  // kDense: it came in with its map's fusion into the primary map
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
  // `depth_noise`: the agent's sensor as its handshake announced it (else options' default).
  // `T_color_trajectory`: the camera whose poses the agent's trajectories give, in its colour
  // camera's frame (SessionCamera's trajectory camera); AgentTrajectory and FusedTrajectory
  // give that camera's poses.
  Status RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera,
                       const std::optional<DepthNoise>& depth_noise = std::nullopt,
                       const Pose& T_color_trajectory = Pose::Identity());
  // Queue work (blocks while the ingest queue is full: back-pressure towards the network).
  // `arrived_s`: MonotonicSeconds() when the message reached the server (0: now); the
  // observer gets it with the change the message causes.
  Status SubmitKeyframe(AgentId agent, KeyframeMessage message, double arrived_s = 0);
  Status SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message, double arrived_s = 0);
  // The agent's session ended (after its last message was submitted): a loop of its still
  // waiting for its next keyframes to agree is confirmed from the other map's side instead
  // (LoopCloser::AgentStopped), once everything it submitted has been through the loop stage.
  Status SubmitSessionEnded(AgentId agent);
  // Periodic (ServerRuntime::Tick): the same for each agent that has sent no keyframe for
  // BackendOptions::idle_loop_seconds (once per pause): a robot that stands still with its
  // agent running makes no next keyframe either.
  void ConfirmIdleAgentsLoops();

  // Returns when everything submitted so far has gone through every stage (and a global BA it
  // caused has finished).
  void WaitIdle();
  // For the end of a run, once nothing more is submitted: a global BA of the whole map for
  // each map whose latest loop or fusion was followed only by windowed or abandoned ones
  // (BackendOptions::final_global_ba_max_observations). Returns when they and the dense
  // updates they cause are done.
  void FinishGlobalBa();
  // Periodic (ServerRuntime::Tick): queues the whole-map global BA FinishGlobalBa would run for
  // one map whose agents have been idle for BackendOptions::idle_global_ba_seconds, when the
  // global BA stage has nothing else to do. Returns at once; the run follows on that stage
  // (a newer loop in its map abandons it, and a later call queues it again).
  void OptimiseIdleMaps();
  // Stops the stages (queued work is finished first). Idempotent.
  void Shutdown();

  // Keyframe trajectories (TUM): an agent's in the frame of the map it is in (the world frame
  // once it is fused into the primary map), and every keyframe of the primary map; poses of
  // each agent's trajectory camera (RegisterAgent).
  Trajectory AgentTrajectory(AgentId agent);
  Trajectory FusedTrajectory();
  // How many keyframes AgentTrajectory(agent) holds, without making it.
  std::size_t AgentKeyframeCount(AgentId agent);
  std::optional<MapId> PrimaryMap() const { return maps_.primary(); }
  std::vector<MapId> Maps() const { return maps_.Maps(); }
  std::vector<AgentId> Agents() const { return maps_.Agents(); }
  bool AgentInPrimaryMap(AgentId agent) const;
  std::optional<MapId> MapOf(AgentId agent) const { return maps_.MapOfAgent(agent); }

  DenseMap* dense() { return dense_.get(); }
  // Held by work whose transient memory is large: a global BA's solve (about 1 kB per
  // observation, 30 MB for a full window) and a dense-map snapshot or export that a caller
  // writes (the cloud and its voxel filter, about 50 bytes a point). Taking it keeps two such
  // peaks from adding up, so the server's peak memory follows its resident memory.
  std::unique_lock<std::mutex> LockLargeTransient(bool wait = true) {
    return wait ? std::unique_lock<std::mutex>(large_transient_mutex_)
                : std::unique_lock<std::mutex>(large_transient_mutex_, std::try_to_lock);
  }
  // The primary map's dense cloud as PLY, for the end of a run: it holds the dense map's lock
  // while it writes (DenseExportMode::kStreamed).
  Status ExportDenseMap(const std::string& path);

  BackendStats stats();
  // The most recent loop events (at least BackendTimings::kMaxSamples of them).
  std::vector<LoopEvent> loop_events() const;
  BackendTimings timings() const;
  // The first arrivals of the run (bounded; see RecordArrival).
  std::vector<KeyframeArrival> keyframe_arrivals() const;
  Json StatsJson();
  // Memory of the sparse maps by part (reads every map: for reports, not for every tick) and
  // of the dense map.
  SparseMemory SparseMemoryUsage();
  Json MemoryJson();

 private:
  struct IngestItem {
    AgentId agent;
    // At most one is set (neither: the agent's session ended). Held by pointer: queue moves
    // stay cheap.
    std::unique_ptr<KeyframeMessage> keyframe;
    std::unique_ptr<PoseUpdateMessage> pose_update;
    double arrived = 0;  // MonotonicSeconds() when the message reached the server
  };
  // The loop stage's work: a new keyframe, or an agent that stopped sending them (its
  // session ended or it is idle).
  struct LoopTask {
    GlobalKeyframeId keyframe;  // its agent's, when agent_stopped
    bool agent_stopped = false;
  };
  struct DenseTask {
    enum class Kind {
      kAdd,
      kUpdate,
      kLoopUpdate,
      kGlobalUpdate,
      kMergeMaps,
      kRemove
    } kind = Kind::kAdd;
    // kAdd: the keyframe's coded RGB-D, decoded by the dense stage; kRemove: a keyframe no
    // longer placed in its map (ServerMap::Placed), whose cloud leaves the dense map.
    GlobalKeyframeId keyframe;
    Pose T_world_cam = Pose::Identity();
    std::shared_ptr<const RgbdPayload> rgbd;
    PinholeCamera camera;  // full resolution
    double received = -1;  // back-end clock; < 0: unknown (a keyframe that joined by fusion)
    std::vector<KeyframePose> poses;  // updates
    MapId from, to;                   // kMergeMaps
  };
  // A global BA request: the map of `agent`, around the loop's keyframes.
  struct GbaRequest {
    // kLoop: the whole map, or a window around `around` once the map has outgrown one.
    // kIdle (OptimiseIdleMaps) and kFinal (FinishGlobalBa): the agent's whole map, never a
    // window, when it holds at most final_global_ba_max_observations.
    enum class Reason { kLoop, kIdle, kFinal };
    AgentId agent;
    std::vector<GlobalKeyframeId> around;
    bool fusion = false;
    Reason reason = Reason::kLoop;
  };

  explicit Backend(const BackendOptions& options);
  // Stage handlers, each on its stage's thread.
  void Ingest(IngestItem item);
  void IngestPoseUpdate(AgentId agent, const PoseUpdateMessage& update, double arrived);
  void IngestKeyframe(AgentId agent, KeyframeMessage message, double arrived);
  // After `restart` began a new segment: the keyframes it left unplaced (followers included)
  // are added to `unplaced` and leave the dense map.
  void RemoveUnplacedFromDense(ServerMap* map, const GlobalKeyframeId& restart,
                               std::vector<GlobalKeyframeId>* unplaced);
  void DetectLoops(const GlobalKeyframeId& id);
  void LoopsOfAStoppedAgent(AgentId agent);
  // Culls `id` if it is redundant (loop stage).
  void CullIfRedundant(const GlobalKeyframeId& id);
  void RunGlobalBa(GbaRequest request);
  // A run's problem, built with its map checked out; the map's requests it holds go to
  // `loops_in_problem`, and its map becomes the running one. nullopt: an idle or final run the
  // map is too large for.
  std::optional<GlobalBaProblem> BuildGlobalBaProblem(const GbaRequest& request, bool windowed,
                                                      MapId* map_id,
                                                      std::uint64_t* loops_in_problem);
  // Whether an idle or final run may take the whole of `map`
  // (final_global_ba_max_observations).
  bool WholeMapBaFits(const ServerMap& map, GbaRequest::Reason reason);
  void UpdateDense(DenseTask task);
  Status AddToDense(const DenseTask& task);

  // The dense-map work of an accepted loop (its map still checked out), then a global BA.
  void AfterLoop(LoopClosure closure);
  void RequestGlobalBa(GbaRequest request);
  // Waits (on the global BA stage) until a windowed run may start: `global_ba_duty`.
  void WaitForGbaTurn();
  // Dense work for keyframes that entered the primary map, and pose changes of keyframes in it.
  // `received`: the back-end clock when the keyframe arrived (< 0: not measured).
  void QueueDenseAdds(ServerMap* map, const std::vector<ServerKeyframe*>& keyframes,
                      double received = -1);
  void QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind);
  PinholeCamera CameraOf(AgentId agent) const;
  DepthNoise DepthNoiseOf(AgentId agent) const;
  Pose TrajectoryCameraOf(AgentId agent) const;  // as registered (identity: the colour camera)
  double Now() const;
  // Tells the observer (if any) that `moved` have new poses in `map`.
  void NotifyPoses(PoseSource source, MapId map, const std::vector<ServerKeyframe*>& moved,
                   double arrived_s);

  const BackendOptions options_;
  MapObserver* observer_ = nullptr;  // set before the stages start, never changed
  MapManager maps_;
  std::unique_ptr<DenseMap> dense_;
  const double start_time_;
  LoopCloser loop_closer_;  // loop stage only
  KeyframeCuller culler_;   // loop stage only
  std::atomic<std::size_t> place_bytes_{
      0};  // the place index's memory, as the loop stage last saw it

  mutable std::mutex cameras_mutex_;
  std::map<AgentId, PinholeCamera> cameras_;
  AgentDepthNoise depth_noise_;
  std::map<AgentId, std::string> names_;
  std::map<AgentId, Pose> trajectory_cameras_;  // T_color_trajectory (RegisterAgent)

  // A newer loop in its map or a fusion abandons a running global BA of a whole map, a fusion
  // a windowed one; shutdown abandons any.
  std::atomic<bool> gba_abort_{false};
  std::atomic<bool> gba_windowed_{false};
  std::atomic<bool> gba_running_{false};
  std::atomic<bool> stopping_{false};
  std::mutex gba_turn_mutex_;
  std::condition_variable gba_turn_cv_;  // woken by shutdown
  double gba_next_start_ = 0;            // back-end clock; global BA stage only
  // Per map: loops and fusions that asked for a global BA, and how many of them the latest
  // applied global BA of the whole map came after (FinishGlobalBa runs where they differ).
  std::mutex gba_counts_mutex_;
  std::map<MapId, std::uint64_t> gba_requested_, gba_whole_map_;
  // The requests an idle run was last queued after (not again for the same ones: only a loop
  // in its map, which counts as a new one, or a fusion abandons it), and when each agent's
  // latest keyframe reached the back-end (back-end clock).
  std::map<MapId, std::uint64_t> gba_idle_queued_;
  std::optional<MapId> gba_running_map_;  // of the global BA being solved
  std::map<AgentId, double> last_keyframe_at_;
  // Per agent: the last_keyframe_at_ value its idle loop check followed (once per pause).
  std::map<AgentId, double> idle_loops_checked_;
  double dense_trimmed_ = 0;  // back-end clock; dense stage only

  std::mutex large_transient_mutex_;  // see LockLargeTransient

  mutable std::mutex stats_mutex_;
  BackendStats stats_;
  BackendTimings timings_;
  std::vector<LoopEvent> loop_events_;
  std::vector<KeyframeArrival> arrivals_;  // the first kMaxArrivals
  std::uint64_t arrivals_not_recorded_ = 0;
  static constexpr std::size_t kMaxArrivals = 400000;
  void RecordArrival(const KeyframeArrival& arrival);  // stats_mutex_ held

  // Declared last: stopped (joined) before anything their handlers use is destroyed.
  Stage<IngestItem> ingest_stage_;
  Stage<LoopTask> loop_stage_;
  Stage<GbaRequest> gba_stage_;  // the newest request replaces one still waiting
  Stage<DenseTask> dense_stage_;
  bool shut_down_ = false;
};

}  // namespace ccmd
