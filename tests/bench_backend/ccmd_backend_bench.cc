// ccmd_backend_bench: K agents on split segments of a sequence, in one process, feeding the
// server back-end through the wire format (serialize + parse). Reports maps after fusion,
// loops, fused ATE against ground truth, every accepted loop checked against ground truth,
// global BA runs and keyframe intake latency with and without a global BA running; with
// --loop-eval also the loop detector's precision and recall (loop_eval.h).

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <map>
#include <mutex>
#include <thread>

#include <opencv2/imgproc.hpp>

#include "apps/app_common.h"
#include "libccmd/backend/backend.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/tracking/keyframe_message.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/percentile.h"
#include "libccmd/util/timer.h"
#include "tests/bench_backend/loop_eval.h"

namespace {

using namespace ccmd;
using bench::RecordedMessage;

// Every message in the order the agents submitted them, keyframes without their RGB-D
// payload (the loop detector never looks at it), for the offline detector evaluation and to
// find a keyframe's timestamp.
class Recorder {
 public:
  void Add(RecordedMessage m) {
    std::lock_guard<std::mutex> lock(mutex_);
    messages_.push_back(std::move(m));
  }
  // Call once the agents have finished.
  const std::vector<RecordedMessage>& messages() const { return messages_; }

 private:
  std::mutex mutex_;
  std::vector<RecordedMessage> messages_;
};

// Depth images are kept at a quarter of their size: enough to tell which surfaces two views
// share, and 600 frames fit in about 50 MB.
constexpr int kGroundTruthDepthShrink = 4;

cv::Mat SmallDepthMetres(const cv::Mat& depth_mm) {
  cv::Mat small, metres;
  cv::resize(
      depth_mm, small,
      cv::Size(depth_mm.cols / kGroundTruthDepthShrink, depth_mm.rows / kGroundTruthDepthShrink), 0,
      0, cv::INTER_NEAREST);
  small.convertTo(metres, CV_32F, 1e-3);
  return metres;
}

struct LatencySummary {
  std::size_t count = 0;
  double median = 0, p95 = 0, max = 0;
};

LatencySummary Summarize(const std::vector<double>& v) {
  LatencySummary s;
  s.count = v.size();
  s.median = Percentile(v, 0.5);
  s.p95 = Percentile(v, 0.95);
  s.max = v.empty() ? 0 : *std::max_element(v.begin(), v.end());
  return s;
}

Json LatencyJson(const LatencySummary& s) {
  Json j;
  j["count"] = s.count;
  j["median_ms"] = s.median;
  j["p95_ms"] = s.p95;
  j["max_ms"] = s.max;
  return j;
}

// Intake latency split by whether a global BA was running when the keyframe entered its map,
// and the global BA runs. The keyframes that arrived without a global BA are the reference.
Json ReportTimings(const BackendTimings& t) {
  std::vector<double> during, without;
  for (std::size_t i = 0; i < t.intake_ms.size(); ++i)
    (t.intake_during_gba[i] ? during : without).push_back(t.intake_ms[i]);
  const LatencySummary d = Summarize(during), w = Summarize(without), all = Summarize(t.intake_ms);
  std::printf("keyframe intake latency (submission to insertion into its map), ms:\n");
  std::printf("  %-28s %9s %8s %8s %8s\n", "", "keyframes", "median", "p95", "max");
  std::printf("  %-28s %9zu %8.1f %8.1f %8.1f\n", "no global BA running", w.count, w.median, w.p95,
              w.max);
  std::printf("  %-28s %9zu %8.1f %8.1f %8.1f\n", "while a global BA ran", d.count, d.median, d.p95,
              d.max);
  std::printf("  %-28s %9zu %8.1f %8.1f %8.1f\n", "all", all.count, all.median, all.p95, all.max);
  Json j;
  j["without_gba"] = LatencyJson(w);
  j["during_gba"] = LatencyJson(d);
  j["all"] = LatencyJson(all);
  if (d.count > 0 && w.count > 0 && w.median > 0 && w.p95 > 0) {
    std::printf("  during / without global BA: median %.2f, p95 %.2f, max %.2f\n",
                d.median / w.median, d.p95 / w.p95, w.max > 0 ? d.max / w.max : 0.0);
    j["ratio_median"] = d.median / w.median;
    j["ratio_p95"] = d.p95 / w.p95;
  }
  std::vector<double> runs = t.global_ba_seconds;
  int applied = 0;
  for (char a : t.global_ba_applied) applied += a != 0;
  double total = 0;
  for (double r : runs) total += r;
  std::printf(
      "global BA: %zu runs (%d applied, %zu abandoned for newer loops), %.2f s in all, median %.2f "
      "s, "
      "max %.2f s; runs:",
      runs.size(), applied, runs.size() - applied, total, Percentile(runs, 0.5),
      runs.empty() ? 0.0 : *std::max_element(runs.begin(), runs.end()));
  for (std::size_t i = 0; i < runs.size(); ++i)
    std::printf(" %.2f%s", runs[i], t.global_ba_applied[i] ? "" : "*");
  std::printf("%s\n", applied < static_cast<int>(runs.size()) ? " (* abandoned)" : "");
  Json g;
  g["runs"] = runs.size();
  g["applied"] = applied;
  g["total_s"] = total;
  Json list = Json::MakeArray();
  for (double r : runs) list.Push(Json(r));
  g["durations_s"] = list;
  j["global_ba"] = g;
  return j;
}

// Sends the front-end's output through the wire format into the back-end.
class WireSink : public KeyframeSink {
 public:
  WireSink(AgentId agent, Backend* backend, const RgbdEncodeOptions& rgbd, Recorder* recorder)
      : agent_(agent), backend_(backend), rgbd_(rgbd), recorder_(recorder) {}
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
    if (!parsed.ok()) return;
    std::optional<RgbdPayload> payload = std::move(parsed->rgbd);
    parsed->rgbd.reset();
    recorder_->Add({agent_, std::make_shared<const KeyframeMessage>(*parsed), nullptr});
    parsed->rgbd = std::move(payload);
    backend_->SubmitKeyframe(agent_, std::move(parsed).value()).IgnoreError();
  }
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override {
    auto bytes = SerializePoseUpdate(ToPoseUpdateMessage(updates));
    if (!bytes.ok()) return;
    bytes_ += bytes->size();
    auto parsed = ParsePoseUpdate(*bytes);
    if (!parsed.ok()) return;
    recorder_->Add({agent_, nullptr, std::make_shared<const PoseUpdateMessage>(*parsed)});
    backend_->SubmitPoseUpdate(agent_, std::move(parsed).value()).IgnoreError();
  }
  std::size_t bytes_ = 0;
  int keyframes_ = 0;
  int rgbd_keyframes_ = 0;
  KeyframeSizeBreakdown parts_;

