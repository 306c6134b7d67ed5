// ccmd_agent: the robot side. Runs the ORB RGB-D front-end on a source (dataset, synthetic,
// camera) and sends compact keyframes to a ccmd_server, or runs offline and writes its
// trajectory.

#include <unistd.h>

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

// A SIGINT/SIGTERM while frames are read asks for a clean stop: the frames read so far are
// finished, sent and acknowledged, and the results written. Once the agent is stopping (a
// signal came, or the source ended), one ends it at once with status 128 + the signal, for
// when that stop waits on a server that is gone.
std::atomic<bool> g_stopping{false};
void OnSignal(int sig) {
  if (!g_stopping.exchange(true)) return;
  static const char kMessage[] =
      "\nccmd_agent: stop signal while stopping: exiting now; what the server has not "
      "acknowledged and the trajectory are not kept\n";
  (void)!::write(STDERR_FILENO, kMessage, sizeof(kMessage) - 1);
  ::_exit(128 + sig);
}

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
  j["depth_only_frames"] = s.depth_only_frames;
  j["depth_noise_ratio"] = s.depth_noise_ratio;
  j["depth_fit_sigmas"] = s.mapping.depth_fit_sigmas;
  j["restarts"] = s.restarts;
  j["motion_model_misses"] = s.motion_model_misses;
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

// Everything the command line sets.
struct AgentArgs {
  std::string source_spec, config_path, segment_spec, trajectory_path, keyframe_trajectory_path,
      stats_path, rate = "max", server, record_dir, name, psk_file, spill_dir, progress_path;
  double flush_timeout = 120.0, budget_kBps = 0,
         max_queue_s = ccmd::BandwidthBudgetOptions{}.max_queue_s, threshold_scale = 1.0;
  ccmd::RgbdEncodeOptions rgbd;
  bool offline = false, synchronous = false, asynchronous = false, rgbd_every_keyframe = false;
  double cpu_budget = 1.0;
  int max_frames = 0, record_compression = 1;
  // Given on the command line (they override the config's values).
  bool depth_bound_given = false, cpu_budget_given = false;
};

