#pragma once

// Configuration files in the ORB-SLAM YAML convention ("%YAML:1.0", keys such as
// Camera.fx, DepthMapFactor), read with cv::FileStorage.

#include <memory>
#include <string>

#include <optional>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/util/status.h"

namespace cv {
class FileStorage;
}

namespace ccmd {

// Read-only view of one YAML config file. Missing keys fall back to defaults; keys that
// exist but hold the wrong type are errors (reported by the typed getters' Status).
class ConfigFile {
 public:
  static StatusOr<ConfigFile> Open(const std::string& path);
  ~ConfigFile();
  ConfigFile(ConfigFile&&) noexcept;
  ConfigFile& operator=(ConfigFile&&) noexcept;

  const std::string& path() const { return path_; }
  bool Has(const std::string& key) const;

  // The value at `key` or `fallback` when absent. A present non-numeric value is an error.
  StatusOr<double> GetDouble(const std::string& key, double fallback) const;
  StatusOr<int> GetInt(const std::string& key, int fallback) const;
  StatusOr<std::string> GetString(const std::string& key, const std::string& fallback) const;
  // A list of exactly `count` numbers at `key`, nullopt when absent.
  StatusOr<std::optional<std::vector<double>>> GetNumbers(const std::string& key,
                                                          std::size_t count) const;

 private:
  ConfigFile() = default;
  // The number a YAML integer at `key` was written as, when the file gives it as one plain
  // decimal literal on the key's own line: OpenCV reads such a literal into an int and wraps
  // one beyond int's range ("4294967936" reads as 640), so the text says what was meant.
  std::optional<double> DecimalLiteral(const std::string& key) const;

  std::string path_;
  std::string text_;
  std::unique_ptr<cv::FileStorage> storage_;
};

// Reads the camera block: Camera.fx/fy/cx/cy (or ORB-SLAM3's Camera1.*; either focal length
// may be negative), Camera.width, Camera.height, Camera.fps, DepthMapFactor, the distortion
// Camera.k1 k2 p1 p2 k3, the colour order Camera.RGB, and the far-point threshold
// ThDepth * Camera.bf / |fx| (ORB-SLAM's definition). Zero, NaN or infinite values where a
// number must be usable are errors naming the key.
StatusOr<PinholeCamera> ReadCamera(const ConfigFile& config);
StatusOr<PinholeCamera> LoadCameraConfig(const std::string& path);

// Cameras whose depth comes from another imager than colour: the depth camera and where it
// sits relative to the colour camera (Camera.*). Depth is registered into the colour image
// as it is read (sensors/depth_registration.h).
struct DepthToColorCalibration {
  PinholeCamera depth;                    // intrinsics of the depth image, at its calibrated size
  Pose T_color_depth = Pose::Identity();  // maps depth-camera points into the colour frame
};

// Reads the optional depth block of a camera config (the colour camera being Camera.*):
//   Depth.fx, Depth.fy, Depth.cx, Depth.cy, Depth.width, Depth.height
//   Depth.R_color_depth: [9 numbers, row-major]   (default identity)
//   Depth.t_color_depth: [tx, ty, tz] in metres    (default zero)
// Returns nullopt if the file has no Depth.fx (no registration wanted).
StatusOr<std::optional<DepthToColorCalibration>> ReadDepthToColor(const ConfigFile& config);
StatusOr<std::optional<DepthToColorCalibration>> LoadDepthToColorCalibration(
    const std::string& path);

// Reads Trajectory.camera: the camera whose poses trajectory files give. "colour" (the
// default; "color" too): the colour camera, whose poses tracking estimates. "depth": the
// Depth block's camera (which must be there), for recordings whose ground truth gives the
// depth camera's poses (7-Scenes, posed by dense tracking on its depth images). Returns that
// camera's pose in the colour camera's frame (T_color_trajectory, identity for "colour").
StatusOr<Pose> ReadTrajectoryCamera(const ConfigFile& config);
StatusOr<Pose> LoadTrajectoryCamera(const std::string& path);

// Writes a camera (and its depth block, if given) as an ORB-SLAM style YAML file that
// ReadCamera and ReadDepthToColor read back unchanged (used by ccmd_synth and --record).
// `extra_keys` (whole lines, e.g. a sensor's DepthNoise keys) are appended as they are.
Status WriteCameraConfig(const PinholeCamera& camera, const std::string& path,
                         const std::optional<DepthToColorCalibration>& depth = std::nullopt,
                         const std::string& extra_keys = "");

}  // namespace ccmd
