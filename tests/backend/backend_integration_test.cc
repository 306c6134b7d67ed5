// Two agents on the halves (10% overlap) of a synthetic sequence feed the back-end through the
// wire format: their maps must be fused through the overlap, the fused keyframe trajectory
// must match the ground truth, every accepted loop must measure the true relative pose, and
// the dense map must fill, and an observer must hear of every keyframe and every pose change.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>
#include <thread>
#include <utility>

#include "libccmd/backend/backend.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/tracking/keyframe_message.h"

namespace ccmd {
namespace {

class WireSink : public KeyframeSink {
 public:
  WireSink(AgentId agent, Backend* backend) : agent_(agent), backend_(backend) {}
  void OnKeyframe(KeyframeSnapshot snapshot) override {
    auto message = ToKeyframeMessage(snapshot, RgbdEncodeOptions());
    ASSERT_TRUE(message.ok());
    auto bytes = SerializeKeyframe(*message);
    ASSERT_TRUE(bytes.ok());
    auto parsed = ParseKeyframe(*bytes);
    ASSERT_TRUE(parsed.ok());
    timestamps_[snapshot.id] = snapshot.timestamp;
    ASSERT_TRUE(backend_->SubmitKeyframe(agent_, std::move(parsed).value()).ok());
  }
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override {
    auto bytes = SerializePoseUpdate(ToPoseUpdateMessage(updates));
    ASSERT_TRUE(bytes.ok());
    auto parsed = ParsePoseUpdate(*bytes);
    ASSERT_TRUE(parsed.ok());
    ASSERT_TRUE(backend_->SubmitPoseUpdate(agent_, std::move(parsed).value()).ok());
  }

  // Written by the front-end's mapping thread; read once the agent has finished.
  std::map<KeyframeId, double> timestamps_;

 private:
  AgentId agent_;
  Backend* backend_;
};

// Keeps what the back-end reported: the last pose and map of each keyframe.
class RecordingObserver : public MapObserver {
 public:
  void OnAgent(AgentId agent, const std::string& name) override {
    std::lock_guard<std::mutex> lock(mutex_);
    names[agent] = name;
  }
  void OnKeyframe(const GlobalKeyframeId& id, MapId map, const Pose& T_map_cam, double arrived_s,
                  bool /*primary*/) override {
    std::lock_guard<std::mutex> lock(mutex_);
    added[id]++;
    poses[id] = T_map_cam;
    maps[id] = map;
    EXPECT_GT(arrived_s, 0);
  }
  void OnPoses(PoseSource source, MapId map, const std::vector<KeyframePose>& moved,
               double) override {
    std::lock_guard<std::mutex> lock(mutex_);
    sources[source]++;
    for (const KeyframePose& p : moved) {
      EXPECT_EQ(added.count(p.id), 1u) << "a pose for a keyframe never added";
      poses[p.id] = p.T_world_cam;
      maps[p.id] = map;
    }
  }
  void OnLoop(const LoopEvent& event) override {
    std::lock_guard<std::mutex> lock(mutex_);
    fusions += event.fusion;
    // A fusion moves every keyframe of both maps to the new one.
    if (event.fusion) {
      const MapId a = maps[event.query], b = maps[event.candidate];
      for (auto& [id, map] : maps) {
        if (map == a || map == b) map = event.map;
      }
    }
  }
  void OnDenseKeyframe(const GlobalKeyframeId& id, MapId, const Pose&) override {
    std::lock_guard<std::mutex> lock(mutex_);
    dense.push_back(id);
  }
  void OnPlacement(MapId, const std::vector<GlobalKeyframeId>& keyframes, bool is_placed) override {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const GlobalKeyframeId& id : keyframes) placed[id] = is_placed;
  }
  void OnCulled(MapId, const GlobalKeyframeId& id) override {
    std::lock_guard<std::mutex> lock(mutex_);
    culled.push_back(id);
  }
  void OnDenseReleased(const std::vector<GlobalKeyframeId>& ids) override {
    std::lock_guard<std::mutex> lock(mutex_);
    released.insert(released.end(), ids.begin(), ids.end());
  }

  // Read after the back-end is idle.
  std::map<AgentId, std::string> names;
  std::map<GlobalKeyframeId, int> added;
  std::map<GlobalKeyframeId, Pose> poses;
  std::map<GlobalKeyframeId, MapId> maps;
  std::map<PoseSource, int> sources;
  std::vector<GlobalKeyframeId> dense;
  std::map<GlobalKeyframeId, bool> placed;  // the last placement reported
  std::vector<GlobalKeyframeId> culled, released;
  int fusions = 0;