void AddOptions(CLI::App* app, AgentArgs* a) {
  app->add_option("--source", a->source_spec,
                  "Frame source: tum:DIR (TUM layout), synth[:frames=N,seed=S,...]")
      ->required();
  app->add_option("--config", a->config_path,
                  "YAML config: camera (Camera.fx, ..., DepthMapFactor) and tracking options; "
                  "default: the dataset's camera.yaml or one guessed from its name");
  app->add_option("--segment", a->segment_spec,
                  "Replay only segment i of k (split replay), e.g. 2/3");
  app->add_flag("--offline", a->offline, "Run without a server");
  app->add_option("--server", a->server, "Server address HOST:PORT");
  app->add_option("--name", a->name,
                  "This agent's name at the server (default: host name and process id)");
  app->add_option("--psk-file", a->psk_file,
                  "Pre-shared key file (else $CCMD_PSK; none: loopback servers only)");
  app->add_option(
      "--spill-dir", a->spill_dir,
      "Folder for messages not yet acknowledged beyond the memory limit, and for this agent's "
      "identity file: keep it to reconnect under the same --name after a restart "
      "(default: a folder in /tmp)");
  app->add_option("--flush-timeout", a->flush_timeout,
                  "At the end, wait for the server's acknowledgements as long as they keep "
                  "coming; give up after this many seconds without one")
      ->capture_default_str();
  app->add_option("--rgbd-downsample", a->rgbd.downsample,
                  "RGB-D sampling: 1, 2 or 4 (r = 1, 0.5, 0.25)")
      ->check(CLI::IsMember({1, 2, 4}))
      ->capture_default_str();
  app->add_option("--jpeg-quality", a->rgbd.jpeg_quality, "Colour JPEG quality")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app->add_option("--depth-bound", a->rgbd.bound_e4,
                  "Depth error bound in 1/10000 of depth (ccmd-bounded); default: the config's "
                  "Link.depthBound, else 50")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app->add_flag(
      "--rgbd-every-keyframe", a->rgbd_every_keyframe,
      "Send RGB-D data with every keyframe (covisibility selection off; for comparisons)");
  app->add_option(
         "--rgbd-threshold-scale", a->threshold_scale,
         "Multiply the RGB-D selection's thresholds (S_min): below 1 fewer keyframes send RGB-D")
      ->check(CLI::Range(0.05, 20.0))
      ->capture_default_str();
  app->add_option("--bandwidth-budget", a->budget_kBps,
                  "Keep to KB_PER_S kilobytes (1000 bytes) per second: keyframe geometry always "
                  "goes, the RGB-D selection and coding adapt to the budget and to what the link "
                  "acknowledges, and the connection is paced at the budget (0: no budget)")
      ->check(CLI::NonNegativeNumber);
  app->add_option(
         "--max-queue", a->max_queue_s,
         "With a budget: seconds of unacknowledged data beyond which keyframes go without RGB-D")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app->add_option("--progress", a->progress_path,
                  "Rewrite a small progress JSON about once a second");
  app->add_option("--trajectory", a->trajectory_path,
                  "Write every tracked frame's pose (TUM format; of the camera the config's "
                  "Trajectory.camera names, colour by default) at the end; the agent keeps 40 "
                  "bytes a frame for it until then");
  app->add_option("--keyframe-trajectory", a->keyframe_trajectory_path,
                  "Write keyframe poses (TUM format)");
  app->add_option("--stats", a->stats_path, "Write run statistics as JSON");
  app->add_option("--rate", a->rate, "Replay pace: realtime (the dataset's timestamps) or max")
      ->check(CLI::IsMember({"realtime", "max"}))
      ->capture_default_str();
  app->add_option("--max-frames", a->max_frames, "Stop after this many frames (0: all)");
  app->add_option(
      "--record", a->record_dir,
      "Also write the frames to DIR in the TUM layout (rgb/, depth/, rgb.txt, depth.txt, "
      "camera.yaml), to replay and evaluate the run later");
  app->add_option("--record-png-compression", a->record_compression, "PNG level for --record (0-9)")
      ->check(CLI::Range(0, 9))
      ->capture_default_str();
  auto* synchronous_flag = app->add_flag(
      "--synchronous", a->synchronous,
      "Run local mapping in the tracking thread: each keyframe is mapped before the next frame "
      "(deterministic). The default for --offline runs on a recording at --rate max");
  app->add_flag("--asynchronous", a->asynchronous,
                "Run local mapping on its own thread beside tracking, as with a live camera or a "
                "server (the default there)")
      ->excludes(synchronous_flag);
  app->add_option(
         "--cpu-budget", a->cpu_budget,
         "CPU cores the agent may use on average (0: no limit; overrides Tracking.cpuBudget). "
         "Local mapping shrinks its bundle adjustment when over; a replay is paced to it")
      ->check(CLI::Range(0.0, 256.0))
      ->capture_default_str();
}

