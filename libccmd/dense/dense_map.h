#pragma once

// The server's global dense map: a tree-structured point store that follows every pose update
// (the paper's section V).
//
// Tree: global -> map -> agent -> segment -> keyframe cloud.
//  * map: a server-side map (MapId); an agent starts in MapId(agent) and moves on map fusion.
//  * agent: every keyframe cloud of one agent, in its map's frame.
//  * segment: a block of kSegmentKeyframes consecutive keyframe ids of one agent; finding a
//    keyframe (or its label's) is two small steps, and empty blocks cost nothing.
//  * keyframe cloud: the back-projected points in the keyframe's own camera frame, their
//    colours, the keyframe's current pose T_world_cam, the points in the map frame derived from
//    that pose, and which points the voxel filter keeps.
// Every point carries the label N of its keyframe (label.h). A pose update re-transforms that
// keyframe's points and nothing else.
//
// Memory follows the mapped space, not the run's length (compact_keyframes): once a keyframe
// has W successors it has left the filter window, and it keeps only what the map needs, in a
// CompactCloud (16-bit coordinates in its own camera frame and colours, 9 bytes a point): the
// points the window filter keeps, without those whose voxel an earlier compacted keyframe of
// the same map already holds. Which voxels are held is one bit per voxel per map. A pose update
// of a compacted keyframe only stores the pose (its points follow exactly when read); the bits
// it holds are moved by Maintain(). After loop, global BA and fusion updates the held voxels
// are rebuilt, oldest keyframe first, dropping points that now share a voxel with an older
// one: surfaces that drift had doubled and a correction brought together are stored once again.
// What is given up: a compacted keyframe's filter is final (a later relative move of it and a
// neighbour cannot bring back a point the filter or the held voxels dropped), so the map equals
// a from-scratch build with the final poses within the voxel size rather than exactly
// (docs/benchmarks/dense.md measures it after a large loop correction).
// A compacted keyframe left with (almost) nothing to store (every voxel it saw but a few at
// the edges is held by an earlier one: a place seen again) is released: its entry and those
// few points leave the store, so a camera circling a room for hours costs the store nothing
// per pass beyond the keyframes still in the window (release_below_points).
// Pose updates name keyframes the store may have released; those are skipped (and counted).
//
// Voxel filter over a sliding window of keyframe indices. Within an agent, a point of
// keyframe k is kept iff it is the first point of k in its voxel and none of the next W stored
// keyframes of the agent (W = window_keyframes, by id order) has a point in that voxel: the
// largest label wins, and only neighbours in the window compete. The rule is local, so:
//  * adding the agent's newest keyframe touches its W predecessors only;
//  * a pose change of keyframe k changes the filter of k and its W predecessors only, computed
//    from those and k's W successors (a "window re-filter");
// and the result never depends on the order of operations: after any updates the store holds
// exactly what a from-scratch build with the final poses holds. Duplicates between keyframes
// further apart than W (revisits, other agents) are removed by the export's global filter.
//
// Update paths:
//  * local BA, UpdateKeyframePose: re-transform one keyframe now (cost: its points; a compacted
//    keyframe only stores its pose); the window re-filter is deferred to Maintain(), which the
//    owner calls when idle and every export and every added keyframe call first, so frequent
//    small updates do not pay for filtering each time;
//  * pose graph after a loop, UpdateLoopPoses: the keyframes of the loop interval, then the
//    windows around them are re-filtered at once;
//  * global BA, UpdateGlobalPoses: only keyframes whose pose changed are touched, agent by agent,
//    then re-filtered;
//  * map fusion, TransformAgent / MergeMaps: one rigid transform for a whole agent's collection.
//
// Thread safety: one mutex guards the whole store; every public method takes it, so any
// thread may call anything. The writer (the server's dense-map stage) holds it for one
// operation; an export holds it while it runs pending re-filters and copies the selected
// points, then filters and writes after releasing it. Back-projection of a new keyframe
// also runs before the lock is taken. Nothing is called back under the lock and no other
// lock is taken inside it.

