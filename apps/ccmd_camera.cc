// ccmd_camera: checks a depth camera before a mapping run, and records what it delivers.
//
//   ccmd_camera --list                                   V4L2 nodes and OpenNI2 devices, modes
//   ccmd_camera --source SPEC [--config FILE] [--frames N]        per-frame statistics
//   ccmd_camera --source SPEC --record DIR [--frames N|0]         TUM-layout recording
//   ccmd_camera --source tum:DIR --config FILE --check-registration  the Depth block's offset
//   ccmd_camera --source tum:DIR --config FILE --check-ground-truth  whose poses the truth gives
//   ccmd_camera --source SPEC [--config FILE] --check-noise [--frames N]  depth noise vs config
//   ccmd_camera --source tum:DIR [--config FILE] --check-shutter [--frames N]  rolling shutter
//
// SPEC is any source spec (openni2[:URI], v4l2:color=...,depth=..., tum:DIR, synth:...).
// Ctrl-C ends a recording cleanly: the current frame is finished and the lists closed.

#include <pthread.h>
#include <signal.h>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <thread>
#include <vector>

#include "apps/app_common.h"
#include "libccmd/codec/depth_downsample.h"
#include "libccmd/eval/depth_agreement.h"
#include "libccmd/io/tum_recorder.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/pixel_formats.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/tracking/config.h"
#include "libccmd/tracking/depth_noise_meter.h"
#include "libccmd/tracking/readout_check.h"
#ifdef CCMD_HAVE_OPENNI2
#include "libccmd/sensors/openni2_source.h"
#endif
#ifdef CCMD_HAVE_V4L2
#include "libccmd/sensors/v4l2_device.h"
#endif
#include "libccmd/util/options_writer.h"
#include "libccmd/util/timer.h"

namespace {

struct DepthStats {
  double valid_fraction = 0;
  int min_mm = 0;
  int median_mm = 0;
  int max_mm = 0;
};

DepthStats ComputeDepthStats(const cv::Mat& depth_mm) {
  std::vector<std::uint16_t> valid;
  valid.reserve(depth_mm.total());
  for (int y = 0; y < depth_mm.rows; ++y) {
    const std::uint16_t* row = depth_mm.ptr<std::uint16_t>(y);
    for (int x = 0; x < depth_mm.cols; ++x) {
      if (row[x] != 0) valid.push_back(row[x]);
    }
  }
  DepthStats stats;
  if (valid.empty()) return stats;
  stats.valid_fraction = static_cast<double>(valid.size()) / depth_mm.total();
  const auto [min, max] = std::minmax_element(valid.begin(), valid.end());
  stats.min_mm = *min;
  stats.max_mm = *max;
  std::nth_element(valid.begin(), valid.begin() + valid.size() / 2, valid.end());
  stats.median_mm = valid[valid.size() / 2];
  return stats;
}

int ListDevices() {
#ifdef CCMD_HAVE_V4L2
  std::printf("V4L2 video nodes:\n");
  const std::vector<std::string> nodes = ccmd::ListV4l2DeviceNodes();
  if (nodes.empty()) std::printf("  none (no /dev/video* nodes)\n");
  for (const std::string& path : nodes) {
    auto device = ccmd::OpenLinuxV4l2Device(path);
    if (!device.ok()) {
      std::printf("  %s  %s\n", path.c_str(), device.status().ToString().c_str());
      continue;
    }
    auto info = (*device)->Query();
    if (!info.ok()) {
      std::printf("  %s  %s\n", path.c_str(), info.status().ToString().c_str());
      continue;
    }
    std::printf("  %s  %s  \"%s\"  %s%s\n", path.c_str(), info->driver.c_str(), info->card.c_str(),
                info->bus.c_str(),
                info->streaming_capture ? "" : "  (not a capture node: metadata or output)");
    bool depth_node = false;
    for (const ccmd::V4l2Mode& mode : info->modes) {
      std::string rates;
      for (const double fps : mode.fps) {
        rates += ' ';
        rates += std::to_string(static_cast<int>(fps + 0.5));
      }
      std::printf("      %s %4dx%-4d fps:%s  (%s)\n", ccmd::FourccToString(mode.fourcc).c_str(),
                  mode.width, mode.height, rates.empty() ? " ?" : rates.c_str(),
                  mode.description.c_str());
      depth_node |= mode.fourcc == ccmd::kFourccZ16;
    }
    if (depth_node) std::printf("      -> depth node (Z16): use it as depth=%s\n", path.c_str());
  }
#else
  std::printf("V4L2: not in this build\n");
#endif

#ifdef CCMD_HAVE_OPENNI2
  std::printf("OpenNI2 devices:\n");
  auto devices = ccmd::ListOpenNI2Devices();
  if (!devices.ok()) {
    std::printf("  %s\n", devices.status().ToString().c_str());
  } else if (devices->empty()) {
    std::printf("  none\n");
  } else {
    for (const ccmd::OpenNI2DeviceInfo& d : *devices) {
      std::printf("  %s  %s %s  usb %04x:%04x  registration %s\n", d.uri.c_str(), d.vendor.c_str(),
                  d.name.c_str(), d.usb_vendor_id, d.usb_product_id,
                  d.registration_supported ? "yes" : "no");
      if (!d.open_status.ok()) std::printf("      %s\n", d.open_status.ToString().c_str());
      for (const ccmd::OpenNI2ModeInfo& m : d.modes) {
        std::printf("      %-6s %4dx%-4d @%d %s\n", m.sensor.c_str(), m.width, m.height, m.fps,
                    m.pixel_format.c_str());
      }
    }
  }
#else
  std::printf("OpenNI2: not in this build\n");
#endif
  return 0;
}

// SIGINT/SIGTERM are blocked in every thread and taken by one watcher thread with sigwait,
// so stopping needs no async-signal-safe tricks: the watcher sets the flag and cancels a
// reconnect wait in progress. The watcher also wakes on SIGUSR1, sent at normal exit.
class StopWatcher {
 public:
  explicit StopWatcher(std::function<void()> on_stop) : on_stop_(std::move(on_stop)) {
    sigemptyset(&signals_);
    sigaddset(&signals_, SIGINT);
    sigaddset(&signals_, SIGTERM);
    sigaddset(&signals_, SIGUSR1);
    pthread_sigmask(SIG_BLOCK, &signals_, nullptr);
    thread_ = std::thread([this] {
      int signal = 0;
      sigwait(&signals_, &signal);
      if (signal != SIGUSR1) {
        stopped_ = true;
        on_stop_();
      }
    });
  }
  ~StopWatcher() {
    pthread_kill(thread_.native_handle(), SIGUSR1);
    thread_.join();
  }
  bool stopped() const { return stopped_.load(); }