// The tracking options: the defaults, then the recording's config, then the command line. The
// config may also set the depth codec's error bound (into a->rgbd) and names the config used
// (into a->config_path).
ccmd::StatusOr<ccmd::TrackingOptions> ReadTracking(AgentArgs* a,
                                                   const ccmd::SourceOptions& source_options,
                                                   const ccmd::RgbdSource& source) {
  ccmd::TrackingOptions tracking;
  // A recording processed offline as fast as it can has nothing to keep up with: mapping each
  // keyframe before the next frame is deterministic (the same recording gives the same
  // trajectory) and, under the CPU budget, no slower than two threads taking turns. A live
  // camera, a paced replay or a server session maps beside tracking, as a robot does.
  tracking.synchronous_mapping =
      a->synchronous || (!a->asynchronous && a->offline && !source.IsLive() && a->rate == "max");
  CCMD_LOG(INFO) << "local mapping "
                 << (tracking.synchronous_mapping ? "in the tracking thread (deterministic)"
                                                  : "on its own thread");
  tracking.cpu_budget = a->cpu_budget;
  // A recording's config gives the tracking and sensor options with its camera, whether it was
  // given, is the folder's camera.yaml or is the shipped one the folder's name points to.
  a->config_path = ccmd::SourceConfigPath(a->source_spec, source_options);
  if (!a->config_path.empty()) {
    CCMD_LOG(INFO) << "tracking options from " << a->config_path;
    CCMD_ASSIGN_OR_RETURN(const ccmd::ConfigFile config, ccmd::ConfigFile::Open(a->config_path));
    CCMD_ASSIGN_OR_RETURN(tracking, ccmd::ReadTrackingOptions(config, tracking));
    // The depth codec's error bound belongs to the sensor (about its noise), so a config may
    // set it; --depth-bound on the command line wins.
    if (!a->depth_bound_given) {
      CCMD_ASSIGN_OR_RETURN(const int bound, config.GetInt("Link.depthBound", a->rgbd.bound_e4));
      if (bound < 1 || bound > 1000)
        return ccmd::InvalidArgument(a->config_path + ": Link.depthBound must be in 1..1000");
      a->rgbd.bound_e4 = bound;
    }
  }
  if (a->cpu_budget_given) tracking.cpu_budget = a->cpu_budget;
  // A recording mapped in the tracking thread keeps to the budget by its pace alone (one
  // thread uses at most one core, and the pacer below waits under a smaller budget).
  tracking.mapping_follows_budget = !tracking.synchronous_mapping || source.IsLive();
  // Frame records and removed keyframes' poses are needed only for the trajectory files;
  // without them nothing in the agent's memory grows with the frames, however long the mission.
  tracking.record_trajectory = !a->trajectory_path.empty() || !a->keyframe_trajectory_path.empty();
  if (a->rgbd_every_keyframe) tracking.rgbd_selection.enabled = false;
  if (a->threshold_scale != 1.0) {
    ccmd::RgbdSelectionOptions& s = tracking.rgbd_selection;
    s.threshold_ratio = std::min(1.0, s.threshold_ratio * a->threshold_scale);
    s.threshold_min_points =
        static_cast<int>(std::lround(s.threshold_min_points * a->threshold_scale));
    s.min_threshold = static_cast<int>(std::lround(s.min_threshold * a->threshold_scale));
  }
  return tracking;
}

// --record: the frames written in the TUM layout as they are read.
ccmd::StatusOr<std::unique_ptr<ccmd::TumRecorder>> OpenRecorder(
    const AgentArgs& a, const ccmd::PinholeCamera& camera, const ccmd::TrackingOptions& tracking,
    bool live) {
  ccmd::TumRecorderOptions record_options;
  record_options.png_compression = a.record_compression;
  // Live cameras must not stall tracking: encode on a writer thread behind a queue.
  record_options.queue_frames = 16;
  record_options.drop_when_full = live;
  // The recording replays with this sensor's depth noise, frame depth weight and rolling
  // shutter, as without them the agent would take the defaults (a Kinect's, a global shutter)
  // for a folder read without --config.
  record_options.config_keys = ccmd::DepthNoiseConfigKeys(tracking.depth_noise);
  if (tracking.frame_depth_weight > 0) {
    record_options.config_keys +=
        "Tracking.frameDepthWeight: " + ccmd::ExactNumber(tracking.frame_depth_weight) + "\n";
  }
  if (tracking.rolling_shutter_readout > 0) {
    record_options.config_keys +=
        "Camera.rollingShutterReadout: " + ccmd::ExactNumber(tracking.rolling_shutter_readout) +
        "\n";
  }
  return ccmd::TumRecorder::Create(a.record_dir, camera, record_options);
}

