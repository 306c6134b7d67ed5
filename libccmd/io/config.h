#pragma once

// Configuration files in the ORB-SLAM YAML convention ("%YAML:1.0", keys such as
// Camera.fx, DepthMapFactor), read with cv::FileStorage.

#include <memory>
#include <string>

#include "libccmd/geometry/camera.h"
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

 private:
  ConfigFile() = default;
  std::string path_;
  std::unique_ptr<cv::FileStorage> storage_;
};

// Reads the camera block: Camera.fx/fy/cx/cy (or ORB-SLAM3's Camera1.*), Camera.width,
// Camera.height, Camera.fps, DepthMapFactor, Camera.k1..k3/p1/p2 (kept, not applied),
// and the far-point threshold ThDepth * Camera.bf / fx (ORB-SLAM's definition).
StatusOr<PinholeCamera> ReadCamera(const ConfigFile& config);
StatusOr<PinholeCamera> LoadCameraConfig(const std::string& path);

// Writes a camera as an ORB-SLAM style YAML file (used by ccmd_synth and --record).
Status WriteCameraConfig(const PinholeCamera& camera, const std::string& path);

}  // namespace ccmd
