#include "libccmd/io/config.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <limits>
#include <opencv2/core.hpp>

#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

ConfigFile::~ConfigFile() = default;
ConfigFile::ConfigFile(ConfigFile&&) noexcept = default;
ConfigFile& ConfigFile::operator=(ConfigFile&&) noexcept = default;

namespace {

// cv::FileStorage parses nested collections recursively, so a file nesting some 20 000 levels
// ("[[[[...", "- - - ...", "a: a: a: ...") overflows the stack. Every level needs a bracket
// or a block indicator ("- ", ": "), so their count bounds the depth: a config holds a few
// dozen keys, and more than kMaxConfigTokens of them all is refused before parsing.
constexpr int kMaxConfigTokens = 4096;
constexpr std::uint64_t kMaxConfigBytes = 16 << 20;

int CountNestingTokens(const std::string& text) {
  int count = 0;
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    // Followed by a space, a line end, any control character or the end: counted.
    const auto next = i + 1 < text.size() ? static_cast<unsigned char>(text[i + 1]) : 0;
    if (c == '[' || c == '{' || ((c == '-' || c == ':') && next <= ' ')) ++count;
  }
  return count;
}

// The file's text, at most kMaxConfigBytes of it. Only a regular file: a program reads its
// config more than once (camera, depth block, tracking options), and a pipe (a shell's
// <(...)) would be empty the second time, or block.
StatusOr<std::string> ReadConfigText(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return InvalidArgument("config file " + path +
                           " is not a regular file (a config is read more than once: give a "
                           "file, not a pipe)");
  }
  return ReadFileToString(path, kMaxConfigBytes);
}

}  // namespace

StatusOr<ConfigFile> ConfigFile::Open(const std::string& path) {
  if (!FileExists(path)) return NotFound("config file " + path + " does not exist");
  CCMD_ASSIGN_OR_RETURN(const std::string text, ReadConfigText(path));
  if (const int tokens = CountNestingTokens(text); tokens > kMaxConfigTokens) {
    return Corrupt("config file " + path + " has " + std::to_string(tokens) +
                   " keys, list items and brackets; a config has at most " +
                   std::to_string(kMaxConfigTokens));
  }
  // OpenCV's base64 reader (the "!!binary" tag) can loop for ever on bytes that are not base64
  // (OpenCV 4.6: a line of 80 0xFF bytes). A camera config writes its numbers and matrices as
  // text, so the tag is refused before parsing.
  if (text.find("!!binary") != std::string::npos) {
    return Corrupt("config file " + path +
                   " has a base64 (!!binary) value; write numbers and matrices as text "
                   "(\"Camera.fx: 525.0\", \"data: [1.0, 0.0, ...]\")");
  }
  ConfigFile config;
  config.path_ = path;
  config.text_ = text;
  config.storage_ = std::make_unique<cv::FileStorage>();
  try {
    // Parsed from the text read above: the file is read once, and what was checked is what
    // is parsed.
    if (!config.storage_->open(
            text, cv::FileStorage::READ | cv::FileStorage::MEMORY | cv::FileStorage::FORMAT_YAML)) {
      return Corrupt("cannot parse config file " + path);
    }
  } catch (const cv::Exception& e) {
    return Corrupt("cannot parse config file " + path + ": " + e.msg);
  }
  // Looking a key up throws unless the top level maps keys to values (a list such as "- 1"
  // does not): found out here, so that the getters need no exception handling.
  try {
    (void)(*config.storage_)["Camera.fx"];
  } catch (const cv::Exception&) {
    return Corrupt("config file " + path +
                   ": the top level must be keys with values (\"Camera.fx: 525.0\"), not a list");
  }
  return config;
}

bool ConfigFile::Has(const std::string& key) const {
  return !(*storage_)[key].empty() && !(*storage_)[key].isNone();
}

std::optional<double> ConfigFile::DecimalLiteral(const std::string& key) const {
  std::size_t at = 0;
  while ((at = text_.find(key, at)) != std::string::npos) {
    const std::size_t line = text_.rfind('\n', at);
    const std::size_t start = line == std::string::npos ? 0 : line + 1;
    const bool indented_only =
        text_.find_first_not_of(" \t", start) == at;  // the key opens its line
    std::size_t i = at + key.size();
    at = i;
    if (!indented_only) continue;
    while (i < text_.size() && (text_[i] == ' ' || text_[i] == '\t')) ++i;
    if (i >= text_.size() || text_[i] != ':') continue;
    ++i;
    while (i < text_.size() && (text_[i] == ' ' || text_[i] == '\t')) ++i;
    std::size_t end = i;
    if (end < text_.size() && (text_[end] == '-' || text_[end] == '+')) ++end;
    const std::size_t digits = end;
    while (end < text_.size() && std::isdigit(static_cast<unsigned char>(text_[end]))) ++end;
    if (end == digits) return std::nullopt;
    const std::size_t after = text_.find_first_not_of(" \t\r", end);
    if (after != std::string::npos && text_[after] != '\n' && text_[after] != '#')
      return std::nullopt;
    return std::strtod(text_.substr(i, end - i).c_str(), nullptr);
  }
  return std::nullopt;
}