// The link to the server: messages are kept (in memory, then on disk) until the server has
// stored them, and resent after reconnections; the sink codes the front-end's output for it,
// under the bandwidth budget if one is set.
ccmd::Status OpenLink(const AgentArgs& a, const ccmd::PinholeCamera& camera,
                      const ccmd::TrackingOptions& tracking, const ccmd::Pose& T_color_trajectory,
                      std::unique_ptr<ccmd::AgentLink>* link,
                      std::unique_ptr<ccmd::LinkSink>* sink) {
  ccmd::AgentLinkOptions link_options;
  link_options.server = a.server;
  link_options.name = a.name.empty() ? ccmd::DefaultAgentName() : a.name;
  link_options.camera = ccmd::SessionFromCamera(camera);
  // The server weighs this agent's keypoint depths with the sensor's noise model.
  link_options.camera.depth_sigma0 = tracking.depth_noise.sigma_0;
  link_options.camera.depth_sigma2 = tracking.depth_noise.sigma_2;
  // The server's trajectories of this agent give the same camera's poses as its own.
  ccmd::SetSessionTrajectoryCamera(T_color_trajectory, &link_options.camera);
  CCMD_ASSIGN_OR_RETURN(link_options.psk, ccmd::ResolvePsk(a.psk_file));
  link_options.spill_dir =
      a.spill_dir.empty() ? "/tmp/ccmd_agent_spill_" + link_options.name : a.spill_dir;
  link_options.max_send_bytes_per_s = a.budget_kBps * 1e3;
  std::unique_ptr<ccmd::BandwidthBudget> budget;
  if (a.budget_kBps > 0) {
    ccmd::BandwidthBudgetOptions budget_options;
    budget_options.budget_bytes_per_s = a.budget_kBps * 1e3;
    budget_options.max_queue_s = a.max_queue_s;
    CCMD_RETURN_IF_ERROR(budget_options.Validate());
    ccmd::LogOptions("budget", budget_options);
    int default_level = 0;
    auto ladder = ccmd::DefaultBudgetLadder(a.rgbd, &default_level);
    budget =
        std::make_unique<ccmd::BandwidthBudget>(budget_options, std::move(ladder), default_level);
  }
  CCMD_ASSIGN_OR_RETURN(*link, ccmd::AgentLink::Create(link_options));
  CCMD_RETURN_IF_ERROR(a.rgbd.Validate());
  *sink = std::make_unique<ccmd::LinkSink>(link->get(), a.rgbd, std::move(budget));
  ccmd::SetLogTag(link_options.name);
  CCMD_LOG(INFO) << "sending to " << a.server << " as '" << link_options.name << "'";
  ccmd::LogOptions("link", link_options);
  ccmd::LogOptions("rgbd", a.rgbd);
  return ccmd::Status::Ok();
}

// The frame loop: read, record, pace, track, report progress; until the source ends, a signal,
// or --max-frames.
ccmd::Status RunFrames(const AgentArgs& a, ccmd::RgbdSource* source, ccmd::TumRecorder* recorder,
                       ccmd::Frontend* frontend, const ccmd::LinkSink* sink,
                       const ccmd::AgentLink* link, const ccmd::Stopwatch& wall,
                       ccmd::CpuPacer* pacer) {
  const int total = source->FrameCount();
  ccmd::app::Progress progress("frames");
  double first_timestamp = -1;
  int frames = 0;
  double last_progress = -1e9;
  ccmd::RgbdFrame frame;
  while (!g_stopping) {
    const ccmd::Status status = source->Read(&frame);
    if (status.code() == ccmd::StatusCode::kEndOfStream) break;
    if (status.code() == ccmd::StatusCode::kUnavailable) continue;  // camera away: retrying
    CCMD_RETURN_IF_ERROR(status);
    if (recorder) {
      CCMD_RETURN_IF_ERROR(recorder->Write(frame).WithContext("recording"));
    }
    if (a.rate == "realtime") {
      if (first_timestamp < 0) first_timestamp = frame.timestamp;
      const double due = frame.timestamp - first_timestamp;
      const double ahead = due - wall.ElapsedSeconds();
      if (ahead > 0) std::this_thread::sleep_for(std::chrono::duration<double>(ahead));  // pacing
    }
    pacer->Pace();
    frontend->ProcessFrame(frame);
    ++frames;
    if (total > 0) progress.Update(frames, total);
    if (!a.progress_path.empty() && wall.ElapsedSeconds() - last_progress >= 1.0) {
      last_progress = wall.ElapsedSeconds();
      ccmd::Json p;
      p["frames"] = frames;
      p["total_frames"] = total;
      p["keyframes"] = frontend->stats().keyframes;
      if (sink) p["link"] = sink->StatsJson(/*detailed=*/false);
      if (link) p["acked"] = link->stats().acked;
      ccmd::WriteJsonFile(p, a.progress_path).IgnoreError();
    }
    if (a.max_frames > 0 && frames >= a.max_frames) break;
  }
  if (g_stopping) {
    std::printf(
        "stopping after %d frames: finishing the map%s and writing the results (a second "
        "Ctrl-C exits at once)\n",
        frames, link ? ", waiting for the server's acknowledgements," : "");
    std::fflush(stdout);
  }
  return ccmd::Status::Ok();
}