 private:
  sigset_t signals_;
  std::function<void()> on_stop_;
  std::atomic<bool> stopped_{false};
  std::thread thread_;
};

// A rig's checks read the config's Depth block and the frames as recorded (depth not
// registered: each check moves it itself). Prints why not and sets `exit_code` (2: no Depth
// block, 1: the source) when that fails.
struct RigSource {
  ccmd::DepthToColorCalibration calibration;
  std::unique_ptr<ccmd::RgbdSource> source;
};
std::optional<RigSource> OpenRigAsRecorded(const std::string& spec, const std::string& config,
                                           const char* check, const char* why, int* exit_code) {
  auto calibration = ccmd::LoadDepthToColorCalibration(config);
  if (!calibration.ok() || !calibration->has_value()) {
    std::fprintf(stderr, "ccmd_camera: %s needs a --config with a Depth block%s (%s)\n", check, why,
                 calibration.ok() ? "none found" : calibration.status().ToString().c_str());
    *exit_code = 2;
    return std::nullopt;
  }
  ccmd::SourceOptions options;
  options.camera_config = config;
  options.configs_dir = ccmd::app::ConfigDir();
  options.register_depth = false;
  auto opened = ccmd::OpenSource(spec, options);
  if (!opened.ok()) {
    std::fprintf(stderr, "ccmd_camera: %s\n", opened.status().ToString().c_str());
    *exit_code = 1;
    return std::nullopt;
  }
  return RigSource{**calibration, std::move(opened).value()};
}

// --check-registration: scores the config's depth-to-colour registration on recorded frames
// against the same registration with the depth camera moved sideways, so a wrong offset or
// its side shows up as a better score elsewhere (ccmd::EdgeAlignmentScore).
int CheckRegistration(const std::string& spec, const std::string& config, int frames) {
  int exit_code = 0;
  auto rig = OpenRigAsRecorded(spec, config, "--check-registration", "", &exit_code);
  if (!rig) return exit_code;
  const std::unique_ptr<ccmd::RgbdSource>& source = rig->source;
  // Frames spread over a recording (every `stride`-th), or the next ones from a live camera.
  const int total = source->FrameCount();
  const int stride = total > frames ? total / frames : 1;
  std::vector<ccmd::RgbdFrame> samples;
  ccmd::RgbdFrame frame;
  for (int i = 0; static_cast<int>(samples.size()) < frames && source->Read(&frame).ok(); ++i) {
    if (i % stride == 0) samples.push_back(frame);
  }
  if (samples.empty()) {
    std::fprintf(stderr, "ccmd_camera: no frames read\n");
    return 1;
  }
  const ccmd::DepthToColorCalibration& c = rig->calibration;
  const ccmd::PinholeCamera& color = source->camera();
  const Eigen::Vector3d t = c.T_color_depth.translation();
  std::printf(
      "registration check on %zu frames: mean colour gradient at depth edges (higher is better)\n",
      samples.size());
  double best_score = -1, best_dx = 0;
  for (int dx_mm = -50; dx_mm <= 50; dx_mm += 10) {
    ccmd::Pose T = c.T_color_depth;
    T.translation().x() += 1e-3 * dx_mm;
    double score = 0;
    for (const ccmd::RgbdFrame& f : samples) {
      const cv::Mat registered = ccmd::RegisterDepthToColor(f.depth_mm, c.depth, color, T);
      score += ccmd::EdgeAlignmentScore(f.bgr, registered);
    }
    score /= samples.size();
    std::printf("  t_color_depth.x %+6.3f m%s  score %6.2f\n", t.x() + 1e-3 * dx_mm,
                dx_mm == 0 ? " (config)" : "         ", score);
    if (score > best_score) {
      best_score = score;
      best_dx = 1e-3 * dx_mm;
    }
  }
  std::printf("best: t_color_depth.x %+.3f m (config %+.3f m)\n", t.x() + best_dx, t.x());
  return 0;
}

// --check-ground-truth: which camera of the rig the recording's ground-truth poses give. Depth
// of one frame is moved into a later one by the ground-truth motion, with the depth camera
// placed at s * t_color_depth in the frame the poses give: s = 0 if they are the depth camera's,
// s = 1 if the colour camera's. Where the view turns, the wrong choice moves the depth camera's
// centre by the rig's offset and the depths disagree more.
int CheckGroundTruth(const std::string& spec, const std::string& config) {
  int exit_code = 0;
  auto rig = OpenRigAsRecorded(spec, config, "--check-ground-truth",
                               ": with one imager there is one camera", &exit_code);
  if (!rig) return exit_code;
  const std::unique_ptr<ccmd::RgbdSource>& source = rig->source;
  const ccmd::Trajectory truth = source->GroundTruth();
  if (truth.empty()) {
    std::fprintf(stderr, "ccmd_camera: %s has no ground truth\n", source->Describe().c_str());
    return 1;
  }
  // Half-size depth (the keyframe codec's median: no mixed depths) of every 3rd frame with a
  // ground-truth pose.
  const ccmd::DepthToColorCalibration& c = rig->calibration;
  const ccmd::PinholeCamera depth_camera = c.depth.Resized(c.depth.width / 2, c.depth.height / 2);
  struct Sample {
    cv::Mat depth;
    ccmd::Pose T_world_pose;
  };
  std::vector<Sample> samples;
  ccmd::RgbdFrame frame;
  for (int i = 0; source->Read(&frame).ok(); ++i) {
    if (i % 3 != 0) continue;
    const auto pose = ccmd::InterpolateTrajectory(truth, frame.timestamp, 0.02);
    if (!pose || frame.depth_mm.cols != c.depth.width || frame.depth_mm.rows != c.depth.height)
      continue;
    auto half = ccmd::DownsampleDepth(frame.depth_mm, 2);
    if (!half.ok()) continue;
    samples.push_back({*half, *pose});
  }
  // Pairs whose view turned by 12-40 degrees: the rig's offset shows, the views still overlap.
  std::vector<std::pair<int, int>> pairs;
  for (int a = 0; a < static_cast<int>(samples.size()); ++a) {
    for (int b = a + 1; b < static_cast<int>(samples.size()) && b <= a + 40; ++b) {
      const double angle = Eigen::AngleAxisd(samples[a].T_world_pose.linear().transpose() *
                                             samples[b].T_world_pose.linear())
                               .angle() *
                           180 / M_PI;
      if (angle >= 12 && angle <= 40) pairs.push_back({a, b});
    }
  }
  if (pairs.empty()) {
    std::fprintf(stderr,
                 "ccmd_camera: no two frames whose view turned by 12-40 degrees: the ground truth "
                 "cannot tell the rig's cameras apart on this recording\n");
    return 1;
  }
  const int stride = std::max<int>(1, static_cast<int>(pairs.size()) / 300);
  const Eigen::Vector3d t = c.T_color_depth.translation();
  std::printf(
      "ground-truth check on %zu pairs of frames (view turned 12-40 degrees): depth moved from "
      "one frame into the other, median disagreement (lower is better), with the poses taken as "
      "those of a camera s x t_color_depth from the depth camera (s = 0: the depth camera, "
      "s = 1: the colour camera)\n",
      (pairs.size() + stride - 1) / stride);
  double best = 1e9, best_s = 0;
  for (const double s : {-1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0}) {
    ccmd::Pose T_pose_depth = ccmd::Pose::Identity();
    T_pose_depth.translation() = s * t;
    double sum = 0;
    int n = 0;
    for (std::size_t k = 0; k < pairs.size(); k += stride) {
      const Sample& a = samples[pairs[k].first];
      const Sample& b = samples[pairs[k].second];
      ccmd::DepthAgreementOptions agreement_options;
      agreement_options.step = 2;
      const ccmd::DepthAgreement agreement =
          ccmd::CompareDepthByGroundTruth(a.depth, b.depth, depth_camera, a.T_world_pose,
                                          b.T_world_pose, T_pose_depth, agreement_options);
      if (agreement.compared < 100) continue;
      sum += agreement.median_error;
      ++n;
    }
    const double mean = n > 0 ? sum / n : 1e9;
    const char* name = s == 0 ? "  the depth camera" : s == 1 ? "  the colour camera" : "";
    std::printf("  s %+4.1f  %6.2f mm%s\n", s, 1e3 * mean, name);
    if (mean < best) {
      best = mean;
      best_s = s;
    }
  }
  std::printf(
      "closest to the %s camera (best s %+.1f): Trajectory.camera: \"%s\" gives "
      "trajectories comparable with this ground truth\n",
      best_s < 0.5 ? "depth" : "colour", best_s, best_s < 0.5 ? "depth" : "colour");
  return 0;
}

// The depth-noise model of the config a source is opened with (the default without one).
ccmd::StatusOr<ccmd::DepthNoise> SourceDepthNoise(const std::string& spec,
                                                  const ccmd::SourceOptions& options) {
  const std::string path = ccmd::SourceConfigPath(spec, options);
  if (path.empty()) return ccmd::DepthNoise();
  CCMD_ASSIGN_OR_RETURN(const ccmd::ConfigFile file, ccmd::ConfigFile::Open(path));
  return ccmd::ReadDepthNoise(file);
}

// The tracking options of the config a source is opened with (the defaults without one).
ccmd::StatusOr<ccmd::TrackingOptions> SourceTrackingOptions(const std::string& spec,
                                                            const ccmd::SourceOptions& options) {
  const std::string path = ccmd::SourceConfigPath(spec, options);
  if (path.empty()) return ccmd::TrackingOptions();
  CCMD_ASSIGN_OR_RETURN(const ccmd::ConfigFile file, ccmd::ConfigFile::Open(path));
  return ccmd::ReadTrackingOptions(file);
}

int Fail(const ccmd::Status& status) {
  std::fprintf(stderr, "ccmd_camera: %s\n", status.ToString().c_str());
  return 1;
}

// --check-noise: the depth noise measured on the camera's frames (planar 8x8 blocks, see
// DepthNoiseMeter) against the config's DepthNoise model, per depth range, and the model's keys
// fitted to it. Frames spread over a recording, or the next ones from a live camera; depth as
// the imager gives it, not registered to colour.
int CheckNoise(const std::string& spec, const std::string& config, int frames) {
  ccmd::SourceOptions options;
  options.camera_config = config;
  options.configs_dir = ccmd::app::ConfigDir();
  // The depth imager's own pixels: registration to colour resamples them (the nearest of
  // several depths wins where they collide), which reads about 10 % less noise.
  options.register_depth = false;
  auto opened = ccmd::OpenSource(spec, options);
  if (!opened.ok()) return Fail(opened.status());
  const std::unique_ptr<ccmd::RgbdSource>& source = *opened;
  auto noise_model = SourceDepthNoise(spec, options);
  if (!noise_model.ok()) return Fail(noise_model.status());
  const ccmd::DepthNoise& model = *noise_model;
  const int total = source->FrameCount();
  const int stride = total > frames ? total / frames : 1;
  ccmd::DepthNoiseMeter meter;
  ccmd::RgbdFrame frame;
  for (int i = 0; meter.frames() < frames && source->Read(&frame).ok(); ++i) {
    if (i % stride == 0) meter.Add(frame.depth_mm);
  }
  const ccmd::DepthNoiseMeasurement m = meter.Measure();
  std::printf("depth noise on %d frames, %d planar 8x8 blocks with every depth\n", meter.frames(),
              m.blocks);
  if (!m.Enough()) {
    std::fprintf(stderr, "ccmd_camera: too few blocks with every depth to measure the noise\n");
    return 1;
  }
  std::printf("  depth m  blocks  measured mm  config mm  ratio\n");
  for (const ccmd::DepthNoiseBin& bin : m.bins) {
    std::printf("  %7.2f  %6d  %11.2f  %9.2f  %5.2f\n", bin.depth, bin.blocks, 1e3 * bin.sigma,
                1e3 * model.Sigma(bin.depth), bin.sigma / model.Sigma(bin.depth));
  }
  std::printf("measured / config: %.2f (1: the config describes this camera)\n", m.RatioTo(model));
  std::printf("fitted model (sigma0 + sigma2 z^2):\n%s",
              ccmd::DepthNoiseConfigKeys(m.fitted).c_str());
  return 0;
}

// --check-shutter: the colour camera's rolling-shutter readout read off a recording with no
// ground truth (ccmd::CheckReadout): its first frames tracked once per candidate readout, each
// run's motion held against the depth images' own.
int CheckShutter(const std::string& spec, const std::string& config, int frames,
                 const std::vector<double>& candidates_ms) {
  ccmd::SourceOptions options;
  options.camera_config = config;
  options.configs_dir = ccmd::app::ConfigDir();
  auto opened = ccmd::OpenSource(spec, options);
  if (!opened.ok()) return Fail(opened.status());
  const std::unique_ptr<ccmd::RgbdSource>& source = *opened;
  auto read = SourceTrackingOptions(spec, options);
  if (!read.ok()) return Fail(read.status());
  const ccmd::TrackingOptions& tracking = *read;
  std::vector<ccmd::RgbdFrame> loaded;
  ccmd::RgbdFrame frame;
  while (static_cast<int>(loaded.size()) < frames && source->Read(&frame).ok())
    loaded.push_back(frame);
  ccmd::ReadoutCheckOptions check;
  check.candidates.clear();
  for (double ms : candidates_ms) check.candidates.push_back(1e-3 * ms);
  std::printf(
      "rolling-shutter check on the first %zu frames: each readout tracked, and the\n"
      "tracked motion held against the depth images' own (smaller is better)\n",
      loaded.size());
  std::fflush(stdout);
  const auto result = ccmd::CheckReadout(
      loaded, source->camera(), tracking, check, [](const ccmd::ReadoutTrial& t) {
        const std::string lost =
            t.lost_frames ? ", " + std::to_string(t.lost_frames) + " frames lost" : "";
        if (t.consistency.pairs == 0) {
          std::printf("  readout %5.1f ms: no pair of frames aligned%s\n", 1e3 * t.readout,
                      lost.c_str());
        } else {
          std::printf(
              "  readout %5.1f ms: rotation %.4f deg, translation %.2f mm (medians over "
              "%d pairs)%s\n",
              1e3 * t.readout, t.consistency.rotation_median_rad * 180 / M_PI,
              1e3 * t.consistency.translation_median_m, t.consistency.pairs, lost.c_str());
        }
        std::fflush(stdout);
      });
  if (!result.ok()) return Fail(result.status());
  std::printf("pairs of frames %d apart (the camera turns about %.0f degrees between them)\n",
              result->gap, check.pair_rotation_deg);
  constexpr int kFewPairs = 20;
  if (result->trials.front().consistency.pairs < kFewPairs) {
    std::printf(
        "only %d pairs aligned at readout 0: too few to read a readout from; record "
        "more frames, or turns that keep the view on the same surfaces\n",
        result->trials.front().consistency.pairs);
    return 1;
  }
  if (!result->readout) {
    std::printf(
        "these frames do not show a readout (no candidate beats 0 by %.0f %%): keep "
        "Camera.rollingShutterReadout at %g (the config's), or record faster turns\n",
        100 * check.min_gain, tracking.rolling_shutter_readout);
  } else if (*result->readout == 0) {
    std::printf("best: a global shutter\nCamera.rollingShutterReadout: 0\n");
  } else {
    std::printf(
        "best: %.1f ms (between the candidates, the vertex of a parabola through the "
        "best three; candidates 5 ms apart around it narrow it down)\n"
        "Camera.rollingShutterReadout: %.4f\n",
        1e3 * *result->readout, *result->readout);
  }
  return 0;
}

struct CameraArgs {
  bool list = false, retry = false, check_registration = false, check_ground_truth = false;
  bool check_noise = false, check_shutter = false;
  std::vector<double> readouts_ms = {0, 10, 20, 30, 40};
  std::string spec, config, record;
  int frames = -1;  // -1: the default of the mode
  int every = 0;    // 0: the default of the mode
  int png_compression = 1;
};

void AddOptions(CLI::App* app, CameraArgs* a) {
  app->add_flag("--list", a->list, "List V4L2 nodes and OpenNI2 devices with their modes");
  app->add_option("--source", a->spec,
                  "Source: openni2[:URI], v4l2:color=DEV,depth=DEV[,...], tum:DIR, synth:...");
  app->add_option("--config", a->config,
                  "Camera config: mode and intrinsics (v4l2: also the depth imager, e.g. "
                  "configs/realsense_d435_v4l2.yaml)");
  app->add_option("--frames", a->frames,
                  "Frames to read (default 10; with --record 0 = until Ctrl-C)")
      ->check(CLI::NonNegativeNumber);
  app->add_option("--record", a->record, "Record to this folder in the TUM layout");
  app->add_option("--every", a->every,
                  "Print every K-th frame (default: every frame, 1 per second when recording)")
      ->check(CLI::NonNegativeNumber);
  app->add_flag("--retry", a->retry, "Reopen a live camera that goes away (backoff 0.5 s .. 8 s)");
  app->add_option("--png-compression", a->png_compression, "PNG level 0..9 for --record")
      ->check(CLI::Range(0, 9))
      ->capture_default_str();
  app->add_flag("--check-registration", a->check_registration,
                "Score the config's Depth block (depth-to-colour registration) on --frames frames "
                "(default 15, spread over a recording) against sideways offsets of -50..50 mm");
  app->add_flag("--check-ground-truth", a->check_ground_truth,
                "Tell which camera of the config's rig (Depth block) a recording's ground-truth "
                "poses give, from its depth alone: the value for the config's Trajectory.camera");
  app->add_flag("--check-noise", a->check_noise,
                "Measure the depth noise on --frames frames (default 30, spread over a recording) "
                "and compare it with the config's DepthNoise model");
  app->add_flag("--check-shutter", a->check_shutter,
                "Read the colour camera's rolling-shutter readout off a recording of hand-held "
                "turns (no ground truth): its first --frames frames (default 450) tracked with "
                "each of --readouts, against the depth images' own motion");
  app->add_option("--readouts", a->readouts_ms, "Candidate readouts in ms for --check-shutter")
      ->check(CLI::Range(0.0, 200.0))
      ->delimiter(',')
      ->capture_default_str();
}

// The recorder of --record: the sensor's depth noise from the config the camera was opened
// with travels with the recording, so that it replays without --config as it would with it.
ccmd::StatusOr<std::unique_ptr<ccmd::TumRecorder>> OpenRecorder(const CameraArgs& a,
                                                                const ccmd::SourceOptions& options,
                                                                const ccmd::PinholeCamera& camera) {
  ccmd::TumRecorderOptions recorder_options;
  recorder_options.png_compression = a.png_compression;
  recorder_options.queue_frames = 16;  // PNG encoding off the capture loop
  recorder_options.writer_threads = 2;
  CCMD_ASSIGN_OR_RETURN(const ccmd::DepthNoise noise, SourceDepthNoise(a.spec, options));
  recorder_options.config_keys = ccmd::DepthNoiseConfigKeys(noise);
  ccmd::LogOptions("record", recorder_options);
  return ccmd::TumRecorder::Create(a.record, camera, recorder_options);
}

// What the capture loop saw, for the summary line.
struct CaptureStats {
  int count = 0;
  double first_time = 0, last_time = 0;
  double min_interval = 1e9, max_interval = 0, valid_sum = 0;
};

// Reads frames until --frames, the end of a recording, a cancelled retry or a stop signal,
// printing every `every`-th and recording each; an error from the source or the recorder is
// printed and ends the loop with the returned failure.
ccmd::Status Capture(int frames, int every, ccmd::RgbdSource* source,
                     const std::atomic<ccmd::RetryingSource*>& retrying, const StopWatcher& watcher,
                     ccmd::TumRecorder* recorder, CaptureStats* out) {
  CaptureStats& c = *out;
  while ((frames == 0 || c.count < frames) && !watcher.stopped()) {
    ccmd::RgbdFrame frame;
    const ccmd::Status status = source->Read(&frame);
    if (status.code() == ccmd::StatusCode::kEndOfStream) break;
    if (status.code() == ccmd::StatusCode::kCancelled) break;
    if (status.code() == ccmd::StatusCode::kUnavailable && retrying.load() != nullptr) continue;
    if (!status.ok()) return status;
    const DepthStats stats = ComputeDepthStats(frame.depth_mm);
    const double interval = c.count > 0 ? frame.timestamp - c.last_time : 0;
    if (c.count == 0) c.first_time = frame.timestamp;
    if (c.count > 0) {
      c.min_interval = std::min(c.min_interval, interval);
      c.max_interval = std::max(c.max_interval, interval);
    }
    c.last_time = frame.timestamp;
    c.valid_sum += stats.valid_fraction;
    if (recorder) CCMD_RETURN_IF_ERROR(recorder->Write(frame));
    if (c.count % every == 0) {
      std::printf(
          "frame %d  t=%.6f s  dt=%5.1f ms  colour %dx%d  depth %dx%d  valid %5.1f%%  "
          "min %d  median %d  max %d mm\n",
          c.count, frame.timestamp, interval * 1e3, frame.bgr.cols, frame.bgr.rows,
          frame.depth_mm.cols, frame.depth_mm.rows, 100 * stats.valid_fraction, stats.min_mm,
          stats.median_mm, stats.max_mm);
      std::fflush(stdout);
    }
    ++c.count;
  }
  return ccmd::Status::Ok();
}

void PrintCaptureSummary(const CaptureStats& c, double wall_seconds, bool stopped, long dropped) {
  const double span = c.last_time - c.first_time;
  std::printf("%d frames over %.3f s of device time (%.3f s wall)", c.count, span, wall_seconds);
  if (c.count > 1 && span > 0) {
    std::printf(": %.2f fps, intervals %.1f..%.1f ms", (c.count - 1) / span, c.min_interval * 1e3,
                c.max_interval * 1e3);
  }
  if (c.count > 0) std::printf(", depth valid %.1f%% on average", 100 * c.valid_sum / c.count);
  std::printf("%s\n", stopped ? " (stopped by signal)" : "");
  if (dropped > 0) {
    std::printf("frames dropped by the source as damaged, unreadable or unpaired: %ld\n", dropped);
  }
}

// Writes the recording's ground truth (a replayed dataset's) and closes it; false when the
// recording could not be completed (printed).
bool CloseRecorder(ccmd::TumRecorder* recorder, const ccmd::RgbdSource& source,
                   const std::string& folder) {
  if (!source.GroundTruth().empty()) {
    const ccmd::Status gt = recorder->WriteGroundTruth(source.GroundTruth());
    if (!gt.ok()) std::fprintf(stderr, "ccmd_camera: %s\n", gt.ToString().c_str());
  }
  const ccmd::Status closed = recorder->Close();
  if (!closed.ok()) std::fprintf(stderr, "ccmd_camera: %s\n", closed.ToString().c_str());
  std::printf("recorded %ld frames to %s", recorder->frames_written(), folder.c_str());
  if (recorder->clipped_depth_pixels() > 0) {
    std::printf(" (%ld depth pixels beyond the file range stored as 0)",
                recorder->clipped_depth_pixels());
  }
  std::printf("; replay with --source tum:%s\n", folder.c_str());
  return closed.ok();
}

// The modes that check a recording instead of reading a camera; nullopt when none is asked.
std::optional<int> RunCheckModes(const CameraArgs& a) {
  if (a.list) return ListDevices();
  if (a.check_ground_truth) {
    if (a.spec.empty() || a.config.empty()) {
      std::fprintf(stderr, "ccmd_camera: --check-ground-truth needs --source and --config\n");
      return 2;
    }
    return CheckGroundTruth(a.spec, a.config);
  }
  if (a.check_noise) {
    if (a.spec.empty()) {
      std::fprintf(stderr, "ccmd_camera: --check-noise needs --source\n");
      return 2;
    }
    return CheckNoise(a.spec, a.config, a.frames > 0 ? a.frames : 30);
  }
  if (a.check_shutter) {
    if (a.spec.empty()) {
      std::fprintf(stderr, "ccmd_camera: --check-shutter needs --source\n");
      return 2;
    }
    return CheckShutter(a.spec, a.config, a.frames > 0 ? a.frames : 450, a.readouts_ms);
  }
  if (a.check_registration) {
    if (a.spec.empty() || a.config.empty()) {
      std::fprintf(stderr, "ccmd_camera: --check-registration needs --source and --config\n");
      return 2;
    }
    return CheckRegistration(a.spec, a.config, a.frames > 0 ? a.frames : 15);
  }
  return std::nullopt;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Check a depth camera and record what it delivers.\n"
      "  ccmd_camera --list\n"
      "  ccmd_camera --source openni2 [--frames 30]\n"
      "  ccmd_camera --source v4l2:color=/dev/video4,depth=/dev/video2 --record DIR\n"
      "Statistics per frame: size, timestamp, interval, depth valid fraction, min/median/max."};
  CameraArgs args;
  AddOptions(&app, &args);
  CLI11_PARSE(app, argc, argv);
  if (const std::optional<int> checked = RunCheckModes(args)) return *checked;
  if (args.spec.empty()) {
    std::fprintf(stderr, "ccmd_camera: give --source SPEC or --list (see --help)\n");
    return 2;
  }
  const int frames = args.frames >= 0 ? args.frames : (args.record.empty() ? 10 : 0);
  if (frames == 0 && args.record.empty()) {
    std::fprintf(stderr, "ccmd_camera: --frames 0 (until Ctrl-C) needs --record\n");
    return 2;
  }

