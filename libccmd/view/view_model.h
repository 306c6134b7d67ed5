#pragma once

// What the live map view shows, kept up to date by the back-end's observer calls: every
// agent, every keyframe of every map with its current pose and whether its cloud is in the
// dense store, the loops and fusions, and the latest per-agent statistics; plus the numbered
// stream of changes (events) that a browser follows after it has read the whole state once.
//
// The event log is a ring bounded in count and bytes: a browser that falls further behind than the
// ring is told to reload the state ("reset") instead of the server keeping every change forever.
//
// Events are JSON objects with a "type" (docs/view.md lists them):
//   agent  {a, name}                       an agent registered
//   kf     {a, k, m, T, t, primary}        a keyframe entered map m at pose T (3x4 row-major,
//                                          T_map_cam); t: its arrival, ms since the Unix epoch;
//                                          primary: m is the world map (its cloud follows soon)
//   cloud  {a, k, t}                       its points are in the dense store (t: then)
//   poses  {src, m, t, kfs: [[a, k, T...]]} keyframes moved (src: agent, loop, global_ba,
//                                          fusion); t: when the cause arrived or was computed
//   loop   {qa, qk, ca, ck, fusion, m, from, inliers}  a loop (or a fusion of the maps in
//                                          `from` into m)
//   placed {m, placed, kfs: [[a, k]]}      keyframes became unplaced (placed false: a restarted
//                                          segment nothing places yet; the dense map holds no
//                                          cloud of it) or were placed by a loop; a keyframe's
//                                          state says "placed": false while so
//   culled {m, kfs: [[a, k]]}              keyframes culled as redundant: no longer drawn on
//                                          their agent's path (nor their loops); one without a
//                                          cloud leaves the state, one with a cloud stays
//                                          ("culled": true) until the cloud is released
//   released {kfs: [[a, k]]}               the dense store released their clouds (every point
//                                          held by an earlier keyframe): nothing to draw; a
//                                          culled keyframe leaves the state
// The state keeps a keyframe while it is kept by the server or has a cloud in the dense
// store, and the loops between kept keyframes, so it follows the mapped space: a camera
// circling a mapped room adds keyframes that are culled and clouds that are released.
// Thread safety: every method may be called from any thread.

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include "libccmd/backend/backend.h"
#include "libccmd/backend/map_observer.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"

namespace ccmd {

struct ViewModelOptions {
  std::size_t max_events = 4096;            // events kept for browsers catching up
  std::size_t max_event_bytes = 32u << 20;  // and their text, at most

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct ViewKeyframe {
  GlobalKeyframeId id;
  MapId map;
  Pose T_map_cam = Pose::Identity();
  bool has_cloud = false;  // in the dense store
  int pose_updates = 0;    // times it moved after it arrived
  bool placed = true;      // false: an unplaced restarted segment (MapObserver::OnPlacement)
  bool culled = false;     // culled by the server, kept here for its cloud
};

// What WaitEvents hands a stream: the text of the events after `after` (SSE-framed, see
// view_server.cc) and the sequence number of the last one.
struct EventBatch {
  enum class Kind { kEvents, kTimeout, kReset, kClosed } kind = Kind::kTimeout;
  std::vector<std::pair<std::uint64_t, std::string>> events;  // (seq, JSON text)
  std::string stats;                                          // newer statistics (JSON), or ""
  std::uint64_t stats_version = 0;
};

class ViewModel : public MapObserver {
 public:
  explicit ViewModel(const ViewModelOptions& options = {});

  // MapObserver
  void OnAgent(AgentId agent, const std::string& name) override;
  void OnKeyframe(const GlobalKeyframeId& id, MapId map, const Pose& T_map_cam, double arrived_s,
                  bool primary) override;
  void OnPoses(PoseSource source, MapId map, const std::vector<KeyframePose>& poses,
               double arrived_s) override;
  void OnLoop(const LoopEvent& event) override;
  void OnDenseKeyframe(const GlobalKeyframeId& id, MapId map, const Pose& T_map_cam) override;
  void OnPlacement(MapId map, const std::vector<GlobalKeyframeId>& keyframes, bool placed) override;
  void OnDenseReleased(const std::vector<GlobalKeyframeId>& ids) override;
  void OnCulled(MapId map, const GlobalKeyframeId& id) override;

  // The latest statistics (a JSON object, e.g. the view server's summary); streams send it
  // when it changes.
  void PublishStats(const Json& stats);

  // The whole state as one JSON object with "seq": the last event it includes.
  Json StateJson() const;
  // Events after `after` (and the statistics if newer than `stats_version`); waits up to
  // `timeout_s` for something new. kReset when events after `after` have left the ring,
  // kClosed after Close().
  EventBatch WaitEvents(std::uint64_t after, std::uint64_t stats_version, double timeout_s) const;
  // Wakes every waiter; later waits return kClosed at once.
  void Close();

  std::vector<ViewKeyframe> Keyframes() const;
  std::map<AgentId, std::string> AgentNames() const;
  std::uint64_t last_seq() const;

  // A pose as the 12 numbers of its 3x4 matrix, row-major (what events carry).
  static Json PoseJson(const Pose& T);
  // Monotonic seconds as milliseconds since the Unix epoch (what browsers compare with).
  static double EpochMillis(double monotonic_s);

 private:
  struct Loop {
    GlobalKeyframeId query, candidate;
    bool fusion = false;
    MapId map;
  };

  void Append(Json event);                       // mutex held
  void DropLoopsOf(const GlobalKeyframeId& id);  // mutex held
  static Json IdJson(const GlobalKeyframeId& id);
  static Json KeyframeJson(const ViewKeyframe& kf);

  const ViewModelOptions options_;
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  std::map<AgentId, std::string> agents_;                     // guarded by mutex_
  std::map<GlobalKeyframeId, ViewKeyframe> keyframes_;        // guarded by mutex_
  std::vector<Loop> loops_;                                   // guarded by mutex_
  std::deque<std::pair<std::uint64_t, std::string>> events_;  // guarded by mutex_
  std::size_t event_bytes_ = 0;                               // guarded by mutex_
  std::uint64_t seq_ = 0;                                     // guarded by mutex_
  std::string stats_ = "{}";                                  // guarded by mutex_
  std::uint64_t stats_version_ = 0;                           // guarded by mutex_
  bool closed_ = false;                                       // guarded by mutex_
};

}  // namespace ccmd