StatusOr<double> ConfigFile::GetDouble(const std::string& key, double fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (!node.isReal() && !node.isInt()) {
    return InvalidArgument(path_ + ": " + key + " must be a number");
  }
  if (node.isInt()) {
    if (const auto literal = DecimalLiteral(key)) return *literal;
  }
  return static_cast<double>(node.real());
}

StatusOr<int> ConfigFile::GetInt(const std::string& key, int fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (node.isInt()) {
    const int value = static_cast<int>(node);
    const auto literal = DecimalLiteral(key);
    if (!literal || *literal == value) return value;
  } else if (node.isReal()) {
    // Range first: converting NaN, infinities or numbers beyond int is undefined.
    const double value = node.real();
    if (value >= std::numeric_limits<int>::min() && value <= std::numeric_limits<int>::max() &&
        value == std::trunc(value)) {
      return static_cast<int>(value);
    }
  }
  return InvalidArgument(path_ + ": " + key + " must be an integer from -2147483648 to 2147483647");
}

StatusOr<std::string> ConfigFile::GetString(const std::string& key,
                                            const std::string& fallback) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return fallback;
  if (!node.isString()) return InvalidArgument(path_ + ": " + key + " must be a string");
  return static_cast<std::string>(node);
}

StatusOr<std::optional<std::vector<double>>> ConfigFile::GetNumbers(const std::string& key,
                                                                    std::size_t count) const {
  const cv::FileNode node = (*storage_)[key];
  if (node.empty() || node.isNone()) return std::optional<std::vector<double>>();
  const std::string what = path_ + ": " + key;
  if (!node.isSeq() || node.size() != count) {
    return InvalidArgument(what + " must be a list of " + std::to_string(count) + " numbers");
  }
  std::vector<double> values;
  for (const cv::FileNode& item : node) {
    if (!item.isReal() && !item.isInt()) return InvalidArgument(what + " must hold numbers");
    values.push_back(item.real());
    if (!std::isfinite(values.back())) return InvalidArgument(what + " must hold finite numbers");
  }
  return std::optional<std::vector<double>>(std::move(values));
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
  const std::string& path = config.path();
  for (const char* key : {"fx", "fy", "cx", "cy"}) {
    if (!config.Has(std::string("Camera.") + key) && !config.Has(std::string("Camera1.") + key)) {
      return InvalidArgument(path + ": Camera." + key + " is missing");
    }
  }
  // Each value is checked where it is read, so that the message names the key.
  auto finite = [&](const char* key, double value, bool non_zero) -> Status {
    if (!std::isfinite(value))
      return InvalidArgument(path + ": " + key + " must be a finite number");
    if (non_zero && value == 0) return InvalidArgument(path + ": " + key + " must not be zero");
    return Status::Ok();
  };
  const char* keys[4] = {"fx", "fy", "cx", "cy"};
  double* values[4] = {&camera.fx, &camera.fy, &camera.cx, &camera.cy};
  for (int i = 0; i < 4; ++i) {
    CCMD_ASSIGN_OR_RETURN(*values[i], GetCameraValue(config, keys[i], 0));
    CCMD_RETURN_IF_ERROR(finite((std::string("Camera.") + keys[i]).c_str(), *values[i], i < 2));
  }
  CCMD_ASSIGN_OR_RETURN(camera.width, config.GetInt("Camera.width", 640));
  CCMD_ASSIGN_OR_RETURN(camera.height, config.GetInt("Camera.height", 480));
  CCMD_ASSIGN_OR_RETURN(camera.fps, config.GetDouble("Camera.fps", 30.0));
  CCMD_ASSIGN_OR_RETURN(camera.depth_map_factor, config.GetDouble("DepthMapFactor", 5000.0));
  if (!(camera.depth_map_factor > 0) || !std::isfinite(camera.depth_map_factor)) {
    return InvalidArgument(path +
                           ": DepthMapFactor must be a positive finite number (units per metre)");
  }
  const char* distortion_keys[5] = {"k1", "k2", "p1", "p2", "k3"};
  for (int i = 0; i < 5; ++i) {
    CCMD_ASSIGN_OR_RETURN(camera.distortion[i], GetCameraValue(config, distortion_keys[i], 0.0));
    CCMD_RETURN_IF_ERROR(
        finite((std::string("Camera.") + distortion_keys[i]).c_str(), camera.distortion[i], false));
  }
  CCMD_ASSIGN_OR_RETURN(const int rgb, config.GetInt("Camera.RGB", 1));
  if (rgb != 0 && rgb != 1)
    return InvalidArgument(path + ": Camera.RGB must be 0 (BGR files) or 1 (RGB files)");
  camera.rgb = rgb == 1;
  // ORB-SLAM: close points are those with depth < ThDepth * bf / fx (bf = baseline * fx).
  CCMD_ASSIGN_OR_RETURN(const double th_depth, config.GetDouble("ThDepth", 40.0));
  CCMD_ASSIGN_OR_RETURN(camera.bf, config.GetDouble("Camera.bf", 40.0));
  if (!(camera.bf > 0) || !std::isfinite(camera.bf)) {
    return InvalidArgument(path + ": Camera.bf must be a positive finite number");
  }
  if (!(th_depth > 0) || !std::isfinite(th_depth)) {
    return InvalidArgument(path + ": ThDepth must be a positive finite number");
  }
  camera.far_depth_m = th_depth * camera.bf / std::fabs(camera.fx);
  CCMD_RETURN_IF_ERROR(camera.ValidateInvertible().WithContext(path));
  return camera;
}

