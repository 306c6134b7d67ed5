// ccmd_backend_bench: K agents on split segments of a sequence, in one process, feeding the
// server back-end through the wire format (serialize + parse). Reports maps after fusion,
// loops, fused ATE against ground truth, global BA runs and keyframe intake latency.

#include <CLI/CLI.hpp>
#include <cstdio>
#include <mutex>
#include <thread>

#include "libccmd/backend/backend.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/tracking/keyframe_message.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/timer.h"

namespace {

using namespace ccmd;

// Sends the front-end's output through the wire format into the back-end.
class WireSink : public KeyframeSink {
 public:
  WireSink(AgentId agent, Backend* backend, const RgbdEncodeOptions& rgbd) : agent_(agent), backend_(backend), rgbd_(rgbd) {}
  void OnKeyframe(KeyframeSnapshot snapshot) override {
    auto message = ToKeyframeMessage(snapshot, rgbd_);
    if (!message.ok()) {
      CCMD_LOG(ERROR) << message.status().ToString();
      return;
    }
    KeyframeSizeBreakdown breakdown;
    auto bytes = SerializeKeyframe(*message, &breakdown);
    if (!bytes.ok()) {
      CCMD_LOG(ERROR) << bytes.status().ToString();
      return;
    }
    bytes_ += bytes->size();
    ++keyframes_;
    rgbd_keyframes_ += message->rgbd.has_value();
    parts_.pose += breakdown.pose;
    parts_.keypoints += breakdown.keypoints;
    parts_.descriptors += breakdown.descriptors;
    parts_.map_points += breakdown.map_points;
    parts_.colour += breakdown.colour;
    parts_.depth += breakdown.depth;
    parts_.other += breakdown.other;
    auto parsed = ParseKeyframe(*bytes);
    if (parsed.ok()) backend_->SubmitKeyframe(agent_, std::move(parsed).value()).IgnoreError();
  }
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override {
    auto bytes = SerializePoseUpdate(ToPoseUpdateMessage(updates));
    if (!bytes.ok()) return;
    bytes_ += bytes->size();
    auto parsed = ParsePoseUpdate(*bytes);
    if (parsed.ok()) backend_->SubmitPoseUpdate(agent_, std::move(parsed).value()).IgnoreError();
  }
  std::size_t bytes_ = 0;
  int keyframes_ = 0;
  int rgbd_keyframes_ = 0;
  KeyframeSizeBreakdown parts_;

 private:
  AgentId agent_;
  Backend* backend_;
  RgbdEncodeOptions rgbd_;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Back-end benchmark: split replay in one process, through the wire format."};
  std::string source_spec, config_path, json_path, out_dir, vocabulary_path;
  int agents = 3;
  bool no_gba = false, no_dense = false;
  app.add_option("--source", source_spec, "tum:DIR or synth:...")->required();
  app.add_option("--config", config_path, "Camera config");
  app.add_option("--agents", agents, "Number of agents (segments)")->check(CLI::Range(1, 16));
  app.add_option("--json", json_path, "Write results as JSON");
  app.add_option("--out", out_dir, "Write trajectories and the dense map here");
  app.add_option("--vocabulary", vocabulary_path, "Vocabulary file (default: trained online)");
  app.add_flag("--no-gba", no_gba, "Disable global BA");
  app.add_flag("--no-dense", no_dense, "Disable the dense map");
  CLI11_PARSE(app, argc, argv);

  BackendOptions options;
  options.global_ba = !no_gba;
  options.dense = !no_dense;
  if (!vocabulary_path.empty()) {
    auto vocabulary = Vocabulary::Load(vocabulary_path);
    if (!vocabulary.ok()) {
      std::fprintf(stderr, "%s\n", vocabulary.status().ToString().c_str());
      return 1;
    }
    options.place.vocabulary = std::make_shared<const Vocabulary>(std::move(vocabulary).value());
  }
  auto backend = Backend::Create(options);
  if (!backend.ok()) {
    std::fprintf(stderr, "%s\n", backend.status().ToString().c_str());
    return 1;
  }
  std::vector<std::unique_ptr<RgbdSource>> sources;
  Trajectory ground_truth;
  for (int i = 0; i < agents; ++i) {
    SourceOptions so;
    so.camera_config = config_path;
    so.configs_dir = CCMD_CONFIG_DIR;
    so.segment = std::make_pair(i + 1, agents);
    auto source = OpenSource(source_spec, so);
    if (!source.ok()) {
      std::fprintf(stderr, "%s\n", source.status().ToString().c_str());
      return 1;
    }
    for (const auto& p : (*source)->GroundTruth()) ground_truth.push_back(p);
    (*backend)->RegisterAgent(AgentId(i + 1), "agent" + std::to_string(i + 1), (*source)->camera()).IgnoreError();
    sources.push_back(std::move(source).value());
  }
  std::sort(ground_truth.begin(), ground_truth.end(), [](auto& a, auto& b) { return a.timestamp < b.timestamp; });
  ground_truth.erase(std::unique(ground_truth.begin(), ground_truth.end(),
                                 [](auto& a, auto& b) { return a.timestamp == b.timestamp; }),
                     ground_truth.end());