 private:
  AgentId agent_;
  Backend* backend_;
  RgbdEncodeOptions rgbd_;
  Recorder* recorder_;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Back-end benchmark: split replay in one process, through the wire format."};
  std::string source_spec, config_path, json_path, out_dir;
  std::string vocabulary_path = app::DefaultVocabularyPath();
  int agents = 3;
  bool no_gba = false, no_dense = false, loop_eval = false;
  app.add_option("--source", source_spec, "tum:DIR or synth:...")->required();
  app.add_option("--config", config_path, "Camera config");
  app.add_option("--agents", agents, "Number of agents (segments)")->check(CLI::Range(1, 16));
  app.add_option("--json", json_path, "Write results as JSON");
  app.add_option("--out", out_dir, "Write trajectories and the dense map here");
  app.add_option("--vocabulary", vocabulary_path,
                 "Vocabulary file (default: the build's, as ccmd_server uses); empty or missing: "
                 "trained online")
      ->capture_default_str();
  app.add_flag("--no-gba", no_gba, "Disable global BA");
  app.add_flag("--no-dense", no_dense, "Disable the dense map");
  BackendOptions options;
  app.add_option("--loop-min-inliers", options.loops.verification.min_inliers,
                 "Inliers a verified loop needs after refinement")
      ->capture_default_str()
      ->check(CLI::Range(6, 1000));
  app.add_flag(
      "--loop-eval", loop_eval,
      "Also measure the loop detector offline: every keyframe queried and its candidates verified, "
      "precision and recall against ground truth");
  CLI11_PARSE(app, argc, argv);