#include <array>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "libccmd/dense/backprojection.h"
#include "libccmd/dense/compact_cloud.h"
#include "libccmd/dense/voxel_grid.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/io/ply.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct DenseMapOptions {
  // Voxel edge (metres). 1 cm is about the pixel footprint at 2.5 m of a 320x240 image
  // (fx = 262.5): the filter removes the overlap between keyframes but little of the detail
  // one keyframe holds. On the synthetic room at rate 0.5 it gives a mean error of 3.8 mm;
  // 2 cm gives 5.5 mm and the paper's 5 cm 5.0 mm with only 60% of the surface covered
  // (docs/benchmarks/dense.md).
  double voxel_size_m = 0.01;
  // W: how many following keyframes of the same agent a keyframe's points compete with.
  // On the synthetic room at 320x240 (a keyframe every 10 frames), W = 4 keeps 28% of the
  // points, W = 8 about as many (27.6%), W = 1 37%; the cost of an add grows with W.
  int window_keyframes = 4;
  // Keyframes that have left the window keep only what the map needs (see above). Off: every
  // back-projected point is kept for the run, and the store equals a from-scratch build with
  // the final poses exactly (about 30 bytes a point).
  bool compact_keyframes = true;
  // A compacted keyframe that stores fewer points than this is released (with them): its entry
  // (about 0.4 kB) would cost more than its points, which on a place seen again are the few
  // voxels that depth noise reaches beyond what the map holds (a 320x240 keyframe back-projects
  // 20-75 thousand points; a new piece of surface is hundreds). 0: only empty ones.
  int release_below_points = 32;
  BackProjectionOptions projection;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
  std::string ToString() const;
};

struct KeyframePose {
  GlobalKeyframeId id;
  Pose T_world_cam;
};

// One RGB-D keyframe as the server receives it: decoded depth (CV_16UC1 millimetres, 0 =
// invalid) and colour (CV_8UC3 BGR) at the transmitted sampling rate, the camera of that
// resolution, and the keyframe's pose in its agent's current map.
struct DenseKeyframe {
  GlobalKeyframeId id;
  Pose T_world_cam = Pose::Identity();
  cv::Mat depth_mm;
  cv::Mat bgr;
  PinholeCamera camera;
};

// Which part of the tree to read.
struct DenseSelection {
  enum class Kind { kGlobal, kMap, kAgent };
  Kind kind = Kind::kGlobal;
  MapId map;
  AgentId agent;

  static DenseSelection Global() { return {}; }
  static DenseSelection Map(MapId m) { return {Kind::kMap, m, AgentId()}; }
  static DenseSelection Agent(AgentId a) { return {Kind::kAgent, MapId(), a}; }
};

enum class DenseFilter {
  kNone,    // every stored point
  kWindow,  // the points the sliding-window filter keeps (the store's map)
  kGlobal,  // those, then one point per voxel over the whole selection (largest label wins)
};

// How an export trades memory against the time it holds the map's lock (writers wait).
enum class DenseExportMode {
  // The points copied under the lock (about 30 ms for 5 million), filtered and written after
  // it: about 45 bytes per exported point meanwhile. For exports while agents are mapping.
  kCopy,
  // Filtered and written under the lock, holding only the voxel filter's bookkeeping (about 20
  // bytes per exported point), for about ten times as long. For the exports at shutdown.
  kStreamed,
};

struct DenseMapStats {
  std::size_t maps = 0;
  std::size_t agents = 0;
  std::size_t segments = 0;
  std::size_t keyframes = 0;
  std::size_t points = 0;              // stored points (all of a keyframe in the window)
  std::size_t kept_points = 0;         // kept by the sliding-window filter (all compacted ones)
  std::size_t compact_keyframes = 0;   // keyframes that have left the window
  std::size_t compact_points = 0;      // points they store
  std::size_t pending_keyframes = 0;   // pose updates awaiting their window re-filter
  std::size_t held_bytes = 0;          // the maps' held-voxel sets
  std::size_t released_keyframes = 0;  // compacted keyframes released (release_below_points)
  std::size_t released_points = 0;     // the points they took with them
  std::size_t absent_updates = 0;      // pose updates of keyframes not in the store (skipped)
  std::size_t memory_bytes = 0;        // everything the store allocates, scratch included
};

inline constexpr int kSegmentKeyframes = 64;

class DenseMap {
 public:
  static StatusOr<std::unique_ptr<DenseMap>> Create(const DenseMapOptions& options = {});

  DenseMap(const DenseMap&) = delete;
  DenseMap& operator=(const DenseMap&) = delete;
  ~DenseMap();

  const DenseMapOptions& options() const { return options_; }

  // Back-projects the keyframe (outside the lock) and adds it with the window filter.
  // Errors: bad images or camera (InvalidArgument), ids beyond the label (OutOfRange), a
  // non-rigid pose, or a keyframe already present (InvalidArgument).
  Status AddKeyframe(const DenseKeyframe& keyframe);
  // The same for a keyframe already back-projected (points in its camera frame).
  Status AddKeyframeCloud(const GlobalKeyframeId& id, const Pose& T_world_cam, CameraCloud cloud);
  // Removes a keyframe (culled by the back-end); its predecessors are re-filtered.
  Status RemoveKeyframe(const GlobalKeyframeId& id);

  // Places an agent in a map without moving its points (the back-end's map of that agent).
  Status SetAgentMap(AgentId agent, MapId map);

