#include "libccmd/io/config.h"

#include <cmath>
#include <cstdio>
#include <opencv2/core.hpp>

#include "libccmd/util/file_util.h"

namespace ccmd {

ConfigFile::~ConfigFile() = default;
ConfigFile::ConfigFile(ConfigFile&&) noexcept = default;
ConfigFile& ConfigFile::operator=(ConfigFile&&) noexcept = default;

StatusOr<ConfigFile> ConfigFile::Open(const std::string& path) {
  if (!FileExists(path)) return NotFound("config file " + path + " does not exist");
  ConfigFile config;
  config.path_ = path;
  config.storage_ = std::make_unique<cv::FileStorage>();
  try {
    if (!config.storage_->open(path, cv::FileStorage::READ | cv::FileStorage::FORMAT_YAML)) {
      return Corrupt("cannot parse config file " + path);
    }
  } catch (const cv::Exception& e) {
    return Corrupt("cannot parse config file " + path + ": " + e.msg);
  }
  return config;
}

bool ConfigFile::Has(const std::string& key) const {
  return !(*storage_)[key].empty() && !(*storage_)[key].isNone();
}

StatusOr<double> ConfigFile::GetDouble(const std::string& key, double fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (!node.isReal() && !node.isInt()) {
    return InvalidArgument(path_ + ": " + key + " must be a number");
  }
  return static_cast<double>(node.real());
}

StatusOr<int> ConfigFile::GetInt(const std::string& key, int fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (node.isInt()) return static_cast<int>(node);
  if (node.isReal()) {
    const double value = node.real();
    if (value == static_cast<int>(value)) return static_cast<int>(value);
  }
  return InvalidArgument(path_ + ": " + key + " must be an integer");
}

StatusOr<std::string> ConfigFile::GetString(const std::string& key,
                                            const std::string& fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (!node.isString()) return InvalidArgument(path_ + ": " + key + " must be a string");
  return static_cast<std::string>(node);
}

namespace {

// ORB-SLAM2 uses "Camera.fx", ORB-SLAM3's newer files "Camera1.fx".
StatusOr<double> GetCameraValue(const ConfigFile& config, const std::string& name,
                                double fallback) {
  if (config.Has("Camera." + name)) return config.GetDouble("Camera." + name, fallback);
  return config.GetDouble("Camera1." + name, fallback);
}

}  // namespace

StatusOr<PinholeCamera> ReadCamera(const ConfigFile& config) {
  PinholeCamera camera;
  for (const char* key : {"fx", "fy", "cx", "cy"}) {
    if (!config.Has(std::string("Camera.") + key) && !config.Has(std::string("Camera1.") + key)) {
      return InvalidArgument(config.path() + ": Camera." + key + " is missing");
    }
  }
  CCMD_ASSIGN_OR_RETURN(camera.fx, GetCameraValue(config, "fx", 0));
  CCMD_ASSIGN_OR_RETURN(camera.fy, GetCameraValue(config, "fy", 0));
  CCMD_ASSIGN_OR_RETURN(camera.cx, GetCameraValue(config, "cx", 0));
  CCMD_ASSIGN_OR_RETURN(camera.cy, GetCameraValue(config, "cy", 0));
  CCMD_ASSIGN_OR_RETURN(camera.width, config.GetInt("Camera.width", 640));
  CCMD_ASSIGN_OR_RETURN(camera.height, config.GetInt("Camera.height", 480));
  CCMD_ASSIGN_OR_RETURN(camera.fps, config.GetDouble("Camera.fps", 30.0));
  CCMD_ASSIGN_OR_RETURN(camera.depth_map_factor, config.GetDouble("DepthMapFactor", 5000.0));
  const char* distortion_keys[5] = {"k1", "k2", "p1", "p2", "k3"};
  for (int i = 0; i < 5; ++i) {
    CCMD_ASSIGN_OR_RETURN(camera.distortion[i], GetCameraValue(config, distortion_keys[i], 0.0));
  }
  // ORB-SLAM: close points are those with depth < ThDepth * bf / fx (bf = baseline * fx).
  CCMD_ASSIGN_OR_RETURN(const double th_depth, config.GetDouble("ThDepth", 40.0));
  CCMD_ASSIGN_OR_RETURN(camera.bf, config.GetDouble("Camera.bf", 40.0));
  if (!(camera.bf > 0)) return InvalidArgument(config.path() + ": Camera.bf must be positive");
  camera.far_depth_m = th_depth * camera.bf / std::fabs(camera.fx);
  std::string why;
  if (!camera.IsValid(&why)) return InvalidArgument(config.path() + ": " + why);
  return camera;
}

StatusOr<PinholeCamera> LoadCameraConfig(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const ConfigFile config, ConfigFile::Open(path));
  return ReadCamera(config);
}

Status WriteCameraConfig(const PinholeCamera& camera, const std::string& path) {
  char text[1024];
  // ThDepth chosen so that ThDepth * bf / fx reproduces far_depth_m.
  std::snprintf(text, sizeof(text),
                "%%YAML:1.0\n"
                "Camera.type: \"PinHole\"\n"
                "Camera.fx: %.6f\nCamera.fy: %.6f\nCamera.cx: %.6f\nCamera.cy: %.6f\n"
                "Camera.k1: %.6f\nCamera.k2: %.6f\nCamera.p1: %.6f\nCamera.p2: %.6f\n"
                "Camera.k3: %.6f\n"
                "Camera.width: %d\nCamera.height: %d\nCamera.fps: %.3f\n"
                "Camera.bf: %.6f\nThDepth: %.6f\nDepthMapFactor: %.3f\nCamera.RGB: 1\n",
                camera.fx, camera.fy, camera.cx, camera.cy, camera.distortion[0],
                camera.distortion[1], camera.distortion[2], camera.distortion[3],
                camera.distortion[4], camera.width, camera.height, camera.fps,
                camera.bf, camera.far_depth_m * std::fabs(camera.fx) / camera.bf,
                camera.depth_map_factor);
  return WriteFileAtomic(path, text);
}

}  // namespace ccmd