  options.global_ba = !no_gba;
  options.dense = !no_dense;
  // As ccmd_server: a vocabulary file when there is one, else online training.
  if (!vocabulary_path.empty() && FileExists(vocabulary_path)) {
    auto vocabulary = Vocabulary::Load(vocabulary_path);
    if (!vocabulary.ok()) {
      std::fprintf(stderr, "%s\n", vocabulary.status().ToString().c_str());
      return 1;
    }
    options.place.vocabulary = std::make_shared<const Vocabulary>(std::move(vocabulary).value());
    std::printf("vocabulary %s: %d words, fingerprint %08x\n", vocabulary_path.c_str(),
                options.place.vocabulary->word_count(), options.place.vocabulary->Fingerprint());
  } else {
    std::printf("no vocabulary file%s%s: trained online from the keyframes\n",
                vocabulary_path.empty() ? "" : " at ", vocabulary_path.c_str());
  }
  std::printf(
      "loop detection: %d candidates verified per query, >= %d inliers after refinement (%d "
      "RANSAC, %d "
      "matches), %d consistent keyframes, same-agent neighbours within %d ids excluded\n",
      options.loops.loop_candidates, options.loops.verification.min_inliers,
      options.loops.verification.min_ransac_inliers, options.loops.verification.min_matches,
      options.loops.loop_consistency, options.loops.exclude_recent_keyframes);
  auto backend = Backend::Create(options);
  if (!backend.ok()) {
    std::fprintf(stderr, "%s\n", backend.status().ToString().c_str());
    return 1;
  }
  std::vector<std::unique_ptr<RgbdSource>> sources;
  std::map<AgentId, PinholeCamera> cameras;
  Trajectory ground_truth;
  for (int i = 0; i < agents; ++i) {
    SourceOptions so;
    so.camera_config = config_path;
    so.configs_dir = app::ConfigDir();
    so.segment = std::make_pair(i + 1, agents);
    auto source = OpenSource(source_spec, so);
    if (!source.ok()) {
      std::fprintf(stderr, "%s\n", source.status().ToString().c_str());
      return 1;
    }
    for (const auto& p : (*source)->GroundTruth()) ground_truth.push_back(p);
    cameras[AgentId(i + 1)] = (*source)->camera();
    (*backend)
        ->RegisterAgent(AgentId(i + 1), "agent" + std::to_string(i + 1), (*source)->camera(),
                        std::nullopt, (*source)->T_color_trajectory())
        .IgnoreError();
    sources.push_back(std::move(source).value());
  }
  std::sort(ground_truth.begin(), ground_truth.end(),
            [](auto& a, auto& b) { return a.timestamp < b.timestamp; });
  ground_truth.erase(std::unique(ground_truth.begin(), ground_truth.end(),
                                 [](auto& a, auto& b) { return a.timestamp == b.timestamp; }),
                     ground_truth.end());

