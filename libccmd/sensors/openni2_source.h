#pragma once

// OpenNI2 depth cameras (PrimeSense/Asus Xtion, Orbbec Astra, Kinect via its OpenNI2 driver)
// and .oni recordings, through the OpenNI2 C++ API (OpenCV in Debian is built without it).
//
// Spec (through OpenSource): "openni2" opens the first device, "openni2:URI" a named one
// (the URI ccmd_camera --list prints), "openni2:/path/file.oni" plays a recording through
// OpenNI2's file driver. The mode (width, height, fps) comes from the camera config when one
// is given, else 640x480 at 30 fps (or the device's default mode if it has no such mode).
//
// The device is set up for RGB-D SLAM: colour and depth streams at the same mode, depth
// registered to colour (when the device can), hardware frame sync, mirroring off. Depth is
// converted to millimetres (DEPTH_1_MM as is, DEPTH_100_UM rounded), device timestamps
// (microseconds) to seconds; colour and depth are paired by timestamp.
//
// Failures: no device -> NotFound; device present but cannot be opened (in use) or silent
// for `timeout_s` -> Unavailable (RetryingSource reopens); mode or pixel format not offered
// -> Unsupported. A recording ends with EndOfStream.

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "libccmd/sensors/rgbd_source.h"

namespace ccmd {

struct OpenNI2Options {
  std::string uri;  // empty: the first device; ends in ".oni": a recording
  // The mode. width = 0: 640x480 at 30 fps if the device has it, else the depth stream's
  // default mode.
  int width = 0;
  int height = 0;
  double fps = 30.0;
  bool register_depth = true;  // depth to colour, if the device supports it
  bool sync = true;            // hardware colour/depth frame sync
  double timeout_s = 2.0;
  double pair_tolerance_s = 0.0;  // 0 = half a frame period
  // Intrinsics of the (registered) depth image; without one they are computed from the
  // field of view the device reports (pixel-centre convention, cx = width / 2 - 0.5).
  std::optional<PinholeCamera> camera;
};

class OpenNI2Source : public RgbdSource {
 public:
  static StatusOr<std::unique_ptr<OpenNI2Source>> Open(const OpenNI2Options& options);
  ~OpenNI2Source() override;

  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return camera_; }
  std::string Describe() const override { return description_; }
  int FrameCount() const override { return frame_count_; }
  bool IsLive() const override { return !is_file_; }

  struct Stats {
    long frames = 0;
    long unpaired_dropped = 0;
    long damaged_dropped = 0;
  };
  const Stats& stats() const { return stats_; }
  long DroppedFrames() const override { return stats_.damaged_dropped + stats_.unpaired_dropped; }

 private:
  struct Impl;
  OpenNI2Source();
  Status Fail(Status status);

  std::unique_ptr<Impl> impl_;
  OpenNI2Options options_;
  PinholeCamera camera_;
  std::string description_;
  bool is_file_ = false;
  int frame_count_ = -1;
  int next_index_ = 0;
  double tolerance_ = 0;
  Status failed_;
  Stats stats_;
};

struct OpenNI2ModeInfo {
  std::string sensor;  // "depth", "colour", "ir"
  int width = 0;
  int height = 0;
  int fps = 0;
  std::string pixel_format;  // "DEPTH_1_MM", "RGB888", ...
};

struct OpenNI2DeviceInfo {
  std::string uri;
  std::string vendor;
  std::string name;
  int usb_vendor_id = 0;
  int usb_product_id = 0;
  bool registration_supported = false;
  std::vector<OpenNI2ModeInfo> modes;
  Status open_status;  // why modes are missing, if the device could not be opened
};

// Devices OpenNI2 sees now (opening each briefly to list its modes).
StatusOr<std::vector<OpenNI2DeviceInfo>> ListOpenNI2Devices();

}  // namespace ccmd
