// ccmd_agent: the robot side. Runs the ORB RGB-D front-end on a source (dataset, synthetic,
// camera) and sends compact keyframes to a ccmd_server, or runs offline and writes its
// trajectory.

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <thread>

#include "apps/app_common.h"
#include "libccmd/io/config.h"
#include "libccmd/io/split.h"
#include "libccmd/io/tum_recorder.h"
#include "libccmd/net/agent_link.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/session_camera.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/system/link_sink.h"
#include "libccmd/tracking/config.h"
#include "libccmd/tracking/cpu_budget.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/process_usage.h"
#include "libccmd/util/string_util.h"
#include "libccmd/util/timer.h"

namespace {

// Exit status when messages were refused or never acknowledged (1: any other error).
constexpr int kExitMessagesLost = 3;

std::atomic<bool> g_stop{false};
void OnSignal(int) { g_stop = true; }

int Fail(const std::string& what) {
  std::fprintf(stderr, "ccmd_agent: %s\n", what.c_str());
  return 1;
}

ccmd::Json StatsJson(const ccmd::FrontendStats& s, double wall_seconds,
                     const std::vector<ccmd::RgbdDecision>& decisions) {
  ccmd::Json j;
  j["frames"] = s.frames;
  j["tracked_frames"] = s.tracked_frames;
  j["lost_frames"] = s.lost_frames;
  j["restarts"] = s.restarts;
  j["keyframes"] = s.keyframes;
  j["map_keyframes"] = s.map_keyframes;
  j["map_points"] = s.map_points;
  j["wall_seconds"] = wall_seconds;
  j["fps"] = wall_seconds > 0 ? s.frames / wall_seconds : 0.0;
  const double n = std::max(1, s.frames);
  j["extract_ms_mean"] = s.extract_ms_total / n;
  j["track_ms_mean"] = s.track_ms_total / n;
  j["extract_cpu_ms_mean"] = s.extract_cpu_ms_total / n;
  j["track_cpu_ms_mean"] = s.track_cpu_ms_total / n;
  const ccmd::MappingStats& m = s.mapping;
  j["local_ba_runs"] = m.local_ba_runs;
  j["local_ba_aborted"] = m.local_ba_aborted;
  j["local_ba_reduced"] = m.local_ba_reduced;
  j["local_ba_skipped_waiting"] = m.local_ba_skipped_waiting;
  j["local_ba_skipped_budget"] = m.local_ba_skipped_budget;
  j["local_ba_iterations"] = m.local_ba_iterations;
  j["cpu_budget_balance_ms"] = m.budget_balance_ms;
  j["cpu_budget_lowest_balance_ms"] = m.budget_lowest_ms;
  j["mapping_cpu_ms_mean"] = m.keyframes ? m.mapping_cpu_ms_total / m.keyframes : 0.0;
  j["local_ba_cpu_ms_mean"] = m.local_ba_runs ? m.local_ba_cpu_ms_total / m.local_ba_runs : 0.0;
  j["local_ba_ms_mean"] = m.local_ba_runs ? m.local_ba_ms_total / m.local_ba_runs : 0.0;
  j["mapping_ms_mean"] = m.keyframes ? m.mapping_ms_total / m.keyframes : 0.0;
  j["culled_keyframes"] = m.culled_keyframes;
  j["evicted_keyframes"] = m.evicted_keyframes;
  j["pose_updates"] = m.pose_updates;
  j["triangulated_points"] = m.triangulated_points;
  j["culled_points"] = m.culled_points;
  j["fused_points"] = m.fused_points;
  j["depth_alignments"] = m.depth_alignments;
  j["depth_alignments_failed"] = m.depth_alignments_failed;
  j["depth_alignment_ms_mean"] = m.keyframes ? m.depth_alignment_ms_total / m.keyframes : 0.0;
  j["rgbd_transmitted"] = m.rgbd_transmitted;
  ccmd::Json list = ccmd::Json::MakeArray();
  for (const auto& d : decisions) {
    ccmd::Json e;
    e["keyframe"] = d.keyframe.value();
    e["transmit"] = d.transmit;
    e["tracked_points"] = d.tracked_points;
    e["threshold"] = d.threshold;
    e["covering"] = d.covering;
    e["threshold_scale"] = d.request.threshold_scale;
    e["allowed"] = d.request.allow;
    ccmd::Json considered = ccmd::Json::MakeArray();
    for (const auto& [id, w] : d.considered)
      considered.Push(ccmd::Json(ccmd::Json::Array{id.value(), w}));
    e["considered"] = considered;
    list.Push(e);
  }
  j["rgbd_decisions"] = list;
  j["rgbd_decisions_not_recorded"] = m.rgbd_decisions_not_recorded;
  return j;
}

// A budget or a slow link can need minutes to deliver what is queued: wait as long as the
// server keeps acknowledging, and give up only after `stall_s` without progress.
ccmd::Status FlushWhileProgressing(ccmd::AgentLink* link, double stall_s) {
  std::uint64_t acked = link->stats().acked;
  ccmd::Stopwatch since_progress;
  while (true) {
    const double left = stall_s - since_progress.ElapsedSeconds();
    const ccmd::Status s = link->Flush(std::max(0.0, std::min(left, 5.0)));
    if (s.ok() || s.code() != ccmd::StatusCode::kTimeout) return s;
    const std::uint64_t now_acked = link->stats().acked;
    if (now_acked > acked) {
      acked = now_acked;
      since_progress.Restart();
    } else if (since_progress.ElapsedSeconds() >= stall_s) {
      return s;
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "CCMD agent: ORB RGB-D visual odometry on a robot. Sends compact keyframes to a "
      "ccmd_server,\n"
      "or runs --offline and writes its trajectory (TUM format).\n"
      "Exit status: 0 when the server acknowledged every message, 3 when messages were refused\n"
      "or never acknowledged (the counts are printed and in --stats), 1 on any other error."};
  std::string source_spec, config_path, segment_spec, trajectory_path, keyframe_trajectory_path,
      stats_path, rate = "max", server, record_dir, name, psk_file, spill_dir, progress_path;
  double flush_timeout = 120.0, budget_kBps = 0,
         max_queue_s = ccmd::BandwidthBudgetOptions{}.max_queue_s, threshold_scale = 1.0;
  ccmd::RgbdEncodeOptions rgbd;
  bool offline = false, synchronous = false, asynchronous = false, rgbd_every_keyframe = false;
  double cpu_budget = 1.0;
  int max_frames = 0, record_compression = 1;
  app.add_option("--source", source_spec,
                 "Frame source: tum:DIR (TUM layout), synth[:frames=N,seed=S,...]")
      ->required();
  app.add_option("--config", config_path,
                 "YAML config: camera (Camera.fx, ..., DepthMapFactor) and tracking options; "
                 "default: the dataset's camera.yaml or one guessed from its name");
  app.add_option("--segment", segment_spec, "Replay only segment i of k (split replay), e.g. 2/3");
  app.add_flag("--offline", offline, "Run without a server");
  app.add_option("--server", server, "Server address HOST:PORT");
  app.add_option("--name", name,
                 "This agent's name at the server (default: host name and process id)");
  app.add_option("--psk-file", psk_file,
                 "Pre-shared key file (else $CCMD_PSK; none: loopback servers only)");
  app.add_option(
      "--spill-dir", spill_dir,
      "Folder for messages not yet acknowledged beyond the memory limit, and for this agent's "
      "identity file: keep it to reconnect under the same --name after a restart "
      "(default: a folder in /tmp)");
  app.add_option("--flush-timeout", flush_timeout,
                 "At the end, wait for the server's acknowledgements as long as they keep coming; "
                 "give up after "
                 "this many seconds without one")
      ->capture_default_str();
  app.add_option("--rgbd-downsample", rgbd.downsample,
                 "RGB-D sampling: 1, 2 or 4 (r = 1, 0.5, 0.25)")
      ->check(CLI::IsMember({1, 2, 4}))
      ->capture_default_str();
  app.add_option("--jpeg-quality", rgbd.jpeg_quality, "Colour JPEG quality")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--depth-bound", rgbd.bound_e4,
                 "Depth error bound in 1/10000 of depth (ccmd-bounded); default: the config's "
                 "Link.depthBound, else 50")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_flag("--rgbd-every-keyframe", rgbd_every_keyframe,
               "Send RGB-D data with every keyframe (covisibility selection off; for comparisons)");
  app.add_option(
         "--rgbd-threshold-scale", threshold_scale,
         "Multiply the RGB-D selection's thresholds (S_min): below 1 fewer keyframes send RGB-D")
      ->check(CLI::Range(0.05, 20.0))
      ->capture_default_str();
  app.add_option(
         "--bandwidth-budget", budget_kBps,
         "Keep to KB_PER_S kilobytes (1000 bytes) per second: keyframe geometry always goes, the "
         "RGB-D "
         "selection and coding adapt to the budget and to what the link acknowledges, and the "
         "connection is paced at the budget (0: no budget)")
      ->check(CLI::NonNegativeNumber);
  app.add_option(
         "--max-queue", max_queue_s,
         "With a budget: seconds of unacknowledged data beyond which keyframes go without RGB-D")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--progress", progress_path, "Rewrite a small progress JSON about once a second");
  app.add_option("--trajectory", trajectory_path,
                 "Write every tracked frame's pose (TUM format; of the camera the config's "
                 "Trajectory.camera names, colour by default) at the end; the agent keeps 40 "
                 "bytes a frame for it until then");
  app.add_option("--keyframe-trajectory", keyframe_trajectory_path,
                 "Write keyframe poses (TUM format)");
  app.add_option("--stats", stats_path, "Write run statistics as JSON");
  app.add_option("--rate", rate, "Replay pace: realtime (the dataset's timestamps) or max")
      ->check(CLI::IsMember({"realtime", "max"}))
      ->capture_default_str();
  app.add_option("--max-frames", max_frames, "Stop after this many frames (0: all)");
  app.add_option(
      "--record", record_dir,
      "Also write the frames to DIR in the TUM layout (rgb/, depth/, rgb.txt, depth.txt, "
      "camera.yaml), to replay and evaluate the run later");
  app.add_option("--record-png-compression", record_compression, "PNG level for --record (0-9)")
      ->check(CLI::Range(0, 9))
      ->capture_default_str();
  auto* synchronous_flag = app.add_flag(
      "--synchronous", synchronous,
      "Run local mapping in the tracking thread: each keyframe is mapped before the next frame "
      "(deterministic). The default for --offline runs on a recording at --rate max");
  app.add_flag("--asynchronous", asynchronous,
               "Run local mapping on its own thread beside tracking, as with a live camera or a "
               "server (the default there)")
      ->excludes(synchronous_flag);
  app.add_option(
         "--cpu-budget", cpu_budget,
         "CPU cores the agent may use on average (0: no limit; overrides Tracking.cpuBudget). "
         "Local mapping shrinks its bundle adjustment when over; a replay is paced to it")
      ->check(CLI::Range(0.0, 256.0))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  ccmd::ConfigureAllocatorForLongRuns();  // resident memory that follows the live data

  if (!offline && server.empty()) {
    return Fail("give --server HOST:PORT, or --offline to run without a server");
  }
  if (offline && !server.empty()) return Fail("--offline and --server exclude each other");
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);

