#pragma once

// A depth camera seen through V4L2 as two video nodes: colour (YUYV or MJPEG) and depth
// (Z16, how a RealSense D435 exposes its depth stream over UVC). Frames of the two nodes are
// paired by their driver timestamps, converted to BGR and millimetres, and colour larger
// than depth is resized to the depth resolution. Intrinsics come from a config file.
//
// Spec (through OpenSource, see source_factory.h):
//   v4l2:color=/dev/video4,depth=/dev/video2[,config=FILE][,width=640,height=480,fps=30]
//        [,color_width=W,color_height=H][,color_format=auto|yuyv|mjpeg][,depth_unit=0.001]
//        [,timeout=2][,pair_tolerance=S][,buffers=4]
//
// Failures: no node -> NotFound; busy, unplugged, silent for `timeout` s -> Unavailable
// (RetryingSource reopens); format/size not offered -> Unsupported, with what is offered.

#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/pixel_formats.h"
#include "libccmd/sensors/rgbd_source.h"
#include "libccmd/sensors/v4l2_device.h"

namespace ccmd {

struct V4l2SourceOptions {
  std::string color_device;  // e.g. /dev/video4
  std::string depth_device;  // e.g. /dev/video2
  std::string config;        // camera YAML (intrinsics of the depth image); may be empty
  int width = 640;           // depth stream size, and the size of every frame handed out
  int height = 480;
  double fps = 30.0;
  int color_width = 0;  // colour stream size; 0 = same as depth
  int color_height = 0;
  std::string color_format = "auto";  // auto (YUYV if offered, else MJPEG), yuyv, mjpeg
  double depth_unit_m = 0.001;        // metres per Z16 unit (D435 default: 1 mm)
  double timeout_s = 2.0;             // no frame for this long -> Unavailable
  double pair_tolerance_s = 0.0;      // 0 = half a frame period
  int buffers = 4;

  // "color=/dev/video4 depth=/dev/video2 640x480@30 ..." for logs.
  std::string ToString() const;
};

// Parses the part of a v4l2: spec after the colon.
StatusOr<V4l2SourceOptions> ParseV4l2Spec(const std::string& spec);

class V4l2Source : public RgbdSource {
 public:
  // Without `registration`, `camera` holds the intrinsics of the depth image; with it,
  // those of the colour image (and the registration those of depth). Intrinsics calibrated
  // at another size are rescaled, with a warning. `opener` opens a node (the real device
  // by default).
  static StatusOr<std::unique_ptr<V4l2Source>> Open(
      const V4l2SourceOptions& options, const PinholeCamera& camera,
      const V4l2DeviceOpener& opener = OpenLinuxV4l2Device,
      const std::optional<DepthToColorCalibration>& registration = std::nullopt);
  ~V4l2Source() override;

  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return camera_; }
  std::string Describe() const override;
  bool IsLive() const override { return true; }

  struct Stats {
    long frames = 0;            // pairs handed out
    long unpaired_dropped = 0;  // frames dropped because the other stream had no partner
    long damaged_dropped = 0;   // frames flagged by the driver or failing to decode
    long driver_gaps = 0;       // frames the driver skipped (sequence-number gaps)
  };
  const Stats& stats() const { return stats_; }
  long DroppedFrames() const override { return stats_.damaged_dropped + stats_.unpaired_dropped; }

 private:
  struct Stream {
    std::string role;  // "colour" or "depth"
    std::string path;
    std::unique_ptr<V4l2Device> device;
    V4l2Format format;
    bool held = false;  // `buffer` is dequeued and not yet given back
    V4l2Buffer buffer;
    bool seen_sequence = false;
    std::uint32_t last_sequence = 0;
  };

  V4l2Source() = default;
  static Status StartStream(const std::string& path, std::uint32_t fourcc, int width, int height,
                            const V4l2SourceOptions& options, Stream* stream);
  Status Fetch(Stream* stream);
  Status Release(Stream* stream);
  Status ConvertColor(const V4l2Buffer& buffer, cv::Mat* bgr);
  Status ConvertDepth(const V4l2Buffer& buffer, cv::Mat* depth_mm);
  // Device errors are sticky: after one, every Read returns it until the source is reopened.
  Status Fail(Status status);

  V4l2SourceOptions options_;
  PinholeCamera camera_;                                 // of the frames handed out
  std::optional<DepthToColorCalibration> registration_;  // depth intrinsics at stream size
  Stream color_;
  Stream depth_;
  MjpegDecoder mjpeg_;
  double tolerance_ = 0;
  int next_index_ = 0;
  Status failed_;
  Stats stats_;
};

// Chooses the colour format for `options.color_format` among the modes a node offers
// ("auto" prefers YUYV, which needs no decoding, then MJPEG).
StatusOr<std::uint32_t> ChooseColorFormat(const V4l2DeviceInfo& info, const std::string& wanted,
                                          int width, int height);

}  // namespace ccmd
