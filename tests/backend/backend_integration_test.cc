// Two agents on the halves (10% overlap) of a synthetic sequence feed the back-end through the
// wire format: their maps must be fused through the overlap, the fused keyframe trajectory
// must match the ground truth, and the dense map must fill.

#include <gtest/gtest.h>

#include <thread>

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
    ASSERT_TRUE(backend_->SubmitKeyframe(agent_, std::move(parsed).value()).ok());
  }
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override {
    auto bytes = SerializePoseUpdate(ToPoseUpdateMessage(updates));
    ASSERT_TRUE(bytes.ok());
    auto parsed = ParsePoseUpdate(*bytes);
    ASSERT_TRUE(parsed.ok());
    ASSERT_TRUE(backend_->SubmitPoseUpdate(agent_, std::move(parsed).value()).ok());
  }

 private:
  AgentId agent_;
  Backend* backend_;
};

TEST(BackendIntegrationTest, TwoAgentsAreFusedIntoOneAccurateMap) {
  BackendOptions options;
  auto backend = Backend::Create(options);
  ASSERT_TRUE(backend.ok()) << backend.status().ToString();
  SyntheticSequenceOptions synth;
  synth.frames = 200;
  const auto segments = SplitWithOverlap(synth.frames, 2);
  ASSERT_TRUE(segments.ok());
  Trajectory ground_truth = MakeLoopPath(synth.frames, synth.fps, synth.path);
  std::vector<std::thread> agents;
  std::vector<std::unique_ptr<WireSink>> sinks;
  for (int i = 0; i < 2; ++i) {
    const AgentId id(i + 1);
    sinks.push_back(std::make_unique<WireSink>(id, backend->get()));
    ASSERT_TRUE((*backend)->RegisterAgent(id, "agent" + std::to_string(i + 1), SyntheticCamera()).ok());
    agents.emplace_back([&, i] {
      SyntheticSource source(synth, (*segments)[i]);
      auto frontend = Frontend::Create(source.camera(), TrackingOptions(), sinks[i].get());
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
  // The dense map holds keyframes of both agents.
  auto cloud = (*backend)->dense()->Extract(DenseSelection::Global());
  ASSERT_TRUE(cloud.ok());
  EXPECT_GT(cloud->size(), 10000u);
  EXPECT_EQ((*backend)->dense()->Agents().size(), 2u);
  (*backend)->Shutdown();
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
