#include "libccmd/synth/sequence.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <thread>

#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status LoopPathOptions::Validate() const {
  for (const double v : {radius_x, radius_y, height, height_amplitude, loop_period_s, yaw_ahead_deg,
                         pitch_deg, pitch_amplitude_deg, roll_amplitude_deg, start_time}) {
    if (!std::isfinite(v)) return InvalidArgument("path values must be finite");
  }
  if (!(radius_x > 0 && radius_y > 0)) return InvalidArgument("path radii must be positive");
  if (!(loop_period_s > 0)) return InvalidArgument("loop period must be positive");
  return Status::Ok();
}

void LoopPathOptions::Describe(OptionsWriter* out) const {
  out->Add("radius_x", radius_x);
  out->Add("radius_y", radius_y);
  out->Add("height", height);
  out->Add("height_amplitude", height_amplitude);
  out->Add("loop_period_s", loop_period_s);
  out->Add("yaw_ahead_deg", yaw_ahead_deg);
  out->Add("pitch_deg", pitch_deg);
  out->Add("pitch_amplitude_deg", pitch_amplitude_deg);
  out->Add("roll_amplitude_deg", roll_amplitude_deg);
  out->Add("start_time", start_time);
}

Status SyntheticSequenceOptions::Validate() const {
  if (frames < 1) return InvalidArgument("frames must be at least 1");
  if (camera) CCMD_RETURN_IF_ERROR(camera->ValidateInvertible().WithContext("camera"));
  if (depth_camera) {
    CCMD_RETURN_IF_ERROR(depth_camera->depth.Validate().WithContext("depth camera"));
  }
  if (ground_truth_of_depth_camera && !depth_camera) {
    return InvalidArgument("a ground truth of the depth camera needs a depth camera");
  }
  if (!camera && (width < 32 || height < 24 || width > 4096 || height > 4096)) {
    return InvalidArgument("image size must be between 32x24 and 4096x4096");
  }
  if (!((camera ? camera->fps : fps) > 0)) return InvalidArgument("fps must be positive");
  if (!(surface_spacing >= 0.002)) return InvalidArgument("surface spacing below 2 mm");
  if (!(frame_depth_weight >= 0) || !std::isfinite(frame_depth_weight)) {
    return InvalidArgument("frame depth weight must be finite and >= 0");
  }
  if (!(noise_scale >= 0) || !std::isfinite(noise_scale)) {
    return InvalidArgument("noise scale must be >= 0");
  }
  if (!(depth_sigma_0 >= 0 && depth_sigma_2 >= 0 && std::isfinite(depth_sigma_0) &&
        std::isfinite(depth_sigma_2))) {
    return InvalidArgument("depth noise sigmas must be >= 0 and finite");
  }
  if (threads < 0) return InvalidArgument("threads must be >= 0 (0: all cores)");
  if (!(exposure_s >= 0 && exposure_s <= 1.0 / (camera ? camera->fps : fps))) {
    return InvalidArgument("exposure must be between 0 and one frame interval");
  }
  if (!(rolling_shutter_s >= 0 && rolling_shutter_s <= 1.0 / (camera ? camera->fps : fps))) {
    return InvalidArgument("rolling shutter readout must be between 0 and one frame interval");
  }
  // (half an interval or more and depth.txt would pair each depth with the next colour image)
  if (!(std::fabs(depth_lag_s) < 0.5 / (camera ? camera->fps : fps))) {
    return InvalidArgument("depth lag must be less than half a frame interval");
  }
  CCMD_RETURN_IF_ERROR(room.Validate().WithContext("room"));
  return path.Validate().WithContext("path");
}

void SyntheticSequenceOptions::Describe(OptionsWriter* out) const {
  out->Add("frames", frames);
  out->Add("width", width);
  out->Add("height", height);
  out->Add("fps", fps);
  if (camera) out->Nested("camera", *camera);
  if (depth_camera) {
    out->Nested("depth_camera", depth_camera->depth);
    const Eigen::Matrix4d T = depth_camera->T_color_depth.matrix();
    out->Add("depth_camera.T_color_depth",
             std::vector<double>(T.data(), T.data() + 12));  // column-major, top three rows
    out->Add("ground_truth_of_depth_camera", ground_truth_of_depth_camera);
  }
  out->Add("seed", seed);
  out->Add("noise", noise);
  out->Add("depth_sigma_0", depth_sigma_0);
  out->Add("depth_sigma_2", depth_sigma_2);
  out->Add("frame_depth_weight", frame_depth_weight);
  out->Add("noise_scale", noise_scale);
  out->Add("surface_spacing", surface_spacing);
  out->Add("exposure_s", exposure_s);
  out->Add("depth_lag_s", depth_lag_s);
  out->Add("rolling_shutter_s", rolling_shutter_s);
  out->Add("threads", threads);
  out->Nested("room", room);
  out->Nested("path", path);
}