 private:
  std::mutex mutex_;
};

// The ground-truth pose at a keyframe's timestamp (keyframes are frames of the path).
Pose TruePose(const Trajectory& ground_truth, double timestamp) {
  const auto it =
      std::min_element(ground_truth.begin(), ground_truth.end(), [&](const auto& a, const auto& b) {
        return std::abs(a.timestamp - timestamp) < std::abs(b.timestamp - timestamp);
      });
  EXPECT_LT(std::abs(it->timestamp - timestamp), 1e-6);
  return it->T_world_cam;
}

TEST(BackendIntegrationTest, TwoAgentsAreFusedIntoOneAccurateMap) {
  BackendOptions options;
  RecordingObserver observer;
  auto backend = Backend::Create(options, &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  SyntheticSequenceOptions synth;
  synth.frames = 200;
  const auto segments = SplitWithOverlap(synth.frames, 2);
  ASSERT_TRUE(segments.ok());
  Trajectory ground_truth = MakeLoopPath(synth.frames, synth.fps, synth.path);
  // Every sink exists before the first agent thread starts: growing the vector while an agent
  // reads it was a data race (ThreadSanitizer).
  std::vector<std::unique_ptr<WireSink>> sinks;
  for (int i = 0; i < 2; ++i) {
    const AgentId id(i + 1);
    sinks.push_back(std::make_unique<WireSink>(id, backend->get()));
    ASSERT_TRUE(
        (*backend)->RegisterAgent(id, "agent" + std::to_string(i + 1), SyntheticCamera()).ok());
  }
  std::vector<std::thread> agents;
  for (int i = 0; i < 2; ++i) {
    agents.emplace_back([&, i, sink = sinks[i].get()] {
      SyntheticSource source(synth, (*segments)[i]);
      auto frontend = Frontend::Create(source.camera(), TrackingOptions(), sink);
      ASSERT_TRUE(frontend.ok());
      RgbdFrame frame;
      while (source.Read(&frame).ok()) (*frontend)->ProcessFrame(frame);
      (*frontend)->Finish();
    });
  }
  for (auto& t : agents) t.join();
  (*backend)->WaitIdle();
  EXPECT_EQ((*backend)->Maps().size(), 1u);
  EXPECT_TRUE((*backend)->AgentInPrimaryMap(AgentId(1)));
  EXPECT_TRUE((*backend)->AgentInPrimaryMap(AgentId(2)));
  const BackendStats stats = (*backend)->stats();
  EXPECT_GE(stats.fusions, 1);
  const Trajectory fused = (*backend)->FusedTrajectory();
  auto ate = ComputeAte(ground_truth, fused);
  ASSERT_TRUE(ate.ok());
  EXPECT_GT(ate->matched, 20u);
  EXPECT_LT(ate->error.rmse, 0.01);
  // Each accepted loop reports the relative pose verification measured; on exact synthetic
  // data it is the true one to millimetres (a false loop would be off by decimetres).
  const std::vector<LoopEvent> events = (*backend)->loop_events();
  ASSERT_EQ(static_cast<int>(events.size()), stats.loops + stats.fusions);
  for (const LoopEvent& e : events) {
    const Pose T_world_query =
        TruePose(ground_truth, sinks[e.query.agent.value() - 1]->timestamps_.at(e.query.keyframe));
    const Pose T_world_candidate = TruePose(
        ground_truth, sinks[e.candidate.agent.value() - 1]->timestamps_.at(e.candidate.keyframe));
    const Pose truth = T_world_candidate.inverse() * T_world_query;
    EXPECT_LT(TranslationDistance(truth, e.T_candidate_query), 0.02);
    EXPECT_LT(RotationDistance(truth, e.T_candidate_query), 1.0 * M_PI / 180);
  }
  // The timing samples agree with the summary: one intake sample per keyframe, one duration per
  // global BA run (the fusion scheduled at least one).
  const BackendTimings timings = (*backend)->timings();
  EXPECT_EQ(timings.intake_ms.size(), stats.keyframes_received);
  ASSERT_EQ(timings.intake_during_gba.size(), timings.intake_ms.size());
  EXPECT_EQ(static_cast<std::size_t>(
                std::count(timings.intake_during_gba.begin(), timings.intake_during_gba.end(), 1)),
            stats.intake_during_gba_count);
  EXPECT_GE(stats.global_ba_runs, 1);
  EXPECT_EQ(static_cast<int>(timings.global_ba_seconds.size()), stats.global_ba_runs);
  ASSERT_EQ(timings.global_ba_applied.size(), timings.global_ba_seconds.size());
  EXPECT_EQ(static_cast<int>(
                std::count(timings.global_ba_applied.begin(), timings.global_ba_applied.end(), 1)),
            stats.global_ba_runs - stats.global_ba_aborted);
  for (double seconds : timings.global_ba_seconds) EXPECT_GT(seconds, 0.0);
  // The dense map holds keyframes of both agents.
  auto cloud = (*backend)->dense()->Extract(DenseSelection::Global());
  ASSERT_TRUE(cloud.ok());
  EXPECT_GT(cloud->size(), 10000u);
  EXPECT_EQ((*backend)->dense()->Agents().size(), 2u);
  // Arrival times: each keyframe reached the back-end once; every keyframe in the dense map
  // entered it once, not before it arrived; agent 2's came in with the fusion.
  std::map<GlobalKeyframeId, double> received;
  int dense = 0, fused_in = 0;
  for (const KeyframeArrival& a : (*backend)->keyframe_arrivals()) {
    if (a.stage == KeyframeArrival::Stage::kReceived) {
      EXPECT_TRUE(received.emplace(a.id, a.wall_s).second) << "keyframe received twice";
      continue;
    }
    ++dense;
    fused_in += a.after_fusion;
    ASSERT_TRUE(received.count(a.id));
    EXPECT_GE(a.wall_s, received[a.id]);
  }
  EXPECT_EQ(received.size(), stats.keyframes_received);
  EXPECT_EQ(static_cast<std::size_t>(dense), (*backend)->stats().dense_keyframes);
  EXPECT_GT(fused_in, 0);

  // The observer heard of each keyframe once, and the last pose it was told is the pose the
  // back-end holds (a missed local BA, pose graph, fusion or global BA update would differ).
  EXPECT_EQ(observer.names.size(), 2u);
  EXPECT_EQ(observer.added.size(), stats.keyframes);
  for (const auto& [id, count] : observer.added) EXPECT_EQ(count, 1);
  // The agents' segments overlap, so both may make a keyframe of the same frame: a timestamp
  // can hold two keyframes, and the observed pose must be one of them.
  std::multimap<double, Pose> held;
  for (const StampedPose& p : fused) held.emplace(p.timestamp, p.T_world_cam);
  for (const auto& [id, pose] : observer.poses) {
    const double t = sinks[id.agent.value() - 1]->timestamps_.at(id.keyframe);
    const auto [first, last] = held.equal_range(t);
    ASSERT_NE(first, last);
    double best = 1e9;
    for (auto it = first; it != last; ++it) {
      best = std::min(best,
                      TranslationDistance(it->second, pose) + RotationDistance(it->second, pose));
    }
    EXPECT_LT(best, 1e-9);
    EXPECT_EQ(observer.maps.at(id), *(*backend)->PrimaryMap());
  }
  EXPECT_EQ(observer.fusions, stats.fusions);
  EXPECT_GT(observer.sources[PoseSource::kAgent], 0);
  EXPECT_GT(observer.sources[PoseSource::kFusion], 0);
  // An applied global BA that moved nothing tells nothing: at most one report per applied run.
  EXPECT_LE(observer.sources[PoseSource::kGlobalBa],
            stats.global_ba_runs - stats.global_ba_aborted);
  EXPECT_EQ(observer.dense.size(), stats.dense_keyframes);
  for (const GlobalKeyframeId& id : observer.dense)
    EXPECT_TRUE((*backend)->dense()->KeyframeCloud(id).ok());
  (*backend)->Shutdown();
}

// Feeds the parts of a synthetic sequence to a front-end in order and finishes it: where one
// part ends and the next starts elsewhere, the camera jumps and tracking is lost.
void TrackParts(Frontend* frontend, const SyntheticSequenceOptions& synth,
                const std::vector<FrameRange>& parts) {
  for (const FrameRange& part : parts) {
    SyntheticSource source(synth, part);
    RgbdFrame frame;
    while (source.Read(&frame).ok()) frontend->ProcessFrame(frame);
  }
  frontend->Finish();
}

// The synthetic room at 320x240 with a 240-frame lap (8 s).
SyntheticSequenceOptions QuickLaps(int frames) {
  SyntheticSequenceOptions synth;
  synth.frames = frames;
  synth.width = 320;
  synth.height = 240;
  synth.path.loop_period_s = 8;
  return synth;
}

// The server's trajectory is within a centimetre of the sequence's ground truth.
void ExpectOnThePath(const SyntheticSequenceOptions& synth, const Trajectory& trajectory) {
  auto ate =
      ComputeAte(SyntheticSource(synth, FrameRange{0, synth.frames - 1}).GroundTruth(), trajectory);
  ASSERT_TRUE(ate.ok()) << ate.status().ToString();
  EXPECT_LT(ate->error.rmse, 0.01);
}

// Agent 1 tracks `synth` at 320x240 into `backend` through `sink` (made for agent 1), with
// local mapping in the tracking thread and a local map of 20 keyframes; returns when the
// back-end is idle.
void TrackOneAgentAtQuarterSize(Backend* backend, WireSink* sink,
                                const SyntheticSequenceOptions& synth) {
  const PinholeCamera camera = SyntheticCamera(320, 240);
  ASSERT_TRUE(backend->RegisterAgent(AgentId(1), "agent1", camera).ok());
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  tracking.max_keyframes = 20;
  auto frontend = Frontend::Create(camera, tracking, sink);
  ASSERT_TRUE(frontend.ok());
  TrackParts(frontend->get(), synth, {{0, synth.frames - 1}});
  backend->WaitIdle();
}

// Global BA windows of 10 keyframes (and 1000 observations), which the map of
// TrackOneAgentAtQuarterSize's laps outgrows.
// Every verified loop is corrected (and asks for a global BA), however little the lap
// drifted: the front-end's drift over a lap is a few millimetres, about the threshold under
// which a loop only counts as already closed.
BackendOptions SmallGlobalBaWindows() {
  BackendOptions options;
  options.global_ba_max_keyframes = 10;
  options.global_ba_max_observations = 1000;
  options.loops.min_correction_m = 0;
  options.loops.min_correction_deg = 0;
  return options;
}

// The keyframes of `before` whose position differs in `now`.
int MovedSince(const std::map<GlobalKeyframeId, Pose>& before,
               const std::map<GlobalKeyframeId, Pose>& now) {
  int moved = 0;
  for (const auto& [id, pose] : now) moved += TranslationDistance(pose, before.at(id)) > 1e-7;
  return moved;
}

// An agent tracks ten frames (one keyframe), then its frames resume elsewhere after a gap in
// time: it restarts in a new segment that nothing measures against that one keyframe. The map
// held nothing else, so the new segment is the map: the keyframe before it leaves the dense
// map and the trajectory, and every keyframe after it is there.
TEST(BackendIntegrationTest, ARestartAfterAYoungStartKeepsTheStartApart) {
  RecordingObserver observer;
  auto backend = Backend::Create(BackendOptions(), &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const AgentId agent(1);
  ASSERT_TRUE((*backend)->RegisterAgent(agent, "agent1", SyntheticCamera()).ok());
  WireSink sink(agent, backend->get());
  SyntheticSequenceOptions synth;
  synth.frames = 600;
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  auto frontend = Frontend::Create(SyntheticCamera(), tracking, &sink);
  ASSERT_TRUE(frontend.ok());
  TrackParts(frontend->get(), synth, {{0, 9}, {300, 359}});
  ASSERT_EQ((*frontend)->stats().restarts, 1);
  (*backend)->WaitIdle();
  EXPECT_EQ((*backend)->stats().segments_restarted, 1);
  EXPECT_EQ((*backend)->stats().segments_unplaced, 1u);  // the keyframes before the restart
  const double restart_time =
      SyntheticSource(synth, FrameRange{300, 300}).GroundTruth()[0].timestamp;
  std::size_t before = 0, after = 0, clouds_after = 0;
  for (const auto& [id, timestamp] : sink.timestamps_) {
    const bool cloud = (*backend)->dense()->KeyframeCloud({agent, id}).ok();
    if (timestamp < restart_time) {
      ++before;
      EXPECT_FALSE(cloud) << id.value();  // the first keyframe always carries RGB-D
      const GlobalKeyframeId global{agent, id};
      EXPECT_EQ(observer.placed.count(global), 1u) << "the observer was not told";
      EXPECT_FALSE(observer.placed[global]);
    } else {
      ++after;
      clouds_after += cloud;
    }
  }
  EXPECT_GE(before, 1u);
  EXPECT_GE(after, 5u);
  EXPECT_GE(clouds_after, 2u);
  const Trajectory fused = (*backend)->FusedTrajectory();
  ASSERT_EQ(fused.size(), after);
  EXPECT_GE(fused.front().timestamp, restart_time);
}

// An agent's features fail for two thirds of a second (its colour blank) and come back in a
// view its map does not hold (the colour inverted from then on: every descriptor differs). It
// places those frames by their depth and, at the first textured one, starts a new segment at
// the pose the depth gave, marked a reset. The server places that segment as the one before:
// nothing waits unplaced (a restart without the mark would wait for a loop, and the trajectory
// would keep only the 12 keyframes before it), and every keyframe is in the trajectory, on the
// path.
TEST(BackendIntegrationTest, ARestartAtAFramePlacedByDepthIsPlacedAsTheSegmentBefore) {
  RecordingObserver observer;
  auto backend = Backend::Create(BackendOptions(), &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const AgentId agent(1);
  ASSERT_TRUE((*backend)->RegisterAgent(agent, "agent1", SyntheticCamera()).ok());
  WireSink sink(agent, backend->get());
  SyntheticSequenceOptions synth;
  synth.frames = 80;
  synth.seed = 1;
  synth.noise = false;
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  tracking.depth_noise.sigma_2 = 0;  // a renderer's depth
  tracking.relocalisation_seconds = 0.5;
  // A keyframe at nearly every frame: the segment is past its young start when the colour goes.
  tracking.keyframe_tracked_ratio = 0.99;
  auto frontend = Frontend::Create(SyntheticCamera(), tracking, &sink);
  ASSERT_TRUE(frontend.ok());
  constexpr int kBlankFrom = 12, kInvertedFrom = 32;
  SyntheticSource source(synth, FrameRange{0, synth.frames - 1});
  RgbdFrame frame;
  for (int i = 0; source.Read(&frame).ok(); ++i) {
    if (i >= kBlankFrom && i < kInvertedFrom) frame.bgr.setTo(cv::Scalar(128, 128, 128));
    if (i >= kInvertedFrom) cv::bitwise_not(frame.bgr, frame.bgr);
    (*frontend)->ProcessFrame(frame);
  }
  (*frontend)->Finish();
  ASSERT_EQ((*frontend)->stats().restarts, 1);
  EXPECT_EQ((*frontend)->stats().lost_frames, 0);
  (*backend)->WaitIdle();
  EXPECT_EQ((*backend)->stats().segments_restarted, 1);
  EXPECT_EQ((*backend)->stats().segments_unplaced, 0u);
  const Trajectory fused = (*backend)->FusedTrajectory();
  EXPECT_EQ(fused.size(), sink.timestamps_.size());
  ExpectOnThePath(synth, fused);
}

// Agent 2 maps a part of the room agent 1 never saw, loses tracking, and restarts where agent
// 1 has been. Its new segment has no place in its own map (nothing measured the gap), but it
// does in agent 1's: the fusion through it places it there, and agent 2's first segment,
// which only the agent's guess relates to the second, waits unplaced for a loop.
TEST(BackendIntegrationTest, ARestartedSegmentFusesWithAnotherAgentsMap) {
  RecordingObserver observer;
  auto backend = Backend::Create(BackendOptions(), &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const SyntheticSequenceOptions synth = QuickLaps(320);  // the camera looks outwards
  const PinholeCamera camera = SyntheticCamera(320, 240);
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  std::vector<std::unique_ptr<WireSink>> sinks;
  for (int i = 0; i < 2; ++i) {
    const AgentId id(i + 1);
    sinks.push_back(std::make_unique<WireSink>(id, backend->get()));
    ASSERT_TRUE((*backend)->RegisterAgent(id, "agent" + std::to_string(i + 1), camera).ok());
  }
  // Agent 1 (the primary map): the first quarter lap. Agent 2: the third quarter, then the
  // first again.
  const std::vector<std::vector<FrameRange>> parts = {{{0, 59}}, {{120, 179}, {240, 314}}};
  for (int i = 0; i < 2; ++i) {
    auto frontend = Frontend::Create(camera, tracking, sinks[i].get());
    ASSERT_TRUE(frontend.ok());
    TrackParts(frontend->get(), synth, parts[i]);
    ASSERT_EQ((*frontend)->stats().restarts, i);
    (*backend)->WaitIdle();
  }
  const BackendStats stats = (*backend)->stats();
  EXPECT_EQ((*backend)->Maps().size(), 1u);
  EXPECT_GE(stats.fusions, 1);
  EXPECT_EQ(stats.segments_placed, 1);
  EXPECT_EQ(stats.segments_unplaced, 1u);  // agent 2's first segment

  const double restart_time =
      SyntheticSource(synth, FrameRange{240, 240}).GroundTruth()[0].timestamp;
  const Trajectory fused = (*backend)->FusedTrajectory();
  std::size_t second_segment = 0;
  for (const auto& [id, timestamp] : sinks[1]->timestamps_) {
    const GlobalKeyframeId global{AgentId(2), id};
    const bool in_trajectory = std::any_of(
        fused.begin(), fused.end(), [&](const StampedPose& p) { return p.timestamp == timestamp; });
    const bool cloud = (*backend)->dense()->KeyframeCloud(global).ok();
    if (timestamp < restart_time) {
      EXPECT_FALSE(in_trajectory) << id.value();
      EXPECT_FALSE(cloud) << id.value();
      ASSERT_EQ(observer.placed.count(global), 1u) << "the observer was not told";
      EXPECT_FALSE(observer.placed[global]) << id.value();
    } else {
      second_segment += in_trajectory;
    }
  }
  EXPECT_GE(second_segment, 3u);
  ExpectOnThePath(synth, fused);
}

// Agent 2's session covers only the last frames of agent 1's: one keyframe, whose loop with
// agent 1's map is verified but can get no second keyframe to agree. The maps stay apart
// while the session lasts, and fuse when it ends, or (`idle`) when the agent, still
// connected, has sent nothing for idle_loop_seconds.
// With `idle`, the session does not end: the agent stands still, and its pause does the same.
void FuseAnAgentThatStopsWithALoopWaiting(bool idle) {
  RecordingObserver observer;
  BackendOptions options;
  // Any pause counts as idle here (a keyframe's loop detection alone takes longer than 1 us):
  // the check does not depend on how fast this machine is.
  options.idle_loop_seconds = idle ? 1e-6 : 0;
  auto backend = Backend::Create(options, &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const SyntheticSequenceOptions synth = QuickLaps(120);  // enough keyframes for a vocabulary
  const PinholeCamera camera = SyntheticCamera(320, 240);
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  std::vector<std::unique_ptr<WireSink>> sinks;
  const std::vector<FrameRange> parts = {{0, 119}, {114, 117}};
  for (int i = 0; i < 2; ++i) {
    const AgentId id(i + 1);
    sinks.push_back(std::make_unique<WireSink>(id, backend->get()));
    ASSERT_TRUE((*backend)->RegisterAgent(id, "agent" + std::to_string(i + 1), camera).ok());
    auto frontend = Frontend::Create(camera, tracking, sinks[i].get());
    ASSERT_TRUE(frontend.ok());
    TrackParts(frontend->get(), synth, {parts[i]});
    (*backend)->WaitIdle();
  }
  ASSERT_EQ(sinks[1]->timestamps_.size(), 1u);
  EXPECT_EQ((*backend)->Maps().size(), 2u);
  EXPECT_EQ((*backend)->stats().fusions, 0);
  EXPECT_EQ((*backend)->stats().loops_at_agent_stop, 0);

  if (idle) {
    (*backend)->ConfirmIdleAgentsLoops();
  } else {
    (*backend)->ConfirmIdleAgentsLoops();  // disabled: nothing happens
    (*backend)->WaitIdle();
    EXPECT_EQ((*backend)->Maps().size(), 2u);
    ASSERT_TRUE((*backend)->SubmitSessionEnded(AgentId(2)).ok());
  }
  (*backend)->WaitIdle();
  EXPECT_EQ((*backend)->Maps().size(), 1u);
  EXPECT_EQ((*backend)->stats().fusions, 1);
  EXPECT_EQ((*backend)->stats().loops_at_agent_stop, 1);
  EXPECT_TRUE((*backend)->AgentInPrimaryMap(AgentId(2)));
  ExpectOnThePath(synth, (*backend)->FusedTrajectory());
}

TEST(BackendIntegrationTest, AnAgentWhoseSessionEndsWithALoopWaitingIsFused) {
  FuseAnAgentThatStopsWithALoopWaiting(false);
}

TEST(BackendIntegrationTest, AnAgentIdleWithALoopWaitingIsFused) {
  FuseAnAgentThatStopsWithALoopWaiting(true);
}

// The same start, but the camera comes round to it again: the loop that places the keyframe
// kept apart brings its cloud back to the dense map (its coded images were kept for that).
TEST(BackendIntegrationTest, AKeyframeKeptApartReturnsToTheDenseMapWhenALoopPlacesIt) {
  RecordingObserver observer;
  auto backend = Backend::Create(BackendOptions(), &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const AgentId agent(1);
  const SyntheticSequenceOptions synth = QuickLaps(330);  // frames 240-329 see 0-89 again
  const PinholeCamera camera = SyntheticCamera(320, 240);
  ASSERT_TRUE((*backend)->RegisterAgent(agent, "agent1", camera).ok());
  WireSink sink(agent, backend->get());
  TrackingOptions tracking;
  tracking.synchronous_mapping = true;
  auto frontend = Frontend::Create(camera, tracking, &sink);
  ASSERT_TRUE(frontend.ok());
  TrackParts(frontend->get(), synth, {{0, 9}, {120, 329}});
  ASSERT_EQ((*frontend)->stats().restarts, 1);
  (*backend)->WaitIdle();
  const BackendStats stats = (*backend)->stats();
  EXPECT_EQ(stats.segments_restarted, 1);
  EXPECT_EQ(stats.segments_placed, 1);
  EXPECT_EQ(stats.segments_unplaced, 0u);
  const GlobalKeyframeId first{agent, sink.timestamps_.begin()->first};
  ASSERT_EQ(observer.placed.count(first), 1u);
  EXPECT_TRUE(observer.placed[first]);
  EXPECT_TRUE((*backend)->dense()->KeyframeCloud(first).ok());
  const Trajectory fused = (*backend)->FusedTrajectory();
  EXPECT_EQ(fused.size(), sink.timestamps_.size());
  ExpectOnThePath(synth, fused);
}

// An agent circling a room twice: its second lap's keyframes are culled (the first lap's
// keyframes see what they see) and what remains of each is its pose, through a kept keyframe.
// Every keyframe stays in the trajectories where the agent and the server put it, and every
// pose change reaches the observer, the culled keyframes' included.
TEST(BackendIntegrationTest, CulledKeyframesKeepTheirPlaceInTheTrajectories) {
  BackendOptions options;
  options.culling.keep_recent = 20;  // the agent's local map below holds as many
  RecordingObserver observer;
  auto backend = Backend::Create(options, &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const AgentId agent(1);
  const SyntheticSequenceOptions synth = QuickLaps(400);
  WireSink sink(agent, backend->get());
  ASSERT_NO_FATAL_FAILURE(TrackOneAgentAtQuarterSize(backend->get(), &sink, synth));
  const Trajectory ground_truth =
      SyntheticSource(synth, FrameRange{0, synth.frames - 1}).GroundTruth();

  const BackendStats stats = (*backend)->stats();
  ASSERT_GE(stats.keyframes_culled, 10u);
  EXPECT_EQ(stats.keyframes, sink.timestamps_.size());
  EXPECT_EQ(observer.culled.size(), stats.keyframes_culled);
  const SparseMemory memory = (*backend)->SparseMemoryUsage();
  EXPECT_EQ(memory.culled_keyframes, stats.keyframes_culled);
  EXPECT_LE(memory.follower_bytes, 100 * memory.culled_keyframes);

  const Trajectory fused = (*backend)->FusedTrajectory();
  ASSERT_EQ(fused.size(), sink.timestamps_.size());
  for (const auto& [id, timestamp] : sink.timestamps_) {
    const auto it = std::find_if(fused.begin(), fused.end(),
                                 [&](const StampedPose& p) { return p.timestamp == timestamp; });
    ASSERT_NE(it, fused.end()) << id.value();
    // What the observer was last told is where the server has it.
    const Pose& told = observer.poses.at({agent, id});
    EXPECT_LT(TranslationDistance(told, it->T_world_cam), 1e-5) << id.value();
    EXPECT_LT(RotationDistance(told, it->T_world_cam), 1e-5) << id.value();
  }
  auto ate = ComputeAte(ground_truth, fused);
  ASSERT_TRUE(ate.ok()) << ate.status().ToString();
  EXPECT_LT(ate->error.rmse, 0.01);
  // Each released cloud is out of the store, and was in it.
  for (const GlobalKeyframeId& id : observer.released) {
    EXPECT_FALSE((*backend)->dense()->KeyframeCloud(id).ok());
    EXPECT_NE(std::find(observer.dense.begin(), observer.dense.end(), id), observer.dense.end());
  }
  EXPECT_EQ((*backend)->dense()->Stats().released_keyframes, observer.released.size());
}

// One agent circling the room once and a quarter, into a back-end whose global BA windows hold 10
// keyframes: the loops where the lap closes are optimised over windows only. At the end,
// FinishGlobalBa optimises the whole map once (more keyframes move than a window holds),
// and once is enough; with a limit below the map's observations the windows' result stands.
// An agent that has not been idle for idle_global_ba_seconds gets no idle run before.
TEST(BackendIntegrationTest, TheEndOfARunOptimisesTheWholeMapOnce) {
  for (const std::size_t limit : {std::size_t{200000}, std::size_t{1}}) {
    BackendOptions options = SmallGlobalBaWindows();
    options.final_global_ba_max_observations = limit;
    options.idle_global_ba_seconds = 3600;  // the agent was never idle that long
    RecordingObserver observer;
    auto backend = Backend::Create(options, &observer);
    ASSERT_TRUE(backend.ok()) << backend.status().ToString();
    const SyntheticSequenceOptions synth = QuickLaps(300);
    WireSink sink(AgentId(1), backend->get());
    ASSERT_NO_FATAL_FAILURE(TrackOneAgentAtQuarterSize(backend->get(), &sink, synth));
    const BackendStats before = (*backend)->stats();
    ASSERT_GE(before.global_ba_windowed, 1) << "no loop was optimised over a window";
    ASSERT_GT((*backend)->FusedTrajectory().size(), 20u);
    const std::map<GlobalKeyframeId, Pose> poses = observer.poses;
    (*backend)->OptimiseIdleMaps();
    (*backend)->WaitIdle();
    ASSERT_EQ((*backend)->stats().global_ba_runs, before.global_ba_runs);

    (*backend)->FinishGlobalBa();
    const BackendStats after = (*backend)->stats();
    const int moved = MovedSince(poses, observer.poses);
    if (limit == 1) {
      EXPECT_EQ(after.global_ba_final, 0);
      EXPECT_EQ(after.global_ba_final_skipped, 1);
      EXPECT_EQ(after.global_ba_runs, before.global_ba_runs);
      EXPECT_EQ(moved, 0);
      continue;
    }
    EXPECT_EQ(after.global_ba_final, 1);
    EXPECT_EQ(after.global_ba_runs, before.global_ba_runs + 1);
    EXPECT_GT(moved, options.global_ba_max_keyframes);
    ExpectOnThePath(synth, (*backend)->FusedTrajectory());
    (*backend)->FinishGlobalBa();  // nothing new since
    EXPECT_EQ((*backend)->stats().global_ba_final, 1);
  }
}

// The same run with the server still up: once its agent has been idle for
// idle_global_ba_seconds, OptimiseIdleMaps has the whole map optimised (more keyframes move
// than a window holds), once, and the end of the run then has nothing left to do.
// (TheEndOfARunOptimisesTheWholeMapOnce: not before the agent has been idle that long.)
TEST(BackendIntegrationTest, AnIdleMapIsOptimisedWholeWhileTheServerRuns) {
  BackendOptions options = SmallGlobalBaWindows();
  options.idle_global_ba_seconds = 1e-6;
  RecordingObserver observer;
  auto backend = Backend::Create(options, &observer);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const SyntheticSequenceOptions synth = QuickLaps(300);
  WireSink sink(AgentId(1), backend->get());
  ASSERT_NO_FATAL_FAILURE(TrackOneAgentAtQuarterSize(backend->get(), &sink, synth));
  const BackendStats before = (*backend)->stats();
  ASSERT_GE(before.global_ba_windowed, 1) << "no loop was optimised over a window";
  const std::map<GlobalKeyframeId, Pose> poses = observer.poses;

  (*backend)->OptimiseIdleMaps();
  (*backend)->WaitIdle();
  const BackendStats after = (*backend)->stats();
  const int moved = MovedSince(poses, observer.poses);
  EXPECT_EQ(after.global_ba_idle, 1);
  EXPECT_EQ(after.global_ba_runs, before.global_ba_runs + 1);
  EXPECT_GT(moved, options.global_ba_max_keyframes);
  ExpectOnThePath(synth, (*backend)->FusedTrajectory());
  (*backend)->OptimiseIdleMaps();  // nothing new since
  (*backend)->FinishGlobalBa();
  EXPECT_EQ((*backend)->stats().global_ba_runs, after.global_ba_runs);
  EXPECT_EQ((*backend)->stats().global_ba_final, 0);
}

// An agent whose trajectories give another camera of its rig (7-Scenes: the depth camera, whose
// poses its ground truth gives): the server's trajectories of it give that camera's poses too.
TEST(BackendIntegrationTest, TrajectoriesGiveTheCameraTheAgentAnnounced) {
  auto backend = Backend::Create(BackendOptions());
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  const AgentId id(1);
  ASSERT_TRUE((*backend)->RegisterAgent(id, "agent1", SyntheticCamera()).ok());
  WireSink sink(id, backend->get());
  SyntheticSequenceOptions synth;
  synth.frames = 40;
  SyntheticSource source(synth, FrameRange{0, 40});
  auto frontend = Frontend::Create(source.camera(), TrackingOptions(), &sink);
  ASSERT_TRUE(frontend.ok());
  RgbdFrame frame;
  while (source.Read(&frame).ok()) (*frontend)->ProcessFrame(frame);
  (*frontend)->Finish();
  (*backend)->WaitIdle();
  const Trajectory colour = (*backend)->AgentTrajectory(id);
  ASSERT_GE(colour.size(), 2u);

  Pose T_color_depth = Pose::Identity();
  T_color_depth.translation() = Eigen::Vector3d(-0.025, 0.003, 0.001);
  T_color_depth.linear() = Eigen::AngleAxisd(0.02, Eigen::Vector3d::UnitY()).toRotationMatrix();
  ASSERT_TRUE(
      (*backend)->RegisterAgent(id, "agent1", SyntheticCamera(), std::nullopt, T_color_depth).ok());
  for (const Trajectory& depth : {(*backend)->AgentTrajectory(id), (*backend)->FusedTrajectory()}) {
    ASSERT_EQ(depth.size(), colour.size());
    for (std::size_t i = 0; i < depth.size(); ++i) {
      EXPECT_EQ(depth[i].timestamp, colour[i].timestamp);
      EXPECT_TRUE(depth[i].T_world_cam.isApprox(colour[i].T_world_cam * T_color_depth, 1e-12)) << i;
      // Not the colour camera's pose: the rig's 25 mm are there.
      EXPECT_NEAR((depth[i].T_world_cam.translation() - colour[i].T_world_cam.translation()).norm(),
                  T_color_depth.translation().norm(), 1e-9);
    }
  }
}

TEST(BackendIntegrationTest, KeyframesBeforeTheCameraOrAfterShutdownAreRefusedCleanly) {
  auto backend = Backend::Create(BackendOptions());
  ASSERT_TRUE(backend.ok());
  PinholeCamera bad = SyntheticCamera();
  bad.fx = -0.0;
  EXPECT_FALSE((*backend)->RegisterAgent(AgentId(1), "x", bad).ok());
  KeyframeMessage m;
  EXPECT_TRUE((*backend)->SubmitKeyframe(AgentId(9), m).ok());  // dropped with a log: no camera
  (*backend)->WaitIdle();
  EXPECT_EQ((*backend)->stats().keyframes, 0u);
  (*backend)->Shutdown();
  EXPECT_FALSE((*backend)->SubmitKeyframe(AgentId(9), m).ok());
}

}  // namespace
}  // namespace ccmd
