#include "libccmd/sensors/source_factory.h"

#include "libccmd/io/config.h"
#include "libccmd/sensors/dataset_source.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/synthetic_source.h"
#ifdef CCMD_HAVE_OPENNI2
#include "libccmd/sensors/openni2_source.h"
#endif
#ifdef CCMD_HAVE_V4L2
#include "libccmd/sensors/v4l2_source.h"
#endif
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

Status SourceOptions::Validate() const {
  if (segment && (segment->second < 1 || segment->first < 1 || segment->first > segment->second)) {
    return InvalidArgument("segment must be i/k with 1 <= i <= k");
  }
  if (!(segment_overlap >= 0 && segment_overlap < 1)) {
    return InvalidArgument("segment overlap must be in [0, 1)");
  }
  return Status::Ok();
}

void SourceOptions::Describe(OptionsWriter* out) const {
  out->Add("camera_config", camera_config);
  out->Add("segment", segment
                          ? std::to_string(segment->first) + "/" + std::to_string(segment->second)
                          : std::string("all"));
  out->Add("segment_overlap", segment_overlap);
  out->Add("configs_dir", configs_dir);
  out->Add("register_depth", register_depth);
}
namespace {

// A source read through a camera config that asks for more than the source does itself: depth
// registered into the colour camera (`registration`: a recorded sequence whose depth is not
// registered, 7-Scenes or a raw Kinect v1 recording, as the V4L2 source does live), and
// trajectories of another camera of the rig (the config's Trajectory.camera).
class ConfiguredSource : public RgbdSource {
 public:
  ConfiguredSource(std::unique_ptr<RgbdSource> inner,
                   const std::optional<DepthToColorCalibration>& registration,
                   const Pose& T_color_trajectory)
      : inner_(std::move(inner)),
        registration_(registration),
        T_color_trajectory_(T_color_trajectory) {}

  Status Read(RgbdFrame* frame) override {
    CCMD_RETURN_IF_ERROR(inner_->Read(frame));
    if (!registration_) return Status::Ok();
    auto registered = RegisterDepth(frame->depth_mm, *registration_, camera());
    if (!registered.ok()) {
      return InvalidArgument("frame " + std::to_string(frame->index) + ": " +
                             registered.status().message());
    }
    frame->depth_mm = std::move(registered).value();
    return Status::Ok();
  }
  const PinholeCamera& camera() const override { return inner_->camera(); }
  std::string Describe() const override {
    return inner_->Describe() + (registration_ ? ", depth registered to colour" : "");
  }
  int FrameCount() const override { return inner_->FrameCount(); }
  bool IsLive() const override { return inner_->IsLive(); }
  Trajectory GroundTruth() const override { return inner_->GroundTruth(); }
  long DroppedFrames() const override { return inner_->DroppedFrames(); }
  Pose T_color_trajectory() const override { return T_color_trajectory_; }

 private:
  std::unique_ptr<RgbdSource> inner_;
  std::optional<DepthToColorCalibration> registration_;
  Pose T_color_trajectory_;
};

StatusOr<std::optional<FrameRange>> SegmentRange(int frames, const SourceOptions& options) {
  if (!options.segment) return std::optional<FrameRange>();
  CCMD_ASSIGN_OR_RETURN(const auto segments,
                        SplitWithOverlap(frames, options.segment->second, options.segment_overlap));
  return std::optional<FrameRange>(segments[options.segment->first - 1]);
}

#ifdef CCMD_HAVE_OPENNI2
StatusOr<std::unique_ptr<RgbdSource>> OpenOpenNI2(const std::string& uri,
                                                  const SourceOptions& options) {
  OpenNI2Options openni2;
  openni2.uri = uri;
  if (!options.camera_config.empty()) {
    // The config sets the mode as well as the intrinsics.
    CCMD_ASSIGN_OR_RETURN(const PinholeCamera camera, LoadCameraConfig(options.camera_config));
    openni2.camera = camera;
    openni2.width = camera.width;
    openni2.height = camera.height;
    openni2.fps = camera.fps;
  }
  CCMD_ASSIGN_OR_RETURN(auto source, OpenNI2Source::Open(openni2));
  return std::unique_ptr<RgbdSource>(std::move(source));
}
#endif

#ifdef CCMD_HAVE_V4L2
StatusOr<std::unique_ptr<RgbdSource>> OpenV4l2(const std::string& argument,
                                               const SourceOptions& options) {
  CCMD_ASSIGN_OR_RETURN(V4l2SourceOptions v4l2, ParseV4l2Spec(argument));
  std::string config = !v4l2.config.empty() ? v4l2.config : options.camera_config;
  if (config.empty() && !options.configs_dir.empty()) {
    config = JoinPath(options.configs_dir, "realsense_d435_v4l2.yaml");
    CCMD_LOG(WARNING) << "v4l2: no camera config given; using " << config
                      << " (typical D435 values: calibrate your unit for good results)";
  }
  if (config.empty()) {
    return InvalidArgument("v4l2 needs the camera's intrinsics: add config=FILE to the spec");
  }
  CCMD_ASSIGN_OR_RETURN(const PinholeCamera camera, LoadCameraConfig(config));
  CCMD_ASSIGN_OR_RETURN(const auto registration, LoadDepthToColorCalibration(config));
  v4l2.config = config;
  CCMD_ASSIGN_OR_RETURN(const Pose T_color_trajectory, LoadTrajectoryCamera(config));
  CCMD_ASSIGN_OR_RETURN(auto source,
                        V4l2Source::Open(v4l2, camera, OpenLinuxV4l2Device, registration));
  if (T_color_trajectory.isApprox(Pose::Identity(), 1e-12)) {
    return std::unique_ptr<RgbdSource>(std::move(source));
  }
  return std::unique_ptr<RgbdSource>(
      new ConfiguredSource(std::move(source), std::nullopt, T_color_trajectory));
}
#endif

}  // namespace