Trajectory MakeLoopPath(int num_frames, double fps, const LoopPathOptions& o) {
  Trajectory trajectory;
  for (int i = 0; i < num_frames; ++i) {
    const double t = i / fps;
    trajectory.push_back({o.start_time + t, LoopPathPose(t, o)});
  }
  return trajectory;
}

Pose LoopPathPose(double t, const LoopPathOptions& o) {
  const double deg = M_PI / 180.0;
  const double phase = 2 * M_PI * t / o.loop_period_s;
  const Eigen::Vector3d eye(o.radius_x * std::cos(phase), o.radius_y * std::sin(phase),
                            o.height + o.height_amplitude * std::sin(3.0 * phase + 0.4));
  const double yaw = phase + o.yaw_ahead_deg * deg;
  const double pitch = (o.pitch_deg + o.pitch_amplitude_deg * std::sin(2.0 * phase + 1.0)) * deg;
  const double roll = o.roll_amplitude_deg * deg * std::sin(5.0 * phase);
  // Camera axes: z forward (yaw/pitch), x right, y down; then roll about z.
  const Eigen::Vector3d forward(std::cos(pitch) * std::cos(yaw), std::cos(pitch) * std::sin(yaw),
                                std::sin(pitch));
  Pose pose = LookAt(eye, eye + forward, Eigen::Vector3d::UnitZ());
  pose.linear() =
      pose.linear() * Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  return pose;
}

PinholeCamera SyntheticCamera(int width, int height) {
  PinholeCamera base;
  base.width = 640;
  base.height = 480;
  base.fx = base.fy = 525.0;
  base.cx = 319.5;
  base.cy = 239.5;
  base.fps = 30.0;
  base.depth_map_factor = 5000.0;
  base.bf = 52.5;  // a 10 cm virtual baseline
  base.far_depth_m = 4.0;
  if (width == 640 && height == 480) return base;
  return base.Resized(width, height);
}

PinholeCamera SequenceCamera(const SyntheticSequenceOptions& options) {
  return options.camera ? *options.camera : SyntheticCamera(options.width, options.height);
}

RenderOptions FrameRenderOptions(const SyntheticSequenceOptions& options, int index) {
  RenderOptions render;
  render.noise = options.noise;
  render.depth.sigma_0 = options.depth_sigma_0 * options.noise_scale;
  render.depth.sigma_2 = options.depth_sigma_2 * options.noise_scale;
  render.color_sigma *= options.noise_scale;
  render.seed = MixSeed(options.seed, static_cast<std::uint64_t>(index) + 1);
  return render;
}

namespace {

std::string FormatTimestamp(double t) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.6f", t);
  return text;
}

std::string DescribeOptions(const SyntheticSequenceOptions& o) {
  std::ostringstream s;
  s << "# ccmd_synth sequence\n"
    << "frames " << o.frames << "\nwidth " << o.width << "\nheight " << o.height << "\nfps "
    << o.fps << "\nseed " << o.seed << "\nnoise " << (o.noise ? 1 : 0) << "\nnoise_scale "
    << o.noise_scale << "\nsurface_spacing " << o.surface_spacing << "\nroom " << o.room.size_x
    << " x " << o.room.size_y << " x " << o.room.height << "\nloop_period_s "
    << o.path.loop_period_s << "\n";
  if (o.exposure_s > 0) s << "exposure_s " << o.exposure_s << "\n";
  if (o.depth_lag_s != 0) s << "depth_lag_s " << o.depth_lag_s << "\n";
  if (o.rolling_shutter_s > 0) s << "rolling_shutter_s " << o.rolling_shutter_s << "\n";
  if (o.camera) s << "camera " << o.camera->ToString() << "\n";
  if (o.depth_camera) {
    const Eigen::Vector3d t = o.depth_camera->T_color_depth.translation();
    s << "depth_camera " << o.depth_camera->depth.ToString() << " at (" << t.x() << ", " << t.y()
      << ", " << t.z() << ") m in the colour frame\n";
  }
  return s.str();
}

// One frame as the camera records it: colour in the file's channel order, depth from the
// depth imager when there is one, in file units.
struct RecordedFrame {
  cv::Mat colour, depth;
};

// The colour image over the exposure: the mean of kBlurSamples views spread evenly over it
// (each with the frame's own noise, so the noise is not averaged away).
constexpr int kBlurSamples = 8;