  ccmd::SourceOptions source_options;
  source_options.configs_dir = ccmd::app::ConfigDir();
  source_options.camera_config = config_path;
  if (!segment_spec.empty()) {
    auto segment = ccmd::ParseSegmentSpec(segment_spec);
    if (!segment.ok()) return Fail(segment.status().message());
    source_options.segment = *segment;
  }
  // Live cameras come wrapped so that an unplugged camera is reopened with backoff while the
  // agent keeps its map and keeps sending.
  auto source = ccmd::OpenSourceWithRetry(source_spec, source_options);
  if (!source.ok()) return Fail(source.status().ToString());
  const ccmd::PinholeCamera camera = (*source)->camera();

  ccmd::TrackingOptions tracking;
  // A recording processed offline as fast as it can has nothing to keep up with: mapping each
  // keyframe before the next frame is deterministic (the same recording gives the same
  // trajectory) and, under the CPU budget, no slower than two threads taking turns. A live
  // camera, a paced replay or a server session maps beside tracking, as a robot does.
  tracking.synchronous_mapping =
      synchronous || (!asynchronous && offline && !(*source)->IsLive() && rate == "max");
  CCMD_LOG(INFO) << "local mapping "
                 << (tracking.synchronous_mapping ? "in the tracking thread (deterministic)"
                                                  : "on its own thread");
  tracking.cpu_budget = cpu_budget;
  // A recording's config gives the tracking and sensor options with its camera, whether it was
  // given, is the folder's camera.yaml or is the shipped one the folder's name points to.
  config_path = ccmd::SourceConfigPath(source_spec, source_options);
  if (!config_path.empty()) {
    CCMD_LOG(INFO) << "tracking options from " << config_path;
    auto config = ccmd::ConfigFile::Open(config_path);
    if (!config.ok()) return Fail(config.status().ToString());
    auto options = ccmd::ReadTrackingOptions(*config, tracking);
    if (!options.ok()) return Fail(options.status().ToString());
    tracking = *options;
    // The depth codec's error bound belongs to the sensor (about its noise), so a config may
    // set it; --depth-bound on the command line wins.
    if (app.count("--depth-bound") == 0) {
      auto bound = config->GetInt("Link.depthBound", rgbd.bound_e4);
      if (!bound.ok()) return Fail(bound.status().ToString());
      if (*bound < 1 || *bound > 1000)
        return Fail(config_path + ": Link.depthBound must be in 1..1000");
      rgbd.bound_e4 = *bound;
    }
  }
  if (app.count("--cpu-budget")) tracking.cpu_budget = cpu_budget;
  // A recording mapped in the tracking thread keeps to the budget by its pace alone (one
  // thread uses at most one core, and the pacer below waits under a smaller budget).
  tracking.mapping_follows_budget = !tracking.synchronous_mapping || (*source)->IsLive();
  // Frame records and removed keyframes' poses are needed only for the trajectory files;
  // without them nothing in the agent's memory grows with the frames, however long the mission.
  tracking.record_trajectory = !trajectory_path.empty() || !keyframe_trajectory_path.empty();
  ccmd::UseOpenCvThreadsForBudget(tracking.cpu_budget);
  if (rgbd_every_keyframe) tracking.rgbd_selection.enabled = false;
  if (threshold_scale != 1.0) {
    ccmd::RgbdSelectionOptions& s = tracking.rgbd_selection;
    s.threshold_ratio = std::min(1.0, s.threshold_ratio * threshold_scale);
    s.threshold_min_points =
        static_cast<int>(std::lround(s.threshold_min_points * threshold_scale));
    s.min_threshold = static_cast<int>(std::lround(s.min_threshold * threshold_scale));
  }
  if (budget_kBps > 0 && offline) return Fail("--bandwidth-budget needs a server (not --offline)");
  std::unique_ptr<ccmd::TumRecorder> recorder;
  if (!record_dir.empty()) {
    ccmd::TumRecorderOptions record_options;
    record_options.png_compression = record_compression;
    // Live cameras must not stall tracking: encode on a writer thread behind a queue.
    record_options.queue_frames = 16;
    record_options.drop_when_full = (*source)->IsLive();
    // The recording replays with this sensor's depth noise and frame depth weight, as without
    // them the agent would take the defaults (a Kinect's) for a folder read without --config.
    record_options.config_keys = ccmd::DepthNoiseConfigKeys(tracking.depth_noise);
    if (tracking.frame_depth_weight > 0) {
      record_options.config_keys +=
          "Tracking.frameDepthWeight: " + ccmd::ExactNumber(tracking.frame_depth_weight) + "\n";
    }
    auto created = ccmd::TumRecorder::Create(record_dir, camera, record_options);
    if (!created.ok()) return Fail(created.status().ToString());
    recorder = std::move(created).value();
  }
  // The link to the server: messages are kept (in memory, then on disk) until the server
  // has stored them, and resent after reconnections.
  std::unique_ptr<ccmd::AgentLink> link;
  std::unique_ptr<ccmd::LinkSink> sink;
  if (!offline) {
    ccmd::AgentLinkOptions link_options;
    link_options.server = server;
    link_options.name = name.empty() ? ccmd::DefaultAgentName() : name;
    link_options.camera = ccmd::SessionFromCamera(camera);
    // The server weighs this agent's keypoint depths with the sensor's noise model.
    link_options.camera.depth_sigma0 = tracking.depth_noise.sigma_0;
    link_options.camera.depth_sigma2 = tracking.depth_noise.sigma_2;
    // The server's trajectories of this agent give the same camera's poses as its own.
    ccmd::SetSessionTrajectoryCamera((*source)->T_color_trajectory(), &link_options.camera);
    auto psk = ccmd::ResolvePsk(psk_file);
    if (!psk.ok()) return Fail(psk.status().ToString());
    link_options.psk = *psk;
    link_options.spill_dir =
        spill_dir.empty() ? "/tmp/ccmd_agent_spill_" + link_options.name : spill_dir;
    link_options.max_send_bytes_per_s = budget_kBps * 1e3;
    std::unique_ptr<ccmd::BandwidthBudget> budget;
    if (budget_kBps > 0) {
      ccmd::BandwidthBudgetOptions budget_options;
      budget_options.budget_bytes_per_s = budget_kBps * 1e3;
      budget_options.max_queue_s = max_queue_s;
      if (const ccmd::Status s = budget_options.Validate(); !s.ok()) return Fail(s.ToString());
      ccmd::LogOptions("budget", budget_options);
      int default_level = 0;
      auto ladder = ccmd::DefaultBudgetLadder(rgbd, &default_level);
      budget =
          std::make_unique<ccmd::BandwidthBudget>(budget_options, std::move(ladder), default_level);
    }
    auto created = ccmd::AgentLink::Create(link_options);
    if (!created.ok()) return Fail(created.status().ToString());
    link = std::move(created).value();
    if (ccmd::Status s = rgbd.Validate(); !s.ok()) return Fail(s.message());
    sink = std::make_unique<ccmd::LinkSink>(link.get(), rgbd, std::move(budget));
    ccmd::SetLogTag(link_options.name);
    CCMD_LOG(INFO) << "sending to " << server << " as '" << link_options.name << "'";
    ccmd::LogOptions("link", link_options);
    ccmd::LogOptions("rgbd", rgbd);
  }
  auto frontend = ccmd::Frontend::Create(camera, tracking, sink.get());
  if (!frontend.ok()) return Fail(frontend.status().ToString());

