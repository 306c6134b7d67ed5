#pragma once

// The mapping half of the agent's front-end, in its own thread: for each new keyframe it
// links the keyframe's points and covisibility, culls weak new points, fuses duplicates with
// neighbouring keyframes, runs a local bundle adjustment over a bounded window, culls redundant
// keyframes, drops the oldest keyframes beyond the map bound, decides whether the keyframe's
// RGB-D data is transmitted (Algorithm 1) and hands the keyframe and the pose updates to the
// sink.

#include <atomic>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <thread>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/tracking/cpu_budget.h"
#include "libccmd/tracking/keyframe_selector.h"
#include "libccmd/tracking/keyframe_sink.h"
#include "libccmd/tracking/map.h"
#include "libccmd/tracking/options.h"
#include "libccmd/tracking/tracker.h"

namespace ccmd {

struct MappingStats {
  int keyframes = 0;
  int local_ba_runs = 0;
  int local_ba_aborted = 0;          // stopped early by a newer keyframe
  int local_ba_reduced = 0;          // smaller, to stay within the CPU budget
  int local_ba_skipped_waiting = 0;  // skipped: a newer keyframe was already waiting
  int local_ba_skipped_budget = 0;   // skipped: far over the CPU budget
  int local_ba_iterations = 0;       // in all runs
  double budget_balance_ms = 0;      // CPU budget account now and at its lowest (0: no budget)
  double budget_lowest_ms = 0;
  double local_ba_ms_total = 0;
  double mapping_ms_total = 0;
  double local_ba_cpu_ms_total = 0;  // CPU time of the mapping thread
  double mapping_cpu_ms_total = 0;
  int culled_keyframes = 0;
  int evicted_keyframes = 0;
  int culled_points = 0;
  int fused_points = 0;
  int triangulated_points = 0;
  int pose_updates = 0;
  int depth_alignments = 0;         // accepted keyframe-to-keyframe depth alignments
  int depth_alignments_failed = 0;  // tried and rejected
  double depth_alignment_ms_total = 0;
  double depth_fit_sigmas = 0;  // MappingQueue::DepthFitSigmas when last updated
  int rgbd_transmitted = 0;
  int rgbd_decisions_not_recorded = 0;  // beyond LocalMapper::kMaxRecordedDecisions
};

class LocalMapper : public MappingQueue {
 public:
  LocalMapper(const PinholeCamera& camera, const TrackingOptions& options, LocalMap* map,
              const OrbExtractor* orb, KeyframeSink* sink);
  ~LocalMapper() override;
  LocalMapper(const LocalMapper&) = delete;
  LocalMapper& operator=(const LocalMapper&) = delete;

  // MappingQueue (called by the tracker with the map locked).
  bool Idle() const override;
  bool CanAccept() const override;
  double KeyframeRatioScale() const override { return sink_ ? sink_->KeyframeRatioScale() : 1.0; }
  double DepthFitSigmas() const override;
  void Insert(const KeyframePtr& keyframe) override;

  // The tracking thread's CPU time for one frame, for the CPU budget.
  void AddFrameCpu(double ms) { budget_.AddFrame(ms); }

  // Synchronous mode: processes every queued keyframe now (call without the map locked).
  void ProcessPending();
  // Processes what is queued and stops the thread. Idempotent.
  void Finish();

  MappingStats stats() const;
  // The RGB-D decisions of the keyframes sent, for --stats: the first kMaxRecordedDecisions
  // (a mission's memory must not grow without bound; the rest are counted in the stats).
  static constexpr std::size_t kMaxRecordedDecisions = 100000;
  std::vector<RgbdDecision> decisions() const;

 private:
  void Run();
  void Process(const KeyframePtr& keyframe);
  void CullRecentPoints(const Keyframe& keyframe);
  // New points from keypoints without depth (or whose partner has none), matched along the
  // epipolar lines of the best covisible keyframes and triangulated (ORB-SLAM's
  // CreateNewMapPoints).
  void TriangulateWithNeighbours(Keyframe* keyframe);
  void FuseWithNeighbours(Keyframe* keyframe);
  // A depth image as its camera took it, and that camera's pose in the colour image's frame.
  struct DepthAsTaken {
    cv::Mat depth_mm;
    Pose T_colour_depth;
  };
  // A keyframe whose depth was taken apart from its colour (Keyframe::T_colour_depth): the
  // depth moved to the colour image's time, before anything reads it. Returns the depth as
  // taken, for the alignment.
  std::optional<DepthAsTaken> MoveDepthToColourTime(Keyframe* keyframe);
  // Aligns the keyframe's depth with its best covisible neighbours' (depth_edges_). `taken`:
  // the depth as taken, whose model is moved rigidly to the colour image's frame instead of
  // being built from the moved (resampled) image.
  void AlignWithNeighbours(Keyframe* keyframe, const DepthAsTaken* taken);
  // Decides how much local BA the keyframe gets (waiting keyframes, CPU budget) and runs it.
  void ScheduleLocalBundleAdjustment(Keyframe* keyframe);
  void LocalBundleAdjustment(Keyframe* keyframe, bool reduced);
  void CullRedundantKeyframes(Keyframe* keyframe);
  void EvictOldKeyframes(Keyframe* keyframe);
  // Fills the keyframe's snapshot and the pose updates; false if the keyframe is gone.
  bool Emit(Keyframe* keyframe, KeyframeSnapshot* snapshot, std::vector<PoseUpdate>* updates);

  PinholeCamera camera_;
  TrackingOptions options_;
  LocalMap* map_;
  const OrbExtractor* orb_;
  KeyframeSink* sink_;
  RgbdSelector selector_;
  MappingBudget budget_;

  static constexpr std::size_t kQueueCapacity = 3;
  mutable std::mutex queue_mutex_;
  std::condition_variable queue_cv_;
  std::deque<KeyframePtr> queue_;
  bool stopping_ = false;
  bool busy_ = false;
  std::atomic<bool> abort_ba_{false};
  std::thread thread_;

  std::vector<MapPointPtr> recent_points_;
  // Dense depth alignments between keyframes still in the map (mapping thread only).
  struct DepthEdge {
    KeyframeId a, b;
    Pose T_b_a;
    Eigen::Matrix<double, 6, 6> sqrt_information;
  };
  std::vector<DepthEdge> depth_edges_;
  // DepthFitSigmas over the last kFitWindow accepted alignments (under stats_mutex_).
  static constexpr std::size_t kFitWindow = 64;
  std::deque<double> fit_sigmas_;
  mutable std::mutex stats_mutex_;
  MappingStats stats_;
  std::vector<RgbdDecision> decisions_;
};

}  // namespace ccmd