  // Pose updates: a keyframe the store does not hold (released, or never added) is skipped and
  // counted (DenseMapStats::absent_updates); an invalid pose is an error and changes nothing.
  // Local BA: one keyframe moved. See the header comment for the deferred window re-filter.
  Status UpdateKeyframePose(const GlobalKeyframeId& id, const Pose& T_world_cam);
  // Pose graph after a loop: every keyframe listed moved; their windows are re-filtered now.
  Status UpdateLoopPoses(const std::vector<KeyframePose>& poses);
  // Global BA: new poses for any number of keyframes; those equal to the stored pose (within
  // 1e-9) are skipped, the rest updated and re-filtered. Returns how many moved.
  StatusOr<std::size_t> UpdateGlobalPoses(const std::vector<KeyframePose>& poses);
  // Map fusion of one agent's collection: every pose becomes T_new_old * pose.
  Status TransformAgent(AgentId agent, const Pose& T_new_old);
  // Map fusion: every agent of `source` moves into `target` (created if absent), its poses
  // premultiplied by T_target_source; `source` disappears.
  Status MergeMaps(MapId source, MapId target, const Pose& T_target_source);

  // Runs the window re-filters that pose updates left pending. Returns keyframes re-filtered.
  std::size_t Maintain();

  // The keyframes released since the last call (see the header comment), for an owner that
  // tells others (the live view). At most kMaxReleasedQueued wait; older ones are dropped
  // from the queue (DenseMapStats::released_keyframes counts every release).
  std::vector<GlobalKeyframeId> TakeReleased();
  static constexpr std::size_t kMaxReleasedQueued = 1 << 16;

  // Points of a part of the tree in its map's frame, with colours and labels. Runs Maintain()
  // first. NotFound for an unknown map or agent.
  StatusOr<PointCloud> Extract(const DenseSelection& selection,
                               DenseFilter filter = DenseFilter::kGlobal);
  // Extract, written as binary PLY (x y z red green blue label) atomically. kStreamed visits
  // the points twice under the lock, once for each voxel's winner and once to write them,
  // instead of holding the extracted cloud; the file is the same.
  Status ExportPly(const std::string& path, const DenseSelection& selection,
                   DenseFilter filter = DenseFilter::kGlobal,
                   DenseExportMode mode = DenseExportMode::kCopy);
  // Every stored point of one keyframe in the map frame (unfiltered), with colours and labels.
  StatusOr<PointCloud> ExtractKeyframe(const GlobalKeyframeId& id) const;
  // The points of one keyframe in its own camera frame, with colours, for a viewer that places
  // them with the keyframe's pose (KeyframePoseOf): with kNone every stored point (what it was
  // added with while in the filter window, what it keeps once compacted), with kWindow (or
  // kGlobal) those the map uses.
  StatusOr<CameraCloud> KeyframeCloud(const GlobalKeyframeId& id,
                                      DenseFilter filter = DenseFilter::kNone) const;
  // The keyframe a label names, if present.
  StatusOr<GlobalKeyframeId> FindLabel(std::uint32_t label) const;

  StatusOr<Pose> KeyframePoseOf(const GlobalKeyframeId& id) const;
  std::vector<MapId> Maps() const;
  std::vector<AgentId> Agents() const;
  StatusOr<MapId> MapOf(AgentId agent) const;
  // The agent's keyframes in id order.
  std::vector<KeyframeId> Keyframes(AgentId agent) const;
  DenseMapStats Stats() const;

 private:
  struct Entry {
    GlobalKeyframeId id;
    std::uint32_t label = 0;
    Pose T_world_cam = Pose::Identity();
    // In the window: every back-projected point.
    CameraCloud cloud;                   // camera frame, never changes
    std::vector<Eigen::Vector3f> world;  // cloud.points under T_world_cam
    // Indices of the points the window filter keeps, ascending. A list rather than a flag
    // per point: a filter pass then visits only kept points, and with about a quarter of the
    // points kept it takes about the same memory.
    std::vector<std::uint32_t> kept;
    // Left the window (compact_keyframes): the points the map needs, and the pose with which
    // their voxels were marked in the map's held set.
    bool compact = false;
    CompactCloud stored;
    Pose T_held = Pose::Identity();
  };
  struct Segment {
    std::array<std::unique_ptr<Entry>, kSegmentKeyframes> slots;
    int count = 0;
  };
  struct AgentNode {
    std::map<std::uint32_t, Segment> segments;  // keyed by keyframe id / kSegmentKeyframes
    std::size_t keyframes = 0;
  };
  struct MapNode {
    std::map<AgentId, AgentNode> agents;
    VoxelSet held;              // voxels holding a point of a compacted keyframe
    bool rebuild_held = false;  // compacted keyframes moved relative to each other
  };

  explicit DenseMap(const DenseMapOptions& options);