  RgbdEncodeOptions rgbd;
  std::vector<std::unique_ptr<WireSink>> sinks;
  std::vector<Trajectory> agent_frames(agents);
  const Stopwatch watch;
  std::vector<std::thread> threads;
  for (int i = 0; i < agents; ++i) {
    sinks.push_back(std::make_unique<WireSink>(AgentId(i + 1), backend->get(), rgbd));
    threads.emplace_back([&, i] {
      TrackingOptions tracking;
      auto frontend = Frontend::Create(sources[i]->camera(), tracking, sinks[i].get());
      if (!frontend.ok()) return;
      RgbdFrame frame;
      while (sources[i]->Read(&frame).ok()) (*frontend)->ProcessFrame(frame);
      (*frontend)->Finish();
      agent_frames[i] = (*frontend)->FrameTrajectory();
    });
  }
  for (auto& t : threads) t.join();
  const double agents_seconds = watch.ElapsedSeconds();
  (*backend)->WaitIdle();
  const double total_seconds = watch.ElapsedSeconds();

  Json result = (*backend)->StatsJson();
  result["agents_seconds"] = agents_seconds;
  result["total_seconds"] = total_seconds;
  const auto maps = (*backend)->Maps();
  result["maps_after_fusion"] = maps.size();
  std::printf("%d agents: %.1f s tracking, %.1f s until the back-end was idle; %zu map(s) left\n", agents,
              agents_seconds, total_seconds, maps.size());
  const Trajectory fused = (*backend)->FusedTrajectory();
  auto ate = ComputeAte(ground_truth, fused);
  if (ate.ok()) {
    result["fused_ate_rmse_m"] = ate->error.rmse;
    result["fused_keyframes"] = ate->matched;
    std::printf("fused trajectory (primary map): %zu keyframes, ATE rmse %.4f m\n", ate->matched, ate->error.rmse);
  }
  Json per_agent = Json::MakeArray();
  for (int i = 0; i < agents; ++i) {
    Json a;
    const Trajectory t = (*backend)->AgentTrajectory(AgentId(i + 1));
    auto agent_ate = ComputeAte(ground_truth, t);
    auto frames_ate = ComputeAte(ground_truth, agent_frames[i]);
    a["in_primary_map"] = (*backend)->AgentInPrimaryMap(AgentId(i + 1));
    a["keyframes"] = sinks[i]->keyframes_;
    a["bytes"] = sinks[i]->bytes_;
    if (agent_ate.ok()) a["ate_rmse_m"] = agent_ate->error.rmse;
    if (frames_ate.ok()) a["agent_frames_ate_rmse_m"] = frames_ate->error.rmse;
    std::printf("agent %d: %d keyframes, %.1f kB/keyframe, server ATE %.4f m, agent-side ATE %.4f m, %s\n", i + 1,
                sinks[i]->keyframes_, sinks[i]->bytes_ / 1e3 / std::max(1, sinks[i]->keyframes_),
                agent_ate.ok() ? agent_ate->error.rmse : -1.0, frames_ate.ok() ? frames_ate->error.rmse : -1.0,
                a["in_primary_map"].boolean() ? "in the primary map" : "NOT fused");
    const KeyframeSizeBreakdown& b = sinks[i]->parts_;
    const double n = std::max(1, sinks[i]->keyframes_) * 1e3;
    std::printf("   per keyframe (kB): pose %.2f keypoints %.1f descriptors %.1f map points %.1f colour %.1f depth %.1f other %.1f; RGB-D sent with %d of %d\n",
                b.pose / n, b.keypoints / n, b.descriptors / n, b.map_points / n, b.colour / n, b.depth / n,
                b.other / n, sinks[i]->rgbd_keyframes_, sinks[i]->keyframes_);
    a["rgbd_keyframes"] = sinks[i]->rgbd_keyframes_;
    per_agent.Push(a);
  }
  result["agents"] = per_agent;
  const BackendStats s = (*backend)->stats();
  std::printf("loops %d, fusions %d, global BA %d (%.1f s), intake median %.1f ms p99 %.1f ms; during GBA: %zu keyframes, median %.1f ms max %.1f ms\n",
              s.loops, s.fusions, s.global_ba_runs, s.global_ba_seconds, s.intake_ms_median, s.intake_ms_p99,
              s.intake_during_gba_count, s.intake_during_gba_ms_median, s.intake_during_gba_ms_max);
  if (!out_dir.empty()) {
    MakeDirectories(out_dir).IgnoreError();
    WriteTumTrajectory(fused, out_dir + "/trajectory_fused.txt").IgnoreError();
    for (int i = 0; i < agents; ++i) {
      WriteTumTrajectory((*backend)->AgentTrajectory(AgentId(i + 1)),
                         out_dir + "/trajectory_agent" + std::to_string(i + 1) + ".txt").IgnoreError();
    }
    if (!no_dense) {
      const Status st = (*backend)->ExportDenseMap(out_dir + "/map.ply");
      if (!st.ok()) std::fprintf(stderr, "%s\n", st.ToString().c_str());
    }
  }
  if (!json_path.empty()) WriteJsonFile(result, json_path).IgnoreError();
  (*backend)->Shutdown();
  return 0;
}