  // Before any thread exists (OpenNI2 starts some when opened), so that every thread
  // inherits the blocked signals and only the watcher receives them.
  std::atomic<ccmd::RetryingSource*> retrying{nullptr};
  StopWatcher watcher([&retrying] {
    if (ccmd::RetryingSource* source = retrying.load()) source->Cancel();
  });

  ccmd::SourceOptions options;
  options.camera_config = args.config;
  options.configs_dir = ccmd::app::ConfigDir();
  auto opened = args.retry ? ccmd::OpenSourceWithRetry(args.spec, options)
                           : ccmd::OpenSource(args.spec, options);
  if (!opened.ok()) return Fail(opened.status());
  std::unique_ptr<ccmd::RgbdSource> source = std::move(opened).value();
  const ccmd::PinholeCamera& camera = source->camera();
  std::printf("source: %s\n", source->Describe().c_str());
  std::printf("camera: %s\n", camera.ToString().c_str());
  ccmd::LogOptions("source", options);
  ccmd::LogOptions("camera", camera);

  std::unique_ptr<ccmd::TumRecorder> recorder;
  if (!args.record.empty()) {
    auto created = OpenRecorder(args, options, camera);
    if (!created.ok()) return Fail(created.status());
    recorder = std::move(created).value();
    std::printf("recording to %s (%s)\n", args.record.c_str(),
                frames > 0 ? (std::to_string(frames) + " frames").c_str() : "until Ctrl-C");
  }
  const int every = args.every > 0 ? args.every
                    : recorder     ? std::max(1, static_cast<int>(camera.fps + 0.5))
                                   : 1;
  std::fflush(stdout);

  retrying = dynamic_cast<ccmd::RetryingSource*>(source.get());
  int exit_code = 0;
  CaptureStats captured;
  const double started = ccmd::MonotonicSeconds();
  if (ccmd::Status s =
          Capture(frames, every, source.get(), retrying, watcher, recorder.get(), &captured);
      !s.ok())
    exit_code = Fail(s);
  PrintCaptureSummary(captured, ccmd::MonotonicSeconds() - started, watcher.stopped(),
                      source->DroppedFrames());
  if (recorder && !CloseRecorder(recorder.get(), *source, args.record)) exit_code = 1;
  retrying = nullptr;  // the source goes before the watcher
  return exit_code;
}