  AgentNode* FindAgent(AgentId agent);
  const AgentNode* FindAgent(AgentId agent) const;
  AgentNode& AgentOrCreate(AgentId agent);
  static Entry* Find(const AgentNode& agent, std::uint32_t id);
  // The entry a pose update names: null for a keyframe the store does not hold (counted in
  // absent_updates_). EntriesOf: the same for each of `poses`.
  Entry* UpdatedEntry(const GlobalKeyframeId& id);
  std::vector<Entry*> EntriesOf(const std::vector<KeyframePose>& poses);
  static Entry* Next(const AgentNode& agent, std::uint32_t id);
  static Entry* Prev(const AgentNode& agent, std::uint32_t id);
  // The id W keyframes before `id` (or the first one), `id` itself if it has no predecessor.
  std::uint32_t WindowStart(const AgentNode& agent, std::uint32_t id) const;

  MapNode& MapNodeOf(AgentId agent);
  // The entry's points in the map frame: its cached ones, or a compacted keyframe's decoded
  // into `scratch`.
  const std::vector<Eigen::Vector3f>& WorldPoints(const Entry& entry,
                                                  std::vector<Eigen::Vector3f>* scratch) const;
  // A pose change: re-transforms a window keyframe, and marks it for Maintain().
  void SetPose(Entry* entry, const Pose& T_world_cam);
  void Transform(Entry* entry) const;
  // Recomputes the filter of every window keyframe with id in [first, last] from its own
  // points and its W successors'. Returns how many keyframes it recomputed.
  std::size_t RefilterRange(const AgentNode& agent, std::uint32_t first, std::uint32_t last);
  // Adds the newest keyframe of an agent: its own filter, then its points removed from the
  // kept points of its W predecessors.
  void FilterAppended(const AgentNode& agent, Entry* entry);
  // Compacts every window keyframe of the agent with id in [first, last] that has W successors.
  void CompactSettled(AgentId agent, std::uint32_t first, std::uint32_t last);
  // Returns whether it keeps too few points to stay (the caller releases it).
  bool Compact(MapNode* map, Entry* entry);
  bool TooFewToKeep(const Entry& entry) const;
  // Frees the voxels a compacted entry holds in its map's held set.
  void FreeHeld(const Entry& entry);
  // Removes an entry (lock held); its predecessors still in the window are re-filtered.
  void RemoveLocked(AgentNode* node, std::uint32_t id);
  // Removes compacted entries that store too few points, and the voxels those hold, and
  // queues their ids (TakeReleased).
  void Release(const std::vector<GlobalKeyframeId>& ids);
  // Moves a compacted keyframe's held voxels from T_held to its pose.
  void MoveHeld(MapNode* map, Entry* entry);
  // Marks every compacted keyframe of the map again, oldest first, dropping points whose voxel
  // an older one holds; releases those left with too few (release_below_points).
  void RebuildHeld(MapNode* map);
  std::size_t MaintainLocked();
  void MarkPending(const Entry& entry);
  Status InsertLocked(std::unique_ptr<Entry> entry);
  void AppendPoints(const Entry& entry, DenseFilter filter, PointCloud* cloud) const;
  // The agents of a selection; NotFound for an unknown map or agent.
  StatusOr<std::vector<const AgentNode*>> SelectedAgentsLocked(const DenseSelection& s) const;
  // How many points Extract would give before its voxel filter.
  std::size_t CountPointsLocked(const std::vector<const AgentNode*>& agents,
                                DenseFilter filter) const;
  // Calls visit(point, colour, label) for every point Extract would give before its voxel
  // filter, in the same order.
  template <typename Visit>
  void ForEachPointLocked(const std::vector<const AgentNode*>& agents, DenseFilter filter,
                          Visit&& visit) const;

  const DenseMapOptions options_;
  const VoxelGrid grid_;

  mutable std::mutex mutex_;
  std::map<MapId, MapNode> maps_;          // guarded by mutex_
  std::map<AgentId, MapId> agent_map_;     // guarded by mutex_
  std::set<GlobalKeyframeId> pending_;     // guarded by mutex_
  std::deque<GlobalKeyframeId> released_;  // guarded by mutex_; not yet taken
  std::size_t released_count_ = 0;         // guarded by mutex_
  std::size_t released_points_ = 0;        // guarded by mutex_
  std::size_t absent_updates_ = 0;         // guarded by mutex_
  VoxelSet occupied_;                      // guarded by mutex_; scratch of FilterAppended
  VoxelBricks<std::uint16_t> nearest_;     // guarded by mutex_; scratch of RefilterRange
  std::vector<VoxelIndex> voxels_;         // guarded by mutex_; scratch: voxels of one keyframe
  std::vector<std::uint32_t> indices_;     // guarded by mutex_; scratch: a kept list being built
  mutable std::vector<Eigen::Vector3f> decoded_;  // guarded by mutex_; scratch: compacted points
};

}  // namespace ccmd