StatusOr<std::unique_ptr<RgbdSource>> OpenSourceWithRetry(const std::string& spec,
                                                          const SourceOptions& options,
                                                          const RetryOptions& retry) {
  CCMD_ASSIGN_OR_RETURN(std::unique_ptr<RgbdSource> first, OpenSource(spec, options));
  if (!first->IsLive()) return first;
  // The retry wrapper's first open hands over the source opened above.
  auto opened = std::make_shared<std::unique_ptr<RgbdSource>>(std::move(first));
  auto opener = [spec, options, opened]() -> StatusOr<std::unique_ptr<RgbdSource>> {
    if (*opened) return std::move(*opened);
    return OpenSource(spec, options);
  };
  CCMD_ASSIGN_OR_RETURN(auto source, RetryingSource::Open(opener, retry));
  return std::unique_ptr<RgbdSource>(std::move(source));
}

std::string DatasetConfigPath(const std::string& folder, const SourceOptions& options) {
  if (!options.camera_config.empty()) return options.camera_config;
  const std::string own = JoinPath(folder, "camera.yaml");
  if (FileExists(own)) return own;
  const std::string guess = GuessCameraConfigName(folder);
  if (guess.empty() || options.configs_dir.empty()) return "";
  return JoinPath(options.configs_dir, guess);
}

std::string SourceConfigPath(const std::string& spec, const SourceOptions& options) {
  const auto colon = spec.find(':');
  const std::string kind = spec.substr(0, colon);
  if ((kind == "tum" || kind == "dataset") && colon != std::string::npos) {
    return DatasetConfigPath(spec.substr(colon + 1), options);
  }
  return options.camera_config;
}

StatusOr<std::unique_ptr<RgbdSource>> OpenSource(const std::string& spec,
                                                 const SourceOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  const auto colon = spec.find(':');
  const std::string kind = spec.substr(0, colon);
  const std::string argument = colon == std::string::npos ? "" : spec.substr(colon + 1);

  if (kind == "tum" || kind == "dataset") {
    if (argument.empty()) return InvalidArgument("tum: needs a folder, e.g. tum:/data/fr1_desk");
    std::optional<PinholeCamera> camera;
    const std::string config_used = DatasetConfigPath(argument, options);
    if (options.camera_config.empty() && !config_used.empty() &&
        config_used != JoinPath(argument, "camera.yaml")) {
      CCMD_LOG(INFO) << "camera config not given; using " << config_used << " for " << argument;
    }
    if (!config_used.empty()) {
      CCMD_ASSIGN_OR_RETURN(camera, LoadCameraConfig(config_used));
    }
    std::optional<DepthToColorCalibration> registration;
    Pose T_color_trajectory = Pose::Identity();
    if (options.register_depth && !config_used.empty()) {
      CCMD_ASSIGN_OR_RETURN(registration, LoadDepthToColorCalibration(config_used));
      CCMD_ASSIGN_OR_RETURN(T_color_trajectory, LoadTrajectoryCamera(config_used));
    }
    // Open once to count frames, then with the segment range.
    CCMD_ASSIGN_OR_RETURN(std::unique_ptr<RgbdSource> source,
                          DatasetSource::Open(argument, camera));
    CCMD_ASSIGN_OR_RETURN(const auto range, SegmentRange(source->FrameCount(), options));
    if (range) {
      CCMD_ASSIGN_OR_RETURN(source, DatasetSource::Open(argument, camera, range));
    }
    if (registration) {
      source =
          std::make_unique<ConfiguredSource>(std::move(source), registration, T_color_trajectory);
    }
    return source;
  }
  if (kind == "synth") {
    CCMD_ASSIGN_OR_RETURN(const SyntheticSequenceOptions synth, ParseSyntheticSpec(argument));
    CCMD_ASSIGN_OR_RETURN(const auto range, SegmentRange(synth.frames, options));
    return std::unique_ptr<RgbdSource>(new SyntheticSource(synth, range));
  }
  if (kind == "openni2") {
#ifdef CCMD_HAVE_OPENNI2
    return OpenOpenNI2(argument, options);
#else
    return Unsupported("this build has no OpenNI2 support (libopenni2-dev was not found)");
#endif
  }
  if (kind == "v4l2") {
#ifdef CCMD_HAVE_V4L2
    return OpenV4l2(argument, options);
#else
    return Unsupported("this build has no V4L2 support (Linux only)");
#endif
  }
  return InvalidArgument("unknown source '" + spec +
                         "' (expected tum:DIR, synth[:options], openni2[:URI] or "
                         "v4l2:color=DEV,depth=DEV[,...])");
}

}  // namespace ccmd