// Everything must reach the server before the agent goes away: waits for the
// acknowledgements, prints what was sent, and fills `link_json`. Returns the exit status: 0,
// or kExitMessagesLost when not everything the agent produced is stored at the server.
int FinishLink(const AgentArgs& a, ccmd::AgentLink* link, const ccmd::LinkSink& sink,
               ccmd::Json* link_json) {
  if (const std::uint64_t waiting = link->stats().unacked; waiting > 0) {
    std::printf("waiting for the server to acknowledge %llu messages (Ctrl-C exits at once)\n",
                static_cast<unsigned long long>(waiting));
    std::fflush(stdout);
  }
  const ccmd::Status flushed = FlushWhileProgressing(link, a.flush_timeout);
  const ccmd::AgentLinkStats ls = link->stats();
  ccmd::Json& j = *link_json;
  j = sink.StatsJson();
  j["acked"] = ls.acked;
  j["unacked"] = ls.unacked;
  j["refused"] = ls.refused;
  j["resent"] = ls.resent;
  j["sessions"] = ls.sessions;
  j["spilled"] = ls.spilled;
  j["bytes_sent"] = ls.bytes_sent;
  j["auth_failures"] = ls.auth_failures;
  j["link_error"] = link->status().ok() ? "" : link->status().ToString();
  link->Close();
  std::printf("sent %llu keyframes (%.1f kB each) and %llu pose updates; %llu acknowledged\n",
              static_cast<unsigned long long>(j["keyframes_sent"].number()),
              j["keyframe_bytes_mean"].number() / 1e3,
              static_cast<unsigned long long>(j["pose_updates_sent"].number()),
              static_cast<unsigned long long>(ls.acked));
  if (ls.unacked == 0 && ls.refused == 0 && flushed.ok()) return 0;
  std::fprintf(stderr,
               "ccmd_agent: %llu messages not acknowledged by the server and %llu refused "
               "by the link: %s\n",
               static_cast<unsigned long long>(ls.unacked),
               static_cast<unsigned long long>(ls.refused),
               flushed.ok() ? "(see the log)" : flushed.ToString().c_str());
  return kExitMessagesLost;
}

void PrintSummary(const ccmd::FrontendStats& stats, double seconds, double cores, double cpu_budget,
                  long dropped_frames) {
  std::printf(
      "%d frames in %.1f s (%.1f fps, %.2f CPU cores), %d tracked, %d lost, %d keyframes (%d in "
      "map), "
      "%zu map points\n",
      stats.frames, seconds, stats.frames / std::max(seconds, 1e-9), cores, stats.tracked_frames,
      stats.lost_frames, stats.keyframes, stats.map_keyframes, stats.map_points);
  const ccmd::MappingStats& m = stats.mapping;
  if (dropped_frames > 0) {
    std::printf("frames dropped by the source as damaged or unreadable: %ld (see the log)\n",
                dropped_frames);
  }
  if (stats.depth_only_frames > 0) {
    std::printf("%d of the tracked frames were placed by their depth alone (too few features)\n",
                stats.depth_only_frames);
  }
  if (stats.restarts > 0) {
    std::printf(
        "tracking restarted %d time(s) in a new map segment after it could not relocalise; "
        "each segment starts from the last tracked pose, so the trajectory jumps where one "
        "starts (a server places the segments against each other where their views meet)\n",
        stats.restarts);
  }
  if (m.local_ba_reduced + m.local_ba_skipped_budget > 0) {
    std::printf("CPU budget %.2f cores: %d local BAs reduced and %d skipped to stay within it\n",
                cpu_budget, m.local_ba_reduced, m.local_ba_skipped_budget);
  }
}