StatusOr<PinholeCamera> LoadCameraConfig(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const ConfigFile config, ConfigFile::Open(path));
  return ReadCamera(config);
}

StatusOr<std::optional<DepthToColorCalibration>> ReadDepthToColor(const ConfigFile& config) {
  const std::string& path = config.path();
  if (!config.Has("Depth.fx")) return std::optional<DepthToColorCalibration>();
  DepthToColorCalibration calibration;
  PinholeCamera& depth = calibration.depth;
  const char* keys[6] = {"Depth.fx", "Depth.fy",    "Depth.cx",
                         "Depth.cy", "Depth.width", "Depth.height"};
  double values[6];
  for (int i = 0; i < 6; ++i) {
    if (!config.Has(keys[i])) return InvalidArgument(path + ": " + keys[i] + " is missing");
    CCMD_ASSIGN_OR_RETURN(values[i], config.GetDouble(keys[i], 0));
    if (!std::isfinite(values[i]))
      return InvalidArgument(path + ": " + keys[i] + " must be a finite number");
  }
  depth.fx = values[0];
  depth.fy = values[1];
  depth.cx = values[2];
  depth.cy = values[3];
  if (values[4] != std::floor(values[4]) || values[5] != std::floor(values[5])) {
    return InvalidArgument(path + ": Depth.width and Depth.height must be whole numbers");
  }
  depth.width = static_cast<int>(std::clamp(values[4], -1.0, 1e6));
  depth.height = static_cast<int>(std::clamp(values[5], -1.0, 1e6));
  depth.depth_map_factor = 1000.0;  // registration works on millimetres
  CCMD_RETURN_IF_ERROR(depth.Validate().WithContext(path + ": Depth block"));

  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  CCMD_ASSIGN_OR_RETURN(const auto r, config.GetNumbers("Depth.R_color_depth", 9));
  if (r) {
    for (int i = 0; i < 9; ++i) R(i / 3, i % 3) = (*r)[i];
    // A calibration printed with a few decimals is only nearly orthonormal; a matrix far
    // from a rotation is a typo (or a transposed/garbled copy).
    if ((R * R.transpose() - Eigen::Matrix3d::Identity()).norm() > 1e-2 || R.determinant() < 0) {
      return InvalidArgument(path + ": Depth.R_color_depth is not a rotation");
    }
  }
  CCMD_ASSIGN_OR_RETURN(const auto v, config.GetNumbers("Depth.t_color_depth", 3));
  if (v) {
    t = Eigen::Vector3d((*v)[0], (*v)[1], (*v)[2]);
    if (t.norm() > 1.0) {
      return InvalidArgument(path + ": Depth.t_color_depth is " + std::to_string(t.norm()) +
                             " m long; it is in metres");
    }
  }
  calibration.T_color_depth.linear() = R;
  calibration.T_color_depth.translation() = t;
  calibration.T_color_depth = Orthonormalized(calibration.T_color_depth);
  return std::optional<DepthToColorCalibration>(calibration);
}

