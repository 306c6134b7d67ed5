// ccmd_frontend_bench: measures the agent front-end on a sequence with ground truth.
//  - accuracy: ATE RMSE of our trajectory, and of OpenCV's cv::rgbd::RgbdOdometry chained
//    frame to frame on the same frames (the reference, measured in the same run);
//  - speed: frames per second of the whole front-end (tracking + local mapping, frames
//    preloaded so that decoding files does not count) and the per-stage split;
//  - footprint (--footprint): resident memory and frame time per window of a long run.

#include <CLI/CLI.hpp>
#include <cstdio>
#include <fstream>
#include <opencv2/imgproc.hpp>
#include <opencv2/rgbd.hpp>
#include <sstream>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/config.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/tracking/config.h"
#include "libccmd/tracking/cpu_budget.h"
#include "libccmd/tracking/depth_consistency.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/util/json.h"
#include "libccmd/util/timer.h"
#include "tests/bench_frontend/speed_bench.h"

namespace {

using namespace ccmd;

double ResidentMegabytes() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  }
  return 0;
}

double ProcessCpuSeconds() { return static_cast<double>(std::clock()) / CLOCKS_PER_SEC; }

Trajectory RgbdOdometryTrajectory(const std::vector<RgbdFrame>& frames, const PinholeCamera& camera,
                                  double* ms_per_frame) {
  const cv::Mat K =
      (cv::Mat_<float>(3, 3) << camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
  cv::Ptr<cv::rgbd::RgbdOdometry> odometry = cv::rgbd::RgbdOdometry::create(K);
  Trajectory trajectory;
  Pose T_world_cam = Pose::Identity();
  cv::Mat previous_gray, previous_depth;
  const Stopwatch watch;
  for (const RgbdFrame& f : frames) {
    cv::Mat gray, depth;
    cv::cvtColor(f.bgr, gray, cv::COLOR_BGR2GRAY);
    f.depth_mm.convertTo(depth, CV_32F, 1e-3);
    if (!previous_gray.empty()) {
      cv::Mat Rt;
      // Rt maps points of the previous frame into the current one: T_current_previous.
      if (odometry->compute(previous_gray, previous_depth, cv::Mat(), gray, depth, cv::Mat(), Rt)) {
        Eigen::Matrix4d M;
        for (int r = 0; r < 4; ++r) {
          for (int c = 0; c < 4; ++c) M(r, c) = Rt.at<double>(r, c);
        }
        Pose T_current_previous(M);
        T_world_cam = T_world_cam * T_current_previous.inverse();
      }  // on failure keep the previous pose (constant position), as a chained odometry would
    }
    trajectory.push_back({f.timestamp, T_world_cam});
    previous_gray = gray;
    previous_depth = depth;
  }
  *ms_per_frame = frames.empty() ? 0 : watch.ElapsedMillis() / frames.size();
  return trajectory;
}

// Which of the loaded frames a run uses, and in which order: other parts of one recording
// (sub-ranges, every n-th frame, played backwards) check that a figure is not particular to
// one stretch of frames.
struct FrameOrder {
  int first = 0;  // frames skipped at the start
  int step = 1;   // every step-th frame from there
  int count = 0;  // at most this many of those (0: all)
  bool reverse = false;
  // Frames to read from the source for this selection (0: all).
  int FramesNeeded() const { return count > 0 ? first + (count - 1) * step + 1 : 0; }
};

// Applies `order` to `frames`. Frames are renumbered in their new order (the tracker counts
// frames between keyframes by index); timestamps stay, so the ground truth still matches.
std::vector<RgbdFrame> ReorderFrames(std::vector<RgbdFrame> frames, const FrameOrder& order) {
  std::vector<RgbdFrame> out;
  for (std::size_t i = order.first; i < frames.size(); i += order.step) {
    if (order.count > 0 && static_cast<int>(out.size()) == order.count) break;
    out.push_back(std::move(frames[i]));
  }
  if (order.reverse) std::reverse(out.begin(), out.end());
  for (std::size_t i = 0; i < out.size(); ++i) out[i].index = static_cast<int>(i);
  return out;
}

// Reads the frames `order` selects from `source`, in that order.
std::vector<RgbdFrame> ReadFrames(RgbdSource& source, const FrameOrder& order) {
  std::vector<RgbdFrame> frames;
  RgbdFrame frame;
  const int needed = order.FramesNeeded();
  while ((needed == 0 || static_cast<int>(frames.size()) < needed) && source.Read(&frame).ok()) {
    frames.push_back(frame);
  }
  return ReorderFrames(std::move(frames), order);
}

// Parses "FIRST-LAST" (0-based, inclusive) into `range`.
bool ParseRange(const std::string& text, std::pair<int, int>* range) {
  int first = 0, last = 0;
  char dash = 0, extra = 0;
  std::istringstream in(text);
  if (!(in >> first >> dash >> last) || dash != '-' || in >> extra || first < 0 || last < first)
    return false;
  *range = {first, last};
  return true;
}

// The colour of frames `range` (in the order played) replaced by its mean: no features, the
// depth kept, as a camera facing a blank wall, or smeared by a fast turn, records it.
void BlankColour(std::vector<RgbdFrame>* frames, std::pair<int, int> range) {
  for (int i = range.first; i <= range.second && i < static_cast<int>(frames->size()); ++i) {
    cv::Mat& bgr = (*frames)[i].bgr;
    bgr = cv::Mat(bgr.size(), bgr.type(), cv::mean(bgr));
  }
}

// How far the tracked motion between frames `gap` apart is from what their depth alone says
// (MeasureDepthConsistency): needs no ground truth, so a camera setting can be chosen by it.
void ReportDepthConsistency(const std::vector<RgbdFrame>& frames, const Trajectory& trajectory,
                            const PinholeCamera& camera, const TrackingOptions& tracking, int gap,
                            Json* result) {
  DepthConsistencyOptions options;
  options.gap = gap;
  options.UseSensorOf(tracking);
  const auto consistency = MeasureDepthConsistency(frames, trajectory, camera, options);
  if (!consistency) {
    std::printf("  depth consistency: no pair of frames %d apart could be aligned\n", gap);
    return;
  }
  constexpr double kDegrees = 180.0 / M_PI;
  std::printf(
      "  depth consistency (frames %d apart, %d pairs aligned, %d not): tracked motion against "
      "the depth's own, median %.2f mm, %.3f deg\n",
      gap, consistency->pairs, consistency->failed, consistency->translation_median_m * 1e3,
      consistency->rotation_median_rad * kDegrees);
  (*result)["depth_consistency_pairs"] = consistency->pairs;
  (*result)["depth_consistency_translation_median_m"] = consistency->translation_median_m;
  (*result)["depth_consistency_translation_mean_m"] = consistency->translation_mean_m;
  (*result)["depth_consistency_rotation_median_deg"] = consistency->rotation_median_rad * kDegrees;
  (*result)["depth_consistency_rotation_mean_deg"] = consistency->rotation_mean_rad * kDegrees;
}

// OpenCV RgbdOdometry on the same frames, the in-run reference. The plain keys give it on the
// frames as the dataset records them, with the camera's published intrinsics: what it is given
// without a calibration, and the reference the front-end's accuracy target names. When the config
// registers depth to colour (a Depth block), it also runs on the registered frames the front-end
// gets (`*_registered` keys), a stronger reference on such recordings.
struct ReferenceRun {
  const std::string& source_spec;
  const SourceOptions& source_options;
  const std::string& config_path;
  const PinholeCamera& camera;  // the front-end's camera (registered frames: the colour camera)
  const FrameOrder& order;
  const Trajectory& ground_truth;
  const Pose& T_color_trajectory;
  const std::string& trajectory_path;  // where to write the registered (or only) run's poses
};

void ReportReference(const Trajectory& ground_truth, const Trajectory& reference, double ms,
                     double our_rmse, const std::string& suffix, const char* what, Json* result) {
  const auto ate = ComputeAte(ground_truth, reference);
  if (!ate.ok()) {
    std::printf("OpenCV RgbdOdometry %s: no ATE (%s)\n", what, ate.status().ToString().c_str());
    return;
  }
  (*result)["rgbd_odometry" + suffix + "_ate_rmse_m"] = ate->error.rmse;
  (*result)["rgbd_odometry" + suffix + "_ms_per_frame"] = ms;
  if (our_rmse > 0) (*result)["ate_ratio_to_rgbd_odometry" + suffix] = our_rmse / ate->error.rmse;
  std::printf(
      "OpenCV RgbdOdometry %s frame to frame: ATE rmse %.4f m, %.1f ms/frame; ratio "
      "ours/baseline %.3f\n",
      what, ate->error.rmse, ms, our_rmse > 0 ? our_rmse / ate->error.rmse : 0.0);
}

// `frames` are the front-end's (registered) frames; they are released before the frames as
// recorded are read, so that one copy of the sequence is in memory at a time.
void RunReference(const ReferenceRun& run, double our_rmse, std::vector<RgbdFrame>* frames,
                  Json* result) {
  const auto registration = run.config_path.empty()
                                ? StatusOr<std::optional<DepthToColorCalibration>>(std::nullopt)
                                : LoadDepthToColorCalibration(run.config_path);
  const bool registered = registration.ok() && registration->has_value();
  double ms = 0;
  const Trajectory same_frames =
      TrajectoryOfCamera(RgbdOdometryTrajectory(*frames, run.camera, &ms), run.T_color_trajectory);
  if (!run.trajectory_path.empty())
    WriteTumTrajectory(same_frames, run.trajectory_path).IgnoreError();
  if (!registered) {
    ReportReference(run.ground_truth, same_frames, ms, our_rmse, "", "on the same frames,", result);
    return;
  }
  ReportReference(run.ground_truth, same_frames, ms, our_rmse, "_registered",
                  "on the registered frames,", result);
  SourceOptions raw_options = run.source_options;
  raw_options.register_depth = false;
  auto raw_source = OpenSource(run.source_spec, raw_options);
  if (!raw_source.ok()) {
    std::printf("OpenCV RgbdOdometry on the frames as recorded: cannot open them (%s)\n",
                raw_source.status().ToString().c_str());
    return;
  }
  frames->clear();
  // The same frames in the same order as the front-end's (--first, --step, --reverse).
  const std::vector<RgbdFrame> raw_frames = ReadFrames(**raw_source, run.order);
  double raw_ms = 0;
  // The frames as recorded are the depth camera's (its intrinsics for both images).
  const Trajectory raw = RgbdOdometryTrajectory(raw_frames, (*registration)->depth, &raw_ms);
  ReportReference(run.ground_truth, raw, raw_ms, our_rmse, "",
                  "on the frames as recorded, depth intrinsics,", result);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Front-end benchmark: ATE against ground truth and OpenCV RgbdOdometry, speed, footprint."};
  std::string source_spec, config_path, json_path, trajectory_path, baseline_path, stage = "all";
  int max_frames = 0, consistency_gap = 10;
  bool skip_baseline = false, synchronous = false, footprint = false;
  double cpu_budget = 0;
  app.add_option("--source", source_spec, "tum:DIR or synth:frames=N,...")->required();
  app.add_option("--config", config_path, "Camera/tracking config");
  app.add_option("--frames", max_frames, "Use at most this many frames (after --first and --step)");
  app.add_option("--json", json_path, "Write the results as JSON");
  app.add_option("--trajectory", trajectory_path, "Write our frame trajectory (TUM format)");
  app.add_option("--baseline-trajectory", baseline_path,
                 "Write RgbdOdometry's trajectory (TUM format)");
  app.add_flag("--skip-baseline", skip_baseline, "Do not run RgbdOdometry");
  app.add_flag("--synchronous", synchronous, "Local mapping in the tracking thread");
  FrameOrder order;
  app.add_option("--first", order.first, "Skip this many frames at the start")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--step", order.step, "Use every n-th frame (from --first)")
      ->check(CLI::PositiveNumber);
  app.add_flag("--reverse", order.reverse, "Play the selected frames backwards");
  std::string blank;
  app.add_option("--blank", blank,
                 "FIRST-LAST: replace these frames' colour (0-based, in the order played) by its "
                 "mean, as a blank wall or a fast turn gives it (no features; depth kept)");
  app.add_option("--depth-consistency", consistency_gap,
                 "After the run, align the depth of frames this many apart and report how far "
                 "the tracked motion is from it (no ground truth needed; 0: off)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_flag("--footprint", footprint,
               "Stream frames (no preloading) and print memory and frame time every 300 frames");
  app.add_option(
         "--cpu-budget", cpu_budget,
         "CPU cores the front-end may use (as ccmd_agent --cpu-budget; the replay is paced to it)")
      ->check(CLI::Range(0.0, 256.0))
      ->capture_default_str();
  app.add_option(
         "--stage", stage,
         "What to run: all; frontend (the front-end only, e.g. under callgrind); extract (ORB "
         "extraction alone, ours and OpenCV's)")
      ->check(CLI::IsMember({"all", "frontend", "extract"}))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  std::pair<int, int> blank_range{-1, -1};
  if (!blank.empty() && (footprint || !ParseRange(blank, &blank_range))) {
    std::fprintf(stderr, "--blank needs FIRST-LAST (0-based, FIRST <= LAST) and no --footprint\n");
    return 2;
  }
  if (stage == "frontend") skip_baseline = true;
  // OpenCV in the calling thread, as the agent runs it on a budget, so that each stage's CPU
  // time (and instruction count under callgrind) is all its own.
  cv::setNumThreads(1);

  SourceOptions source_options;
  source_options.camera_config = config_path;
  source_options.configs_dir = CCMD_CONFIG_DIR;
  auto source = OpenSource(source_spec, source_options);
  if (!source.ok()) {
    std::fprintf(stderr, "%s\n", source.status().ToString().c_str());
    return 1;
  }
  const PinholeCamera camera = (*source)->camera();
  TrackingOptions options;
  config_path = SourceConfigPath(source_spec, source_options);  // as ccmd_agent reads it
  if (!config_path.empty()) {
    auto config = ConfigFile::Open(config_path);
    if (!config.ok()) return 1;
    auto read = ReadTrackingOptions(*config, options);
    if (!read.ok()) {
      std::fprintf(stderr, "%s\n", read.status().ToString().c_str());
      return 1;
    }
    options = *read;
  }
  options.synchronous_mapping = synchronous;
  options.cpu_budget = cpu_budget;
  const Trajectory ground_truth = (*source)->GroundTruth();
  auto frontend = Frontend::Create(camera, options, nullptr);
  if (!frontend.ok()) return 1;

  Json result;
  result["source"] = (*source)->Describe();
  std::vector<RgbdFrame> frames;
  double wall = 0, cpu = 0;
  if (footprint) {
    // Streaming: frames are rendered/read as they go; per-window statistics.
    Json windows = Json::MakeArray();
    Stopwatch window_watch;
    RgbdFrame frame;
    int n = 0;
    double window_frontend_ms = 0;
    const Stopwatch total;
    while ((*source)->Read(&frame).ok() && (max_frames == 0 || n < max_frames)) {
      const Stopwatch step;
      (*frontend)->ProcessFrame(frame);
      window_frontend_ms += step.ElapsedMillis();
      if (++n % 300 == 0) {
        const FrontendStats s = (*frontend)->stats();
        Json w;
        w["frames"] = n;
        w["rss_mb"] = ResidentMegabytes();
        w["frontend_ms_per_frame"] = window_frontend_ms / 300;
        w["map_keyframes"] = s.map_keyframes;
        w["map_points"] = s.map_points;
        w["cpu_seconds"] = ProcessCpuSeconds();
        std::printf(
            "frames %5d  rss %7.1f MB  front-end %6.2f ms/frame  map %3d keyframes %6zu points\n",
            n, w["rss_mb"].number(), window_frontend_ms / 300, s.map_keyframes, s.map_points);
        std::fflush(stdout);
        windows.Push(w);
        window_frontend_ms = 0;
      }
    }
    (*frontend)->Finish();
    wall = total.ElapsedSeconds();
    result["windows"] = windows;
  } else {
    order.count = max_frames;
    frames = ReadFrames(**source, order);
    if (blank_range.first >= 0) BlankColour(&frames, blank_range);
    if (stage != "frontend") {
      // Alone, three alternating passes; before a whole run, one.
      const bench::ExtractionSpeed extraction =
          bench::MeasureExtraction(frames, options.orb, stage == "extract" ? 3 : 1, true);
      bench::Print(extraction);
      result["extraction"] = bench::ToJson(extraction);
      if (stage == "extract")
        return json_path.empty() || WriteJsonFile(result, json_path).ok() ? 0 : 1;
    }
    const double cpu0 = ProcessCpuSeconds();
    const Stopwatch watch;
    CpuPacer pacer(cpu_budget);
    for (const RgbdFrame& f : frames) {
      pacer.Pace();
      (*frontend)->ProcessFrame(f);
    }
    (*frontend)->Finish();
    wall = watch.ElapsedSeconds();
    cpu = ProcessCpuSeconds() - cpu0;
  }
  const FrontendStats stats = (*frontend)->stats();
  // Poses of the camera the ground truth gives (the config's Trajectory.camera).
  const Pose T_color_trajectory = (*source)->T_color_trajectory();
  Trajectory ours = TrajectoryOfCamera((*frontend)->FrameTrajectory(), T_color_trajectory);
  // Played backwards, the trajectory is in reverse time order; evaluation matches by time.
  std::sort(ours.begin(), ours.end(),
            [](const auto& a, const auto& b) { return a.timestamp < b.timestamp; });
  const double fps = stats.frames / std::max(wall, 1e-9);
  result["frames"] = stats.frames;
  result["tracked_frames"] = stats.tracked_frames;
  result["lost_frames"] = stats.lost_frames;
  result["depth_only_frames"] = stats.depth_only_frames;
  result["motion_model_misses"] = stats.motion_model_misses;
  result["keyframes"] = stats.keyframes;
  result["fps"] = fps;
  result["sensor_fps"] = camera.fps;
  result["realtime_factor"] = fps / camera.fps;
  result["cpu_cores_used"] = wall > 0 ? cpu / wall : 0;
  result["extract_ms_mean"] = stats.extract_ms_total / std::max(1, stats.frames);
  result["track_ms_mean"] = stats.track_ms_total / std::max(1, stats.frames);
  result["local_ba_ms_mean"] = stats.mapping.local_ba_runs
                                   ? stats.mapping.local_ba_ms_total / stats.mapping.local_ba_runs
                                   : 0.0;
  result["mapping_ms_mean"] =
      stats.mapping.keyframes ? stats.mapping.mapping_ms_total / stats.mapping.keyframes : 0.0;
  std::printf("%s\n", (*source)->Describe().c_str());
  std::printf(
      "ccmd front-end: %d frames, %d tracked (%d by depth alone), %d lost, %d keyframes, %.1f fps "
      "(%.2fx real time)\n",
      stats.frames, stats.tracked_frames, stats.depth_only_frames, stats.lost_frames,
      stats.keyframes, fps, fps / camera.fps);
  std::printf(
      "  per frame: extraction %.2f ms, tracking %.2f ms; per keyframe: mapping %.1f ms (local BA "
      "%.1f ms)\n",
      result["extract_ms_mean"].number(), result["track_ms_mean"].number(),
      result["mapping_ms_mean"].number(), result["local_ba_ms_mean"].number());
  result["depth_alignments"] = stats.mapping.depth_alignments;
  result["depth_alignments_failed"] = stats.mapping.depth_alignments_failed;
  result["depth_alignment_ms_mean"] =
      stats.mapping.keyframes ? stats.mapping.depth_alignment_ms_total / stats.mapping.keyframes
                              : 0.0;
  result["triangulated_points"] = stats.mapping.triangulated_points;
  result["local_ba_runs"] = stats.mapping.local_ba_runs;
  result["local_ba_iterations"] = stats.mapping.local_ba_iterations;
  result["culled_points"] = stats.mapping.culled_points;
  bench::ReportStages(stats, &result);
  std::printf("  points: %d triangulated without depth, %d new points culled\n",
              stats.mapping.triangulated_points, stats.mapping.culled_points);
  std::printf("  depth alignment: %d accepted, %d rejected, %.1f ms per keyframe\n",
              stats.mapping.depth_alignments, stats.mapping.depth_alignments_failed,
              result["depth_alignment_ms_mean"].number());
  if (consistency_gap > 0 && !frames.empty() && stage != "frontend") {
    ReportDepthConsistency(frames, (*frontend)->FrameTrajectory(), camera, options, consistency_gap,
                           &result);
  }
  if (!trajectory_path.empty()) WriteTumTrajectory(ours, trajectory_path).IgnoreError();
  if (!ground_truth.empty()) {
    auto ate = ComputeAte(ground_truth, ours);
    if (ate.ok()) {
      result["ate_rmse_m"] = ate->error.rmse;
      result["ate_max_m"] = ate->error.max;
      std::printf("  ATE rmse %.4f m (max %.4f m, %zu poses)\n", ate->error.rmse, ate->error.max,
                  ate->matched);
    }
    // The keyframes alone, as local mapping left them: what the server receives.
    const auto keyframe_ate = ComputeAte(
        ground_truth, TrajectoryOfCamera((*frontend)->KeyframeTrajectory(), T_color_trajectory));
    if (keyframe_ate.ok()) {
      result["keyframe_ate_rmse_m"] = keyframe_ate->error.rmse;
      std::printf("  keyframes alone: ATE rmse %.4f m (%zu keyframes)\n", keyframe_ate->error.rmse,
                  keyframe_ate->matched);
    }
    if (!skip_baseline && !frames.empty()) {
      const ReferenceRun reference{source_spec, source_options, config_path,        camera,
                                   order,       ground_truth,   T_color_trajectory, baseline_path};
      RunReference(reference, ate.ok() ? ate->error.rmse : 0.0, &frames, &result);
    }
  }
  if (!json_path.empty()) {
    const Status s = WriteJsonFile(result, json_path);
    if (!s.ok()) {
      std::fprintf(stderr, "%s\n", s.ToString().c_str());
      return 1;
    }
  }
  return 0;
}