cv::Mat BlurredColour(const SyntheticScene& scene, const SyntheticSequenceOptions& options,
                      const PinholeCamera& camera, double t, const RenderOptions& render) {
  cv::Mat sum(camera.height, camera.width, CV_32FC3, cv::Scalar::all(0));
  for (int k = 0; k < kBlurSamples; ++k) {
    const double t_k = t + options.exposure_s * ((k + 0.5) / kBlurSamples - 0.5);
    const RenderedFrame view = RenderFrame(scene, camera, LoopPathPose(t_k, options.path), render);
    cv::accumulate(view.bgr, sum);
  }
  cv::Mat bgr;
  sum.convertTo(bgr, CV_8UC3, 1.0 / kBlurSamples);
  return bgr;
}

// The colour image of a rolling shutter: kRollingBands bands of rows, each the view (blurred
// over the exposure when there is one) at its band's middle row's time. A band's rows are at
// most readout / (2 kRollingBands) from their own time: 0.5 ms for a 30 ms readout, a tenth of
// a pixel at a hand-held camera's speed.
constexpr int kRollingBands = 32;

cv::Mat RollingShutterColour(const SyntheticScene& scene, const SyntheticSequenceOptions& options,
                             const PinholeCamera& camera, double t, const RenderOptions& render) {
  cv::Mat bgr(camera.height, camera.width, CV_8UC3);
  const int bands = std::min(kRollingBands, camera.height);
  for (int b = 0; b < bands; ++b) {
    const int first = b * camera.height / bands, last = (b + 1) * camera.height / bands;
    const double middle_row = 0.5 * (first + last);
    const double t_b = t + options.rolling_shutter_s * (middle_row / camera.height - 0.5);
    RenderOptions rows = render;
    rows.row_first = first;
    rows.row_last = last - 1;
    const cv::Mat view =
        options.exposure_s > 0
            ? BlurredColour(scene, options, camera, t_b, rows)
            : RenderFrame(scene, camera, LoopPathPose(t_b, options.path), rows).bgr;
    view.rowRange(first, last).copyTo(bgr.rowRange(first, last));
  }
  return bgr;
}

// Frame `index`, `t` seconds into the path, at the camera's pose then.
RecordedFrame RenderRecordedFrame(const SyntheticScene& scene,
                                  const SyntheticSequenceOptions& options,
                                  const PinholeCamera& camera, double t, int index,
                                  VisibilityMarks* marks) {
  const RenderOptions render = FrameRenderOptions(options, index);
  const Pose T_world_cam = LoopPathPose(t, options.path);
  const RenderedFrame frame = RenderFrame(scene, camera, T_world_cam, render, marks);
  const cv::Mat bgr = options.rolling_shutter_s > 0
                          ? RollingShutterColour(scene, options, camera, t, render)
                      : options.exposure_s > 0 ? BlurredColour(scene, options, camera, t, render)
                                               : frame.bgr;
  RecordedFrame out;
  out.colour = camera.rgb ? bgr : SwapRedBlue(bgr);
  cv::Mat depth_mm = frame.depth_mm;
  const Pose T_world_cam_at_depth =
      options.depth_lag_s != 0 ? LoopPathPose(t + options.depth_lag_s, options.path) : T_world_cam;
  if (options.depth_camera) {
    const Pose T_world_depth = T_world_cam_at_depth * options.depth_camera->T_color_depth;
    depth_mm = RenderFrame(scene, options.depth_camera->depth, T_world_depth, render).depth_mm;
  } else if (options.depth_lag_s != 0) {
    depth_mm = RenderFrame(scene, camera, T_world_cam_at_depth, render).depth_mm;
  }
  depth_mm.convertTo(out.depth, CV_16U, camera.depth_map_factor / 1000.0);
  return out;
}

}  // namespace

