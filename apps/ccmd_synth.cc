// ccmd_synth: renders a synthetic RGB-D sequence of a textured room with exact ground truth,
// in the TUM RGB-D layout, plus the ground-truth surface for reconstruction error.

#include <CLI/CLI.hpp>
#include <cstdio>

#include "apps/app_common.h"
#include "libccmd/io/config.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/options_writer.h"

int main(int argc, char** argv) {
  CLI::App app{
      "Render a synthetic RGB-D sequence (TUM layout) of a textured room with exact ground truth.\n"
      "Writes rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt, camera.yaml and surface.ply.\n"
      "With --config the images are those the config's camera would record: its size, focal "
      "lengths\n"
      "(a negative fy flips the rows, as in ICL-NUIM), lens distortion, frame rate, depth scale,\n"
      "colour order, depth from the Depth block's imager when there is one, and the depth\n"
      "noise of the DepthNoise keys when it states them."};
  ccmd::SyntheticSequenceOptions options;
  std::string out, config;
  bool no_noise = false;
  app.add_option("--out", out, "Output folder (created if missing)")->required();
  app.add_option("--config", config,
                 "Camera config (ORB-SLAM YAML, e.g. configs/tum_fr1.yaml) to render through; "
                 "sets the image size and frame rate");
  app.add_option("--frames", options.frames, "Number of frames")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  app.add_option("--seed", options.seed, "Scene and noise seed")->capture_default_str();
  app.add_option("--width", options.width, "Image width")
      ->check(CLI::Range(32, 4096))
      ->capture_default_str();
  app.add_option("--height", options.height, "Image height")
      ->check(CLI::Range(24, 4096))
      ->capture_default_str();
  app.add_option("--fps", options.fps, "Frame rate")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--noise", options.noise_scale, "Noise scale (1 = default sensor model)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_flag("--no-noise", no_noise, "Exact depth and colour");
  app.add_option("--surface-spacing", options.surface_spacing,
                 "Ground-truth surface sampling in metres")
      ->check(CLI::Range(0.002, 1.0))
      ->capture_default_str();
  app.add_option("--texture-density", options.room.shapes_per_m2,
                 "Texture shapes per square metre of surface (fewer: plainer walls, fewer corners)")
      ->check(CLI::Range(0.0, 10000.0))
      ->capture_default_str();
  app.add_option("--loop-period", options.path.loop_period_s, "Seconds per loop of the camera path")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  double exposure_ms = 0;
  app.add_option("--exposure", exposure_ms,
                 "Motion blur: each colour image averages the views over this exposure (ms, "
                 "centred on the frame's time, at most a frame interval; depth stays sharp)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  double depth_lag_ms = 0;
  app.add_option("--depth-lag", depth_lag_ms,
                 "Depth taken this many ms after the colour image, as by a sensor whose streams "
                 "are not synchronised (TUM RGB-D: 10-15 ms); under half a frame interval")
      ->capture_default_str();
  double rolling_shutter_ms = 0;
  app.add_option("--rolling-shutter", rolling_shutter_ms,
                 "Rolling shutter: the colour image's rows are read out over this many ms, first "
                 "row to last, each row the view at its own time (the frame's time is the middle "
                 "row's; at most a frame interval; depth stays a global shutter's)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--threads", options.threads, "Render threads (0 = all cores)")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  if (no_noise || options.noise_scale == 0.0) options.noise = false;
  options.exposure_s = exposure_ms * 1e-3;
  options.depth_lag_s = depth_lag_ms * 1e-3;
  options.rolling_shutter_s = rolling_shutter_ms * 1e-3;
  if (!config.empty()) {
    for (const char* fixed : {"--width", "--height", "--fps"}) {
      if (app.count(fixed) > 0) {
        std::fprintf(stderr,
                     "ccmd_synth: %s comes from the camera config; leave it out with --config\n",
                     fixed);
        return 1;
      }
    }
    auto camera = ccmd::LoadCameraConfig(config);
    auto depth = camera.ok() ? ccmd::LoadDepthToColorCalibration(config) : camera.status();
    if (!depth.ok()) {
      std::fprintf(stderr, "ccmd_synth: %s\n", depth.status().ToString().c_str());
      return 1;
    }
    // The camera's depth noise, when the config states it (DepthNoise keys).
    auto file = ccmd::ConfigFile::Open(config);
    ccmd::DepthNoise rendered;
    rendered.sigma_0 = options.depth_sigma_0;
    rendered.sigma_2 = options.depth_sigma_2;
    auto noise = file.ok() ? ccmd::ReadDepthNoise(*file, rendered) : file.status();
    if (!noise.ok()) {
      std::fprintf(stderr, "ccmd_synth: %s\n", noise.status().ToString().c_str());
      return 1;
    }
    options.depth_sigma_0 = noise->sigma_0;
    options.depth_sigma_2 = noise->sigma_2;
    auto frame_depth_weight = file->GetDouble("Tracking.frameDepthWeight", 0.0);
    if (!frame_depth_weight.ok()) {
      std::fprintf(stderr, "ccmd_synth: %s\n", frame_depth_weight.status().ToString().c_str());
      return 1;
    }
    options.frame_depth_weight = *frame_depth_weight;
    // The ground truth of the camera the config's trajectories are of (7-Scenes: depth).
    auto trajectory_camera = ccmd::ReadTrajectoryCamera(*file);
    if (!trajectory_camera.ok()) {
      std::fprintf(stderr, "ccmd_synth: %s\n", trajectory_camera.status().ToString().c_str());
      return 1;
    }
    options.ground_truth_of_depth_camera =
        *depth && !trajectory_camera->isApprox(ccmd::Pose::Identity(), 1e-12);
    options.camera = *camera;
    options.depth_camera = *depth;
    options.width = camera->width;
    options.height = camera->height;
    options.fps = camera->fps;
    std::fprintf(stderr, "camera from %s: %s%s; depth noise %.2g m + %.2g m^-1 z^2\n",
                 config.c_str(), camera->ToString().c_str(),
                 *depth ? ", depth from the Depth block's imager" : "", options.depth_sigma_0,
                 options.depth_sigma_2);
  }

  std::fprintf(stderr, "rendering %d frames %dx%d (seed %llu) into %s\n", options.frames,
               options.width, options.height, static_cast<unsigned long long>(options.seed),
               out.c_str());
  if (ccmd::Status valid = options.Validate(); !valid.ok()) {
    std::fprintf(stderr, "ccmd_synth: %s\n", valid.ToString().c_str());
    return 1;
  }
  ccmd::LogOptions("synth", options);
  ccmd::app::Progress progress("frames");
  auto summary = ccmd::WriteSyntheticSequence(
      out, options, [&](int done, int total) { progress.Update(done, total); });
  if (!summary.ok()) {
    std::fprintf(stderr, "ccmd_synth: %s\n", summary.status().ToString().c_str());
    return 1;
  }
  std::printf(
      "wrote %d frames to %s in %.1f s (render %.1f ms/frame), surface.ply with %zu points\n",
      summary->frames, out.c_str(), summary->seconds, summary->render_ms_per_frame,
      summary->surface_points);
  return 0;
}
