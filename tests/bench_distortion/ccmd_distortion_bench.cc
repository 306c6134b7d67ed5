// ccmd_distortion_bench: what lens distortion handling buys and costs. The synthetic room is
// rendered through a config's camera with its distortion (TUM fr1 by default: k1 0.26,
// k2 -0.95, k3 1.16, several pixels at the image corners), and two front-ends track the same
// frames: one with the config's camera (keypoints undistorted, as shipped) and one with the
// distortion coefficients zeroed (the images used as if undistorted, as before). Reported:
// the ATE of both and their ratio; the cost of undistorting a frame's keypoints against
// extracting them; the dense back-projection of a keyframe with and without distortion.

#include <CLI/CLI.hpp>
#include <cstdio>
#include <opencv2/imgproc.hpp>

#include "libccmd/dense/backprojection.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/config.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/tracking/config.h"
#include "libccmd/tracking/frame.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/util/json.h"
#include "libccmd/util/timer.h"

namespace {

using namespace ccmd;

struct Costs {
  double extract_ms = 0, undistort_ms = 0, keypoints = 0;
  double backproject_ms = 0, backproject_plain_ms = 0;
  int samples = 0;
};

// Per frame: feature extraction (the reference), then undistorting its keypoints, timed apart;
// every tenth frame also the dense back-projection at the transmitted half resolution.
void MeasureCosts(const RgbdFrame& frame, const PinholeCamera& camera, const OrbExtractor& orb,
                  int index, Costs* costs) {
  cv::Mat gray;
  cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
  PinholeCamera plain = camera;
  plain.distortion = {0, 0, 0, 0, 0};
  Stopwatch watch;
  FrameFeatures features = ComputeFeatures(gray, frame.depth_mm, orb, plain, TrackingOptions{});
  costs->extract_ms += watch.ElapsedMillis();
  watch = Stopwatch();
  for (cv::KeyPoint& k : features.keypoints) {
    const Eigen::Vector2d ideal = camera.UndistortPixel({k.pt.x, k.pt.y});
    k.pt = cv::Point2f(static_cast<float>(ideal.x()), static_cast<float>(ideal.y()));
  }
  costs->undistort_ms += watch.ElapsedMillis();
  costs->keypoints += static_cast<double>(features.keypoints.size());
  if (index % 10 == 0) {
    cv::Mat depth, bgr;
    cv::resize(frame.depth_mm, depth, cv::Size(), 0.5, 0.5, cv::INTER_NEAREST);
    cv::resize(frame.bgr, bgr, depth.size(), 0, 0, cv::INTER_AREA);
    watch = Stopwatch();
    auto distorted = BackProjectKeyframe(depth, bgr, camera.Scaled(0.5));
    costs->backproject_ms += watch.ElapsedMillis();
    watch = Stopwatch();
    auto pinhole = BackProjectKeyframe(depth, bgr, plain.Scaled(0.5));
    costs->backproject_plain_ms += watch.ElapsedMillis();
    ++costs->samples;
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Front-end accuracy with and without lens undistortion on a distorted synthetic sequence, "
      "and its cost."};
  std::string config_path = std::string(CCMD_CONFIG_DIR) + "/tum_fr1.yaml", json_path;
  int frames = 300;
  std::uint64_t seed = 1;
  app.add_option("--config", config_path, "Camera config whose distortion to render and undo")
      ->capture_default_str();
  app.add_option("--frames", frames, "Frames of the room's loop")
      ->check(CLI::Range(30, 100000))
      ->capture_default_str();
  app.add_option("--seed", seed, "Room and noise seed")->capture_default_str();
  app.add_option("--json", json_path, "Also write the figures as JSON");
  CLI11_PARSE(app, argc, argv);

  auto camera = LoadCameraConfig(config_path);
  auto config = ConfigFile::Open(config_path);
  if (!camera.ok() || !config.ok()) {
    std::fprintf(stderr, "%s\n",
                 (camera.ok() ? config.status() : camera.status()).ToString().c_str());
    return 1;
  }
  if (!camera->HasDistortion()) {
    std::fprintf(stderr, "%s has no distortion: nothing to compare\n", config_path.c_str());
    return 1;
  }
  auto tracking = ReadTrackingOptions(*config);
  if (!tracking.ok()) return 1;
  tracking->synchronous_mapping = true;  // deterministic
  PinholeCamera ignored = *camera;
  ignored.distortion = {0, 0, 0, 0, 0};
  auto undistorting = Frontend::Create(*camera, *tracking, nullptr);
  auto ignoring = Frontend::Create(ignored, *tracking, nullptr);
  if (!undistorting.ok() || !ignoring.ok()) return 1;

  SyntheticSequenceOptions synth;
  synth.frames = frames;
  synth.seed = seed;
  synth.camera = *camera;
  RoomSceneOptions room = synth.room;
  room.seed = seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(frames, camera->fps, synth.path);
  const OrbExtractor orb(tracking->orb);
  Costs costs;
  std::printf("rendering and tracking %d frames through %s (%s)\n", frames, config_path.c_str(),
              camera->ToString().c_str());
  for (int i = 0; i < frames; ++i) {
    RgbdFrame frame;
    const RenderedFrame rendered =
        RenderFrame(scene, *camera, path[i].T_world_cam, FrameRenderOptions(synth, i));
    frame.index = i;
    frame.timestamp = path[i].timestamp;
    frame.bgr = rendered.bgr;
    frame.depth_mm = rendered.depth_mm;
    (*undistorting)->ProcessFrame(frame);
    (*ignoring)->ProcessFrame(frame);
    MeasureCosts(frame, *camera, orb, i, &costs);
    if ((i + 1) % 50 == 0) std::printf("  %d frames\n", i + 1), std::fflush(stdout);
  }
  (*undistorting)->Finish();
  (*ignoring)->Finish();
  auto with = ComputeAte(path, (*undistorting)->FrameTrajectory());
  auto without = ComputeAte(path, (*ignoring)->FrameTrajectory());
  if (!with.ok() || !without.ok()) {
    std::fprintf(stderr, "ATE: %s\n",
                 (with.ok() ? without.status() : with.status()).ToString().c_str());
    return 1;
  }
  Json j;
  j["config"] = config_path;
  j["frames"] = frames;
  j["ate_undistorted_m"] = with->error.rmse;
  j["ate_distortion_ignored_m"] = without->error.rmse;
  j["ate_ratio"] = with->error.rmse / without->error.rmse;
  j["lost_frames_undistorted"] = (*undistorting)->stats().lost_frames;
  j["lost_frames_ignored"] = (*ignoring)->stats().lost_frames;
  j["keypoints_per_frame"] = costs.keypoints / frames;
  j["extract_ms_per_frame"] = costs.extract_ms / frames;
  j["undistort_ms_per_frame"] = costs.undistort_ms / frames;
  j["undistort_to_extract_ratio"] = costs.undistort_ms / costs.extract_ms;
  j["backproject_ms"] = costs.backproject_ms / costs.samples;
  j["backproject_pinhole_ms"] = costs.backproject_plain_ms / costs.samples;
  j["backproject_ratio"] = costs.backproject_ms / costs.backproject_plain_ms;
  std::printf("\n| front-end | ATE RMSE (mm) | lost frames |\n|---|---|---|\n");
  std::printf("| keypoints undistorted (shipped) | %.2f | %d |\n", 1e3 * with->error.rmse,
              (*undistorting)->stats().lost_frames);
  std::printf("| distortion ignored | %.2f | %d |\n", 1e3 * without->error.rmse,
              (*ignoring)->stats().lost_frames);
  std::printf("ratio undistorted / ignored: %.3f\n\n", j["ate_ratio"].number());
  std::printf(
      "cost per frame: %.0f keypoints undistorted in %.3f ms, feature extraction %.2f ms (ratio "
      "%.4f)\n",
      j["keypoints_per_frame"].number(), j["undistort_ms_per_frame"].number(),
      j["extract_ms_per_frame"].number(), j["undistort_to_extract_ratio"].number());
  std::printf(
      "dense back-projection of a half-resolution keyframe: %.2f ms with distortion, %.2f ms "
      "pinhole "
      "(ratio %.2f)\n",
      j["backproject_ms"].number(), j["backproject_pinhole_ms"].number(),
      j["backproject_ratio"].number());
  if (!json_path.empty()) {
    const Status s = WriteJsonFile(j, json_path);
    if (!s.ok()) std::fprintf(stderr, "%s\n", s.ToString().c_str());
  }
  return 0;
}