StatusOr<SyntheticSequenceSummary> WriteSyntheticSequence(
    const std::string& folder, const SyntheticSequenceOptions& options,
    const std::function<void(int, int)>& progress) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  const PinholeCamera camera = SequenceCamera(options);
  const double fps = options.camera ? camera.fps : options.fps;
  const Stopwatch total;
  CCMD_RETURN_IF_ERROR(MakeDirectories(JoinPath(folder, "rgb")));
  CCMD_RETURN_IF_ERROR(MakeDirectories(JoinPath(folder, "depth")));

  RoomSceneOptions room = options.room;
  room.seed = options.seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(options.frames, fps, options.path);

  const int threads =
      options.threads > 0 ? options.threads : std::max(1u, std::thread::hardware_concurrency());
  std::atomic<int> next{0}, done{0};
  std::atomic<double> render_seconds{0.0};
  std::mutex mutex;
  Status first_error;
  std::vector<VisibilityMarks> marks(threads);
  auto worker = [&](int id) {
    marks[id].Init(scene, options.surface_spacing);
    while (true) {
      const int i = next++;
      if (i >= options.frames) break;
      const Stopwatch watch;
      const RecordedFrame frame =
          RenderRecordedFrame(scene, options, camera, i / fps, i, &marks[id]);
      double expected = render_seconds.load();
      while (!render_seconds.compare_exchange_weak(expected, expected + watch.ElapsedSeconds())) {
      }
      const std::string name = FormatTimestamp(path[i].timestamp) + ".png";
      const std::string depth_name =
          FormatTimestamp(path[i].timestamp + options.depth_lag_s) + ".png";
      bool ok = false;
      try {
        ok = cv::imwrite(JoinPath(folder, "rgb/" + name), frame.colour) &&
             cv::imwrite(JoinPath(folder, "depth/" + depth_name), frame.depth);
      } catch (const cv::Exception&) {
        ok = false;
      }
      if (!ok) {
        std::lock_guard<std::mutex> lock(mutex);
        if (first_error.ok()) first_error = IoError("cannot write frame images in " + folder);
        next = options.frames;  // stop the other workers too
        break;
      }
      const int finished = ++done;
      if (progress) {
        std::lock_guard<std::mutex> lock(mutex);
        progress(finished, options.frames);
      }
    }
  };
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) pool.emplace_back(worker, t);
  for (auto& t : pool) t.join();
  if (!first_error.ok()) return first_error;

  std::string rgb_list = "# color images\n# timestamp filename\n";
  std::string depth_list = "# depth maps\n# timestamp filename\n";
  for (const StampedPose& p : path) {
    const std::string stamp = FormatTimestamp(p.timestamp);
    const std::string depth_stamp = FormatTimestamp(p.timestamp + options.depth_lag_s);
    rgb_list += stamp + " rgb/" + stamp + ".png\n";
    depth_list += depth_stamp + " depth/" + depth_stamp + ".png\n";
  }
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(folder, "rgb.txt"), rgb_list));
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(folder, "depth.txt"), depth_list));
  if (options.ground_truth_of_depth_camera) {
    CCMD_RETURN_IF_ERROR(WriteTumTrajectory(
        TrajectoryOfCamera(path, options.depth_camera->T_color_depth),
        JoinPath(folder, "groundtruth.txt"), "ground truth of the depth camera, T_world_depth"));
  } else {
    CCMD_RETURN_IF_ERROR(WriteTumTrajectory(path, JoinPath(folder, "groundtruth.txt"),
                                            "ground truth of the colour camera, T_world_cam"));
  }
  // The camera's own depth noise and frame depth weight, for the agents that read camera.yaml
  // (the defaults need no keys: they are the agents' defaults too).
  std::ostringstream config_keys;
  if (options.depth_sigma_0 != DepthSensorModel().sigma_0 ||
      options.depth_sigma_2 != DepthSensorModel().sigma_2) {
    config_keys.precision(9);
    config_keys << "DepthNoise.sigma0: " << options.depth_sigma_0
                << "\nDepthNoise.sigma2: " << options.depth_sigma_2 << "\n";
  }
  if (options.frame_depth_weight > 0)
    config_keys << "Tracking.frameDepthWeight: " << options.frame_depth_weight << "\n";
  if (options.ground_truth_of_depth_camera) config_keys << "Trajectory.camera: \"depth\"\n";
  // The renderer's timestamps are when each image was taken: the agents may move the depth
  // to its colour image's time by them.
  if (options.depth_lag_s != 0) config_keys << "Tracking.depthLagCompensation: 1\n";
  // A rolling shutter's readout is the camera's own: the agents move the keypoints by it.
  if (options.rolling_shutter_s > 0)
    config_keys << "Camera.rollingShutterReadout: " << options.rolling_shutter_s << "\n";
  CCMD_RETURN_IF_ERROR(WriteCameraConfig(camera, JoinPath(folder, "camera.yaml"),
                                         options.depth_camera, config_keys.str()));
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(folder, "sequence.txt"), DescribeOptions(options)));

  VisibilityMarks seen = marks[0];
  for (int t = 1; t < threads; ++t) seen.Merge(marks[t]);
  const PointCloud surface = scene.SampleSurface(options.surface_spacing, &seen.cells);
  CCMD_RETURN_IF_ERROR(WritePly(surface, JoinPath(folder, "surface.ply")));

  SyntheticSequenceSummary summary;
  summary.frames = options.frames;
  summary.surface_points = surface.size();
  summary.seconds = total.ElapsedSeconds();
  summary.render_ms_per_frame = render_seconds.load() * 1e3 / options.frames;
  return summary;
}

}  // namespace ccmd
