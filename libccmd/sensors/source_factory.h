#pragma once

// Opens a source from its command-line spec:
//   tum:DIR         a TUM-layout folder (TUM RGB-D, ICL-NUIM, 7-Scenes converted, ccmd_synth)
//   synth[:k=v,..]  the synthetic room rendered on the fly (frames, seed, width, height, noise)
//   openni2         the first OpenNI2 device (Xtion, Astra, ...)
//   openni2:URI     a named OpenNI2 device (URI from ccmd_camera --list), or a .oni recording
//   v4l2:color=/dev/videoN,depth=/dev/videoM[,config=FILE][,width=640,height=480,fps=30]
//        [,color_width=W,color_height=H][,color_format=auto|yuyv|mjpeg][,depth_unit=0.001]
//        [,timeout=2][,pair_tolerance=S][,buffers=4]
//                   two V4L2 nodes of one camera (a RealSense D435: its RGB node and its
//                   Z16 depth node); see docs/cameras.md.
// Live cameras take their mode and intrinsics from the camera config (--config, or config=
// in the v4l2 spec); v4l2 falls back to configs/realsense_d435_v4l2.yaml (typical values,
// with the depth-to-colour registration block), openni2 to the device's field of view at
// 640x480, 30 fps.

#include <memory>
#include <optional>
#include <string>

#include "libccmd/io/split.h"
#include "libccmd/sensors/retrying_source.h"
#include "libccmd/sensors/rgbd_source.h"
#include "libccmd/util/options_writer.h"

namespace ccmd {

struct SourceOptions {
  std::string camera_config;                   // YAML; empty: the dataset's camera.yaml or a guess
  std::optional<std::pair<int, int>> segment;  // (i, k): replay segment i of k (1-based)
  double segment_overlap = 0.1;
  std::string configs_dir;  // where shipped configs live, for guesses
  // Recorded sequences: register depth to colour when the camera config has a Depth block.
  // false gives the frames as recorded (the benchmark's reference runs on them too).
  bool register_depth = true;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

StatusOr<std::unique_ptr<RgbdSource>> OpenSource(const std::string& spec,
                                                 const SourceOptions& options);

// The config file a recorded sequence (tum:DIR, or DIR itself) is read with: the one given
// (options.camera_config), else the folder's camera.yaml, else the shipped config its name or
// layout points to (GuessCameraConfigName, in options.configs_dir); "" when there is none.
// Its camera is the source's, and the programs take their tracking and sensor options (depth
// noise, ...) from the same file, so a guessed config counts as a given one.
std::string DatasetConfigPath(const std::string& folder, const SourceOptions& options);
// The config file the source of `spec` is opened with: DatasetConfigPath for a recorded
// sequence, options.camera_config for anything else.
std::string SourceConfigPath(const std::string& spec, const SourceOptions& options);

// Like OpenSource, but a live camera comes wrapped in a RetryingSource (retrying_source.h):
// when it fails with Unavailable it is reopened with backoff instead of ending the run.
// Datasets and synthetic sources are returned as they are.
StatusOr<std::unique_ptr<RgbdSource>> OpenSourceWithRetry(const std::string& spec,
                                                          const SourceOptions& options,
                                                          const RetryOptions& retry = {});

}  // namespace ccmd