StatusOr<std::optional<DepthToColorCalibration>> LoadDepthToColorCalibration(
    const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const ConfigFile config, ConfigFile::Open(path));
  return ReadDepthToColor(config);
}

StatusOr<Pose> ReadTrajectoryCamera(const ConfigFile& config) {
  CCMD_ASSIGN_OR_RETURN(const std::string camera, config.GetString("Trajectory.camera", "colour"));
  if (camera == "colour" || camera == "color") return Pose::Identity();
  if (camera != "depth") {
    return InvalidArgument(config.path() + ": Trajectory.camera is \"" + camera +
                           "\"; it must be \"colour\" or \"depth\"");
  }
  CCMD_ASSIGN_OR_RETURN(const auto depth, ReadDepthToColor(config));
  if (!depth) {
    return InvalidArgument(config.path() +
                           ": Trajectory.camera is \"depth\" but there is no Depth block");
  }
  return depth->T_color_depth;
}

StatusOr<Pose> LoadTrajectoryCamera(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(const ConfigFile config, ConfigFile::Open(path));
  return ReadTrajectoryCamera(config);
}

Status WriteCameraConfig(const PinholeCamera& camera, const std::string& path,
                         const std::optional<DepthToColorCalibration>& depth,
                         const std::string& extra_keys) {
  // Every real as the shortest text that reads back as the same double, so a camera written
  // and read again is the same camera, however large or small its values.
  std::string out = "%YAML:1.0\nCamera.type: \"PinHole\"\n";
  const auto key = [&out](const char* name, double value) {
    out += std::string(name) + ": " + ExactNumber(value) + "\n";
  };
  key("Camera.fx", camera.fx);
  key("Camera.fy", camera.fy);
  key("Camera.cx", camera.cx);
  key("Camera.cy", camera.cy);
  const char* distortion_keys[] = {"Camera.k1", "Camera.k2", "Camera.p1", "Camera.p2", "Camera.k3"};
  for (int i = 0; i < 5; ++i) key(distortion_keys[i], camera.distortion[i]);
  out += "Camera.width: " + std::to_string(camera.width) + "\n";
  out += "Camera.height: " + std::to_string(camera.height) + "\n";
  key("Camera.fps", camera.fps);
  key("Camera.bf", camera.bf);
  // ThDepth: the shortest value that the reader's ThDepth * bf / |fx| turns back into
  // far_depth_m exactly (a config's ThDepth: 100 must not come back as 99.99999999999999,
  // whose far depth differs in the last bit).
  const double th_depth = camera.far_depth_m * std::fabs(camera.fx) / camera.bf;
  std::string th_text = ExactNumber(th_depth);
  for (int digits = 1; digits <= 17; ++digits) {
    char text[40];
    std::snprintf(text, sizeof(text), "%.*g", digits, th_depth);
    const double rounded = std::strtod(text, nullptr);
    if (rounded * camera.bf / std::fabs(camera.fx) == camera.far_depth_m) {
      th_text = ExactNumber(rounded);  // "100", not "1e+02"
      break;
    }
  }
  out += "ThDepth: " + th_text + "\n";
  key("DepthMapFactor", camera.depth_map_factor);
  out += std::string("Camera.RGB: ") + (camera.rgb ? "1" : "0") + "\n";
  if (depth) {
    const PinholeCamera& d = depth->depth;
    key("Depth.fx", d.fx);
    key("Depth.fy", d.fy);
    key("Depth.cx", d.cx);
    key("Depth.cy", d.cy);
    out += "Depth.width: " + std::to_string(d.width) + "\n";
    out += "Depth.height: " + std::to_string(d.height) + "\n";
    const auto list = [](const double* values, int count) {
      std::string text = "[";
      for (int i = 0; i < count; ++i) text += (i ? ", " : "") + ExactNumber(values[i]);
      return text + "]\n";
    };
    const Eigen::Matrix<double, 3, 3, Eigen::RowMajor> R = depth->T_color_depth.linear();
    const Eigen::Vector3d t = depth->T_color_depth.translation();
    out += "Depth.R_color_depth: " + list(R.data(), 9);
    out += "Depth.t_color_depth: " + list(t.data(), 3);
  }
  return WriteFileAtomic(path, out + extra_keys);
}

}  // namespace ccmd