// --trajectory and --keyframe-trajectory, of the camera the config's Trajectory.camera names.
ccmd::Status WriteTrajectories(const AgentArgs& a, ccmd::Frontend* frontend,
                               const ccmd::Pose& T_color_trajectory) {
  const std::string camera_note = T_color_trajectory.isApprox(ccmd::Pose::Identity(), 1e-12)
                                      ? ""
                                      : ", the depth camera's: the config's Trajectory.camera";
  if (!a.trajectory_path.empty()) {
    CCMD_RETURN_IF_ERROR(ccmd::WriteTumTrajectory(
        ccmd::TrajectoryOfCamera(frontend->FrameTrajectory(), T_color_trajectory),
        a.trajectory_path, "ccmd_agent frame trajectory (T_world_cam" + camera_note + ")"));
  }
  if (!a.keyframe_trajectory_path.empty()) {
    CCMD_RETURN_IF_ERROR(ccmd::WriteTumTrajectory(
        ccmd::TrajectoryOfCamera(frontend->KeyframeTrajectory(), T_color_trajectory),
        a.keyframe_trajectory_path, "ccmd_agent keyframes (T_world_cam" + camera_note + ")"));
  }
  return ccmd::Status::Ok();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "CCMD agent: ORB RGB-D visual odometry on a robot. Sends compact keyframes to a "
      "ccmd_server,\n"
      "or runs --offline and writes its trajectory (TUM format).\n"
      "Exit status: 0 when the server acknowledged every message, 3 when messages were refused\n"
      "or never acknowledged (the counts are printed and in --stats), 1 on any other error.\n"
      "Ctrl-C (SIGINT, SIGTERM) stops cleanly: what was read is mapped, sent and written. Once\n"
      "the agent is stopping, Ctrl-C exits at once (status 128 + signal), keeping nothing unsent."};
  AgentArgs a;
  AddOptions(&app, &a);
  CLI11_PARSE(app, argc, argv);
  a.depth_bound_given = app.count("--depth-bound") > 0;
  a.cpu_budget_given = app.count("--cpu-budget") > 0;
  // The agent keeps glibc's own mmap threshold (the server fixes it, ccmd_server.cc): its
  // working set is the same few image-sized buffers every frame, which the heap reuses, where
  // a fixed 128 kB threshold mapped and faulted in fresh pages for each of them, every frame
  // (half the frame rate); its resident size stays flat either way
  // (docs/benchmarks/frontend.md#the-allocator).

  if (!a.offline && a.server.empty()) {
    return Fail("give --server HOST:PORT, or --offline to run without a server");
  }
  if (a.offline && !a.server.empty()) return Fail("--offline and --server exclude each other");
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);

  ccmd::SourceOptions source_options;
  source_options.configs_dir = ccmd::app::ConfigDir();
  source_options.camera_config = a.config_path;
  if (!a.segment_spec.empty()) {
    auto segment = ccmd::ParseSegmentSpec(a.segment_spec);
    if (!segment.ok()) return Fail(segment.status().message());
    source_options.segment = *segment;
  }
  // Live cameras come wrapped so that an unplugged camera is reopened with backoff while the
  // agent keeps its map and keeps sending.
  auto opened = ccmd::OpenSourceWithRetry(a.source_spec, source_options);
  if (!opened.ok()) return Fail(opened.status().ToString());
  const std::unique_ptr<ccmd::RgbdSource> source = std::move(opened).value();
  const ccmd::PinholeCamera camera = source->camera();
  const ccmd::Pose T_color_trajectory = source->T_color_trajectory();

  auto read_tracking = ReadTracking(&a, source_options, *source);
  if (!read_tracking.ok()) return Fail(read_tracking.status().ToString());
  const ccmd::TrackingOptions tracking = *read_tracking;
  ccmd::UseOpenCvThreadsForBudget(tracking.cpu_budget);
  if (a.budget_kBps > 0 && a.offline)
    return Fail("--bandwidth-budget needs a server (not --offline)");
  std::unique_ptr<ccmd::TumRecorder> recorder;
  if (!a.record_dir.empty()) {
    auto created = OpenRecorder(a, camera, tracking, source->IsLive());
    if (!created.ok()) return Fail(created.status().ToString());
    recorder = std::move(created).value();
  }
  std::unique_ptr<ccmd::AgentLink> link;
  std::unique_ptr<ccmd::LinkSink> sink;
  if (!a.offline) {
    const ccmd::Status opened_link =
        OpenLink(a, camera, tracking, T_color_trajectory, &link, &sink);
    if (!opened_link.ok()) return Fail(opened_link.ToString());
  }
  auto frontend = ccmd::Frontend::Create(camera, tracking, sink.get());
  if (!frontend.ok()) return Fail(frontend.status().ToString());

  CCMD_LOG(INFO) << "source: " << source->Describe();
  CCMD_LOG(INFO) << "camera: " << camera.ToString();
  ccmd::LogOptions("source", source_options);
  ccmd::LogOptions("camera", camera);
  ccmd::LogOptions("tracking", tracking);
  const ccmd::Stopwatch wall;
  const double cpu_start = ccmd::ProcessCpuTimeSeconds();
  // A live camera sets the pace itself; a replay is held to the CPU budget.
  ccmd::CpuPacer pacer(source->IsLive() ? 0.0 : tracking.cpu_budget);
  const ccmd::Status ran = RunFrames(a, source.get(), recorder.get(), frontend->get(), sink.get(),
                                     link.get(), wall, &pacer);
  // What was tracked before an error is still sent, summarised and written; the exit status
  // then says the run did not end as it should.
  if (!ran.ok()) Fail(ran.ToString() + " (stopped there; finishing with the frames read before)");
  g_stopping = true;  // from here on a stop signal ends the agent at once
  (*frontend)->Finish();
  ccmd::Json link_json;
  const int exit_code = link ? FinishLink(a, link.get(), *sink, &link_json) : 0;
  if (recorder) {
    const ccmd::Trajectory gt = source->GroundTruth();
    if (!gt.empty()) recorder->WriteGroundTruth(gt).IgnoreError();
    const ccmd::Status closed = recorder->Close();
    if (!closed.ok()) return Fail("recording: " + closed.ToString());
    std::printf("recorded %ld frames to %s (%ld dropped)\n", recorder->frames_written(),
                a.record_dir.c_str(), recorder->frames_dropped());
  }
  const double seconds = wall.ElapsedSeconds();
  const double cores = (ccmd::ProcessCpuTimeSeconds() - cpu_start) / std::max(seconds, 1e-9);
  const ccmd::FrontendStats stats = (*frontend)->stats();
  PrintSummary(stats, seconds, cores, tracking.cpu_budget, source->DroppedFrames());
  if (const ccmd::Status s = WriteTrajectories(a, frontend->get(), T_color_trajectory); !s.ok())
    return Fail(s.ToString());
  if (!a.stats_path.empty()) {
    ccmd::Json json = StatsJson(stats, seconds, (*frontend)->decisions());
    json["cpu_budget"] = tracking.cpu_budget;
    json["synchronous_mapping"] = tracking.synchronous_mapping;
    json["cpu_cores_used"] = cores;
    json["paced_ms"] = pacer.paced_ms();
    json["dropped_frames"] = source->DroppedFrames();
    const ccmd::ProcessUsage usage = ccmd::CurrentProcessUsage();
    json["peak_rss_mb"] = usage.peak_rss_mb;
    json["minor_page_faults"] = usage.minor_page_faults;
    if (link) json["link"] = link_json;
    const ccmd::Status s = ccmd::WriteJsonFile(json, a.stats_path);
    if (!s.ok()) return Fail(s.ToString());
  }
  return ran.ok() ? exit_code : 1;
}