  CCMD_LOG(INFO) << "source: " << (*source)->Describe();
  CCMD_LOG(INFO) << "camera: " << camera.ToString();
  ccmd::LogOptions("source", source_options);
  ccmd::LogOptions("camera", camera);
  ccmd::LogOptions("tracking", tracking);
  const int total = (*source)->FrameCount();
  ccmd::app::Progress progress("frames");
  const ccmd::Stopwatch wall;
  const double cpu_start = ccmd::ProcessCpuTimeSeconds();
  // A live camera sets the pace itself; a replay is held to the CPU budget.
  ccmd::CpuPacer pacer((*source)->IsLive() ? 0.0 : tracking.cpu_budget);
  double first_timestamp = -1;
  int frames = 0;
  double last_progress = -1e9;
  ccmd::RgbdFrame frame;
  while (!g_stop) {
    const ccmd::Status status = (*source)->Read(&frame);
    if (status.code() == ccmd::StatusCode::kEndOfStream) break;
    if (status.code() == ccmd::StatusCode::kUnavailable) continue;  // camera away: retrying
    if (!status.ok()) return Fail(status.ToString());
    if (recorder) {
      const ccmd::Status recorded = recorder->Write(frame);
      if (!recorded.ok()) return Fail("recording: " + recorded.ToString());
    }
    if (rate == "realtime") {
      if (first_timestamp < 0) first_timestamp = frame.timestamp;
      const double due = frame.timestamp - first_timestamp;
      const double ahead = due - wall.ElapsedSeconds();
      if (ahead > 0) std::this_thread::sleep_for(std::chrono::duration<double>(ahead));  // pacing
    }
    pacer.Pace();
    (*frontend)->ProcessFrame(frame);
    ++frames;
    if (total > 0) progress.Update(frames, total);
    if (!progress_path.empty() && wall.ElapsedSeconds() - last_progress >= 1.0) {
      last_progress = wall.ElapsedSeconds();
      ccmd::Json p;
      p["frames"] = frames;
      p["total_frames"] = total;
      p["keyframes"] = (*frontend)->stats().keyframes;
      if (sink) p["link"] = sink->StatsJson(/*detailed=*/false);
      if (link) p["acked"] = link->stats().acked;
      ccmd::WriteJsonFile(p, progress_path).IgnoreError();
    }
    if (max_frames > 0 && frames >= max_frames) break;
  }
  (*frontend)->Finish();
  ccmd::Json link_json;
  int exit_code = 0;
  if (link) {
    // Everything must reach the server before the agent goes away.
    const ccmd::Status flushed = FlushWhileProgressing(link.get(), flush_timeout);
    const ccmd::AgentLinkStats ls = link->stats();
    link_json = sink->StatsJson();
    link_json["acked"] = ls.acked;
    link_json["unacked"] = ls.unacked;
    link_json["refused"] = ls.refused;
    link_json["resent"] = ls.resent;
    link_json["sessions"] = ls.sessions;
    link_json["spilled"] = ls.spilled;
    link_json["bytes_sent"] = ls.bytes_sent;
    link_json["auth_failures"] = ls.auth_failures;
    link_json["link_error"] = link->status().ok() ? "" : link->status().ToString();
    link->Close();
    std::printf("sent %llu keyframes (%.1f kB each) and %llu pose updates; %llu acknowledged\n",
                static_cast<unsigned long long>(link_json["keyframes_sent"].number()),
                link_json["keyframe_bytes_mean"].number() / 1e3,
                static_cast<unsigned long long>(link_json["pose_updates_sent"].number()),
                static_cast<unsigned long long>(ls.acked));
    if (ls.unacked > 0 || ls.refused > 0 || !flushed.ok()) {
      // Not everything the agent produced is stored at the server: say so, and fail.
      std::fprintf(stderr,
                   "ccmd_agent: %llu messages not acknowledged by the server and %llu refused "
                   "by the link: %s\n",
                   static_cast<unsigned long long>(ls.unacked),
                   static_cast<unsigned long long>(ls.refused),
                   flushed.ok() ? "(see the log)" : flushed.ToString().c_str());
      exit_code = kExitMessagesLost;
    }
  }
  if (recorder) {
    const ccmd::Trajectory gt = (*source)->GroundTruth();
    if (!gt.empty()) recorder->WriteGroundTruth(gt).IgnoreError();
    const ccmd::Status closed = recorder->Close();
    if (!closed.ok()) return Fail("recording: " + closed.ToString());
    std::printf("recorded %ld frames to %s (%ld dropped)\n", recorder->frames_written(),
                record_dir.c_str(), recorder->frames_dropped());
  }
  const double seconds = wall.ElapsedSeconds();
  const double cores = (ccmd::ProcessCpuTimeSeconds() - cpu_start) / std::max(seconds, 1e-9);
  const ccmd::FrontendStats stats = (*frontend)->stats();
  std::printf(
      "%d frames in %.1f s (%.1f fps, %.2f CPU cores), %d tracked, %d lost, %d keyframes (%d in "
      "map), "
      "%zu map points\n",
      stats.frames, seconds, stats.frames / std::max(seconds, 1e-9), cores, stats.tracked_frames,
      stats.lost_frames, stats.keyframes, stats.map_keyframes, stats.map_points);
  const ccmd::MappingStats& m = stats.mapping;
  if (stats.restarts > 0) {
    std::printf(
        "tracking restarted %d time(s) in a new map segment after it could not relocalise\n",
        stats.restarts);
  }
  if (m.local_ba_reduced + m.local_ba_skipped_budget > 0) {
    std::printf("CPU budget %.2f cores: %d local BAs reduced and %d skipped to stay within it\n",
                tracking.cpu_budget, m.local_ba_reduced, m.local_ba_skipped_budget);
  }
  const std::string camera_note =
      (*source)->T_color_trajectory().isApprox(ccmd::Pose::Identity(), 1e-12)
          ? ""
          : ", the depth camera's: the config's Trajectory.camera";
  if (!trajectory_path.empty()) {
    const ccmd::Status s = ccmd::WriteTumTrajectory(
        ccmd::TrajectoryOfCamera((*frontend)->FrameTrajectory(), (*source)->T_color_trajectory()),
        trajectory_path, "ccmd_agent frame trajectory (T_world_cam" + camera_note + ")");
    if (!s.ok()) return Fail(s.ToString());
  }
  if (!keyframe_trajectory_path.empty()) {
    const ccmd::Status s = ccmd::WriteTumTrajectory(
        ccmd::TrajectoryOfCamera((*frontend)->KeyframeTrajectory(),
                                 (*source)->T_color_trajectory()),
        keyframe_trajectory_path, "ccmd_agent keyframes (T_world_cam" + camera_note + ")");
    if (!s.ok()) return Fail(s.ToString());
  }
  if (!stats_path.empty()) {
    ccmd::Json json = StatsJson(stats, seconds, (*frontend)->decisions());
    json["cpu_budget"] = tracking.cpu_budget;
    json["synchronous_mapping"] = tracking.synchronous_mapping;
    json["cpu_cores_used"] = cores;
    json["paced_ms"] = pacer.paced_ms();
    if (link) json["link"] = link_json;
    const ccmd::Status s = ccmd::WriteJsonFile(json, stats_path);
    if (!s.ok()) return Fail(s.ToString());
  }
  return exit_code;
}