  RgbdEncodeOptions rgbd;
  Recorder recorder;
  std::vector<std::unique_ptr<WireSink>> sinks;
  std::vector<Trajectory> agent_frames(agents);
  // Per agent, each frame's depth by timestamp: the ground truth of which surfaces a keyframe
  // sees (only when there are ground-truth poses to place them with).
  const bool have_ground_truth = !ground_truth.empty();
  std::vector<std::map<double, cv::Mat>> frame_depths(agents);
  const Stopwatch watch;
  std::vector<std::thread> threads;
  for (int i = 0; i < agents; ++i) {
    sinks.push_back(std::make_unique<WireSink>(AgentId(i + 1), backend->get(), rgbd, &recorder));
    threads.emplace_back([&, i] {
      TrackingOptions tracking;
      auto frontend = Frontend::Create(sources[i]->camera(), tracking, sinks[i].get());
      if (!frontend.ok()) return;
      RgbdFrame frame;
      while (sources[i]->Read(&frame).ok()) {
        if (have_ground_truth) frame_depths[i][frame.timestamp] = SmallDepthMetres(frame.depth_mm);
        (*frontend)->ProcessFrame(frame);
      }
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
  std::printf("%d agents: %.1f s tracking, %.1f s until the back-end was idle; %zu map(s) left\n",
              agents, agents_seconds, total_seconds, maps.size());
  const Trajectory fused = (*backend)->FusedTrajectory();
  auto ate = ComputeAte(ground_truth, fused);
  if (ate.ok()) {
    result["fused_ate_rmse_m"] = ate->error.rmse;
    result["fused_keyframes"] = ate->matched;
    std::printf("fused trajectory (primary map): %zu keyframes, ATE rmse %.4f m\n", ate->matched,
                ate->error.rmse);
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
    std::printf(
        "agent %d: %d keyframes, %.1f kB/keyframe, server ATE %.4f m, agent-side ATE %.4f m, %s\n",
        i + 1, sinks[i]->keyframes_, sinks[i]->bytes_ / 1e3 / std::max(1, sinks[i]->keyframes_),
        agent_ate.ok() ? agent_ate->error.rmse : -1.0,
        frames_ate.ok() ? frames_ate->error.rmse : -1.0,
        a["in_primary_map"].boolean() ? "in the primary map" : "NOT fused");
    const KeyframeSizeBreakdown& b = sinks[i]->parts_;
    const double n = std::max(1, sinks[i]->keyframes_) * 1e3;
    std::printf(
        "   per keyframe (kB): pose %.2f keypoints %.1f descriptors %.1f map points %.1f colour "
        "%.1f depth %.1f other %.1f; RGB-D sent with %d of %d\n",
        b.pose / n, b.keypoints / n, b.descriptors / n, b.map_points / n, b.colour / n, b.depth / n,
        b.other / n, sinks[i]->rgbd_keyframes_, sinks[i]->keyframes_);
    a["rgbd_keyframes"] = sinks[i]->rgbd_keyframes_;
    per_agent.Push(a);
  }
  result["agents"] = per_agent;
  const BackendStats s = (*backend)->stats();
  std::printf(
      "loops %d, fusions %d, global BA %d (%.1f s), intake median %.1f ms p99 %.1f ms; during GBA: "
      "%zu keyframes, median %.1f ms max %.1f ms\n",
      s.loops, s.fusions, s.global_ba_runs, s.global_ba_seconds, s.intake_ms_median,
      s.intake_ms_p99, s.intake_during_gba_count, s.intake_during_gba_ms_median,
      s.intake_during_gba_ms_max);
  result["intake"] = ReportTimings((*backend)->timings());

  if (have_ground_truth) {
    // Ground truth per keyframe: its frame's true pose and depth.
    std::map<double, Pose> true_pose;
    for (const StampedPose& p : ground_truth) true_pose[p.timestamp] = p.T_world_cam;
    bench::PlaceGroundTruth truth{bench::PlaceGroundTruthOptions()};
    int missing = 0;
    for (const RecordedMessage& m : recorder.messages()) {
      if (!m.keyframe) continue;
      const int agent_index = m.agent.value() - 1;
      const auto pose = true_pose.find(m.keyframe->timestamp);
      const auto depth = frame_depths[agent_index].find(m.keyframe->timestamp);
      if (pose == true_pose.end() || depth == frame_depths[agent_index].end()) {
        ++missing;
        continue;
      }
      const PinholeCamera& camera = cameras.at(m.agent);
      truth.Add({m.agent, m.keyframe->id}, pose->second, depth->second,
                camera.Resized(depth->second.cols, depth->second.rows));
    }
    frame_depths.clear();
    if (missing > 0)
      std::printf("%d keyframes without ground truth are left out of the loop checks\n", missing);
    // How well the agents' own maps agree with the ground truth sets the tolerance a loop's
    // transform is judged with (at least the default).
    std::printf("loop checks against ground truth:\n");
    bench::TransformError p95;
    result["covisible_pairs_error"] =
        bench::ReportCovisiblePairs(bench::CovisiblePairErrors(recorder.messages(), truth), &p95);
    const bench::PlaceGroundTruthOptions& defaults = truth.options();
    truth.SetTransformTolerance(std::max(defaults.max_translation_error, p95.translation),
                                std::max(defaults.max_rotation_error_deg, p95.rotation_deg));
    std::printf(
        "  a loop's transform is right within %.1f mm and %.2f deg of the true one (the larger of "
        "the "
        "default and the reference's p95)\n",
        truth.options().max_translation_error * 1e3, truth.options().max_rotation_error_deg);
    result["transform_tolerance_m"] = truth.options().max_translation_error;
    result["transform_tolerance_deg"] = truth.options().max_rotation_error_deg;
    const std::vector<LoopEvent> events = (*backend)->loop_events();
    result["accepted_loops"] =
        bench::ReportLoopEvents(bench::CheckLoopEvents(events, truth), events);
    if (loop_eval) {
      const bench::DetectorEvaluation evaluation =
          bench::EvaluateDetector(recorder.messages(), cameras, options, truth);
      result["loop_detector"] = bench::ReportDetector(evaluation, truth);
    }
  }
  if (!out_dir.empty()) {
    MakeDirectories(out_dir).IgnoreError();
    WriteTumTrajectory(fused, out_dir + "/trajectory_fused.txt").IgnoreError();
    for (int i = 0; i < agents; ++i) {
      WriteTumTrajectory((*backend)->AgentTrajectory(AgentId(i + 1)),
                         out_dir + "/trajectory_agent" + std::to_string(i + 1) + ".txt")
          .IgnoreError();
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
