// The live view's model: what the back-end reports becomes the state a browser reads once and
// the numbered events it follows; the event log is bounded and tells a browser that fell too
// far behind to reload.

#include <gtest/gtest.h>

#include <thread>

#include "libccmd/view/view_model.h"

namespace ccmd {
namespace {

GlobalKeyframeId Id(int agent, int keyframe) {
  return {AgentId(static_cast<std::uint16_t>(agent)),
          KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

Pose Moved(double x, double yaw) {
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(x, 0.1, -0.2);
  return T;
}

const Json* FindKeyframe(const Json& state, int agent, int keyframe) {
  for (const Json& kf : state.Get("keyframes")->array()) {
    if (kf.Get("a")->number() == agent && kf.Get("k")->number() == keyframe) return &kf;
  }
  return nullptr;
}

void ExpectPose(const Json& numbers, const Pose& T) {
  ASSERT_EQ(numbers.size(), 12u);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) EXPECT_NEAR(numbers.at(4 * r + c).number(), T.matrix()(r, c), 1e-9);
  }
}

TEST(ViewModelTest, TheStateFollowsKeyframesPoseUpdatesAndAFusion) {
  ViewModel model;
  model.OnAgent(AgentId(1), "alpha");
  model.OnAgent(AgentId(2), "beta");
  for (int k = 0; k < 3; ++k) model.OnKeyframe(Id(1, k), MapId(1), Moved(k, 0), 1.0, true);
  for (int k = 0; k < 2; ++k) model.OnKeyframe(Id(2, k), MapId(2), Moved(-k, 0), 1.0, false);
  model.OnPoses(PoseSource::kAgent, MapId(1), {{Id(1, 1), Moved(5, 0.1)}}, 2.0);
  LoopEvent fusion;
  fusion.query = Id(2, 1);
  fusion.candidate = Id(1, 2);
  fusion.fusion = true;
  fusion.map = MapId(1000);
  model.OnLoop(fusion);
  model.OnPoses(PoseSource::kFusion, MapId(1000),
                {{Id(2, 0), Moved(7, 0.2)}, {Id(2, 1), Moved(8, 0.3)}}, 3.0);
  model.OnDenseKeyframe(Id(1, 0), MapId(1), Moved(0, 0));

  const Json state = model.StateJson();
  EXPECT_EQ(state.Get("seq")->number(), 2 + 5 + 1 + 1 + 1 + 1);
  ASSERT_EQ(state.Get("keyframes")->size(), 5u);
  ASSERT_EQ(state.Get("agents")->size(), 2u);
  EXPECT_EQ(state.Get("agents")->at(1).Get("name")->string(), "beta");
  // Both maps are one now; poses are the last reported ones.
  for (const Json& kf : state.Get("keyframes")->array()) EXPECT_EQ(kf.Get("m")->number(), 1000);
  ExpectPose(*FindKeyframe(state, 1, 1)->Get("T"), Moved(5, 0.1));
  ExpectPose(*FindKeyframe(state, 1, 2)->Get("T"), Moved(2, 0));
  ExpectPose(*FindKeyframe(state, 2, 1)->Get("T"), Moved(8, 0.3));
  EXPECT_EQ(FindKeyframe(state, 1, 1)->Get("moves")->number(), 1);
  EXPECT_EQ(FindKeyframe(state, 1, 2)->Get("moves")->number(), 0);
  EXPECT_TRUE(FindKeyframe(state, 1, 0)->Get("cloud")->boolean());
  EXPECT_FALSE(FindKeyframe(state, 1, 1)->Get("cloud")->boolean());
  ASSERT_EQ(state.Get("loops")->size(), 1u);
  EXPECT_TRUE(state.Get("loops")->at(0).Get("fusion")->boolean());

  // The same story as events, in order.
  const EventBatch batch = model.WaitEvents(0, 0, 1.0);
  ASSERT_EQ(batch.kind, EventBatch::Kind::kEvents);
  std::vector<std::string> types;
  for (const auto& [seq, text] : batch.events) {
    EXPECT_EQ(seq, types.size() + 1);
    auto e = Json::Parse(text);
    ASSERT_TRUE(e.ok());
    types.push_back(e->Get("type")->string());
  }
  EXPECT_EQ(types, (std::vector<std::string>{"agent", "agent", "kf", "kf", "kf", "kf", "kf",
                                             "poses", "loop", "poses", "cloud"}));
  auto loop = Json::Parse(batch.events[8].second);
  ASSERT_TRUE(loop.ok());
  ASSERT_EQ(loop->Get("from")->size(), 2u);  // the two maps that became map 1000
  auto first = Json::Parse(batch.events[2].second);
  EXPECT_TRUE(first->Get("primary")->boolean());
  EXPECT_GT(first->Get("t")->number(), 1e12);  // milliseconds since 1970
}

// An agent's restarted segment is unplaced until a loop places it: the state says so per
// keyframe, and each change is one event (keyframes never announced are left out).
TEST(ViewModelTest, PlacementOfRestartedSegmentsIsStateAndEvents) {
  ViewModel model;
  model.OnAgent(AgentId(1), "alpha");
  for (int k = 0; k < 4; ++k) model.OnKeyframe(Id(1, k), MapId(1), Moved(k, 0), 1.0, true);
  model.OnDenseKeyframe(Id(1, 2), MapId(1), Moved(2, 0));
  model.OnPlacement(MapId(1), {Id(1, 2), Id(1, 3), Id(1, 9)}, false);
  Json state = model.StateJson();
  // Unplaced keyframes are out of the dense map: a restart keeps the few before it apart.
  EXPECT_FALSE(FindKeyframe(state, 1, 2)->Get("cloud")->boolean());
  EXPECT_FALSE(FindKeyframe(state, 1, 1)->Has("placed"));
  EXPECT_FALSE(FindKeyframe(state, 1, 2)->Get("placed")->boolean());
  EXPECT_FALSE(FindKeyframe(state, 1, 3)->Get("placed")->boolean());
  model.OnPlacement(MapId(1), {Id(1, 2), Id(1, 3)}, true);
  state = model.StateJson();
  EXPECT_FALSE(FindKeyframe(state, 1, 2)->Has("placed"));
  model.OnPlacement(MapId(1), {Id(1, 9)}, true);  // unknown only: no event

  const EventBatch batch = model.WaitEvents(0, 0, 1.0);
  ASSERT_EQ(batch.events.size(), 1u + 4u + 1u + 2u);
  auto unplaced = Json::Parse(batch.events[6].second);
  ASSERT_TRUE(unplaced.ok());
  EXPECT_EQ(unplaced->Get("type")->string(), "placed");
  EXPECT_FALSE(unplaced->Get("placed")->boolean());
  EXPECT_EQ(unplaced->Get("kfs")->size(), 2u);
  auto placed = Json::Parse(batch.events[7].second);
  ASSERT_TRUE(placed.ok());
  EXPECT_TRUE(placed->Get("placed")->boolean());
}

// A camera circling a mapped room: its new keyframes are culled by the server and their clouds
// released by the dense store. The state keeps a keyframe only while the server keeps it or its
// cloud is drawn, and only the loops between kept keyframes, so it does not grow with passes.
TEST(ViewModelTest, CulledKeyframesLeaveTheStateOnceTheyHaveNoCloud) {
  ViewModel model;
  model.OnAgent(AgentId(1), "alpha");
  for (int k = 0; k < 4; ++k) model.OnKeyframe(Id(1, k), MapId(1), Moved(k, 0), 1.0, true);
  for (int k : {1, 2}) model.OnDenseKeyframe(Id(1, k), MapId(1), Moved(k, 0));
  LoopEvent loop;
  loop.query = Id(1, 3);
  loop.candidate = Id(1, 0);
  loop.map = MapId(1);
  model.OnLoop(loop);
  model.OnCulled(MapId(1), Id(1, 3));  // no cloud: gone, with its loop
  model.OnCulled(MapId(1), Id(1, 2));  // a cloud: stays for it, off the path
  Json state = model.StateJson();
  EXPECT_EQ(state.Get("keyframes")->size(), 3u);
  EXPECT_EQ(FindKeyframe(state, 1, 3), nullptr);
  EXPECT_TRUE(FindKeyframe(state, 1, 2)->Get("culled")->boolean());
  EXPECT_FALSE(FindKeyframe(state, 1, 1)->Has("culled"));
  EXPECT_EQ(state.Get("loops")->size(), 0u);
  // Released clouds: a culled keyframe leaves the state, a kept one stays without its cloud.
  model.OnDenseReleased({Id(1, 2), Id(1, 1), Id(1, 9)});
  state = model.StateJson();
  EXPECT_EQ(state.Get("keyframes")->size(), 2u);
  EXPECT_EQ(FindKeyframe(state, 1, 2), nullptr);
  EXPECT_FALSE(FindKeyframe(state, 1, 1)->Get("cloud")->boolean());
  model.OnCulled(MapId(1), Id(1, 7));  // never announced: no event
  model.OnDenseReleased({Id(1, 8)});   // nor here

  const EventBatch batch = model.WaitEvents(0, 0, 1.0);
  std::vector<std::string> types;
  for (const auto& [seq, text] : batch.events)
    types.push_back(Json::Parse(text)->Get("type")->string());
  EXPECT_EQ(types, (std::vector<std::string>{"agent", "kf", "kf", "kf", "kf", "cloud", "cloud",
                                             "loop", "culled", "culled", "released"}));
  auto released = Json::Parse(batch.events.back().second);
  ASSERT_TRUE(released.ok());
  EXPECT_EQ(released->Get("kfs")->size(), 2u);  // the unknown one left out
}

TEST(ViewModelTest, PosesOfUnknownKeyframesAreNotEvents) {
  ViewModel model;
  model.OnPoses(PoseSource::kGlobalBa, MapId(1), {{Id(1, 9), Pose::Identity()}}, 1.0);
  EXPECT_EQ(model.last_seq(), 0u);
  EXPECT_EQ(model.WaitEvents(0, 0, 0.01).kind, EventBatch::Kind::kTimeout);
}

// A keyframe culled before its map fused with the world map has no cloud then and leaves the
// state; its cloud comes with the fusion, and brings it back, culled, where the cloud is.
TEST(ViewModelTest, ACloudAfterTheCullingBringsTheKeyframeBack) {
  ViewModel model;
  model.OnKeyframe(Id(2, 4), MapId(2), Moved(1, 0), 1.0, false);
  model.OnCulled(MapId(2), Id(2, 4));
  ASSERT_EQ(model.StateJson().Get("keyframes")->size(), 0u);
  model.OnDenseKeyframe(Id(2, 4), MapId(1), Moved(3, 0.2));
  const Json state = model.StateJson();
  const Json* kf = FindKeyframe(state, 2, 4);
  ASSERT_NE(kf, nullptr);
  EXPECT_TRUE(kf->Get("culled")->boolean());
  EXPECT_TRUE(kf->Get("cloud")->boolean());
  EXPECT_EQ(kf->Get("m")->number(), 1);
  ExpectPose(*kf->Get("T"), Moved(3, 0.2));
  const EventBatch batch = model.WaitEvents(0, 0, 1.0);
  std::vector<std::string> types;
  for (const auto& [seq, text] : batch.events)
    types.push_back(Json::Parse(text)->Get("type")->string());
  EXPECT_EQ(types, (std::vector<std::string>{"kf", "culled", "kf", "cloud"}));
}

TEST(ViewModelTest, TheLogIsBoundedAndABrowserTooFarBehindReloads) {
  ViewModelOptions options;
  options.max_events = 16;
  ASSERT_TRUE(options.Validate().ok());
  ViewModel model(options);
  for (int k = 0; k < 40; ++k) model.OnKeyframe(Id(1, k), MapId(1), Pose::Identity(), 1.0, true);
  EXPECT_EQ(model.last_seq(), 40u);
  EXPECT_EQ(model.WaitEvents(5, 0, 1.0).kind, EventBatch::Kind::kReset);
  EXPECT_EQ(model.WaitEvents(41, 0, 1.0).kind,
            EventBatch::Kind::kReset);  // a number from another run
  const EventBatch recent = model.WaitEvents(37, 0, 1.0);
  ASSERT_EQ(recent.kind, EventBatch::Kind::kEvents);
  ASSERT_EQ(recent.events.size(), 3u);
  EXPECT_EQ(recent.events.front().first, 38u);
  EXPECT_EQ(model.WaitEvents(24, 0, 1.0).events.size(), 16u);  // the oldest one kept
  EXPECT_EQ(model.WaitEvents(23, 0, 1.0).kind, EventBatch::Kind::kReset);
  EXPECT_EQ(model.WaitEvents(40, 0, 0.01).kind, EventBatch::Kind::kTimeout);
  // The state still has everything.
  EXPECT_EQ(model.StateJson().Get("keyframes")->size(), 40u);

  // Statistics come with the next wait when newer than the caller's.
  Json stats;
  stats["keyframes"] = 40;
  model.PublishStats(stats);
  const EventBatch with_stats = model.WaitEvents(40, 0, 1.0);
  ASSERT_EQ(with_stats.kind, EventBatch::Kind::kEvents);
  EXPECT_TRUE(with_stats.events.empty());
  EXPECT_EQ(with_stats.stats, stats.Dump(-1));
  EXPECT_EQ(model.WaitEvents(40, with_stats.stats_version, 0.01).kind, EventBatch::Kind::kTimeout);
}

TEST(ViewModelTest, CloseWakesAWaitingStream) {
  ViewModel model;
  EventBatch seen;
  std::thread waiter([&] { seen = model.WaitEvents(0, 0, 600); });
  model.Close();
  waiter.join();
  EXPECT_EQ(seen.kind, EventBatch::Kind::kClosed);
  EXPECT_EQ(model.WaitEvents(0, 0, 600).kind, EventBatch::Kind::kClosed);
}

}  // namespace
}  // namespace ccmd
