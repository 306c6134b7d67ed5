// Fuzz target: the YAML config reader (cv::FileStorage underneath) and everything that reads
// a config: the camera block, the depth-to-colour block, Trajectory.camera and the tracking
// options (DepthNoise.* included). The bytes go through a file, as a config does. Whatever is
// accepted must pass its own validation.

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "libccmd/io/config.h"
#include "libccmd/tracking/config.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  std::vector<std::vector<std::uint8_t>> seeds;
  for (const auto& entry : std::filesystem::directory_iterator(CCMD_CONFIG_DIR)) {
    if (entry.path().extension() != ".yaml") continue;
    std::ifstream in(entry.path(), std::ios::binary);
    seeds.emplace_back(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  if (seeds.empty()) FuzzFail("no seed configs in " CCMD_CONFIG_DIR);
  // The keys the configs/ files leave out: tracking options and a depth block with a pose.
  const std::string extra =
      "%YAML:1.0\n"
      "Camera.fx: 500.0\nCamera.fy: -500.0\nCamera.cx: 319.5\nCamera.cy: 239.5\n"
      "Camera.width: 640\nCamera.height: 480\nCamera.k1: 0.01\n"
      "ORBextractor.nFeatures: 1000\nORBextractor.scaleFactor: 1.2\nORBextractor.nLevels: 8\n"
      "ORBextractor.iniThFAST: 20\nORBextractor.minThFAST: 7\n"
      "Tracking.localBAWindow: 10\nTracking.localBAIterations: 5\n"
      "Tracking.localBARobustIterations: 5\nTracking.maxKeyframes: 200\n"
      "DepthNoise.sigma0: 0.002\nDepthNoise.sigma2: 0.0019\n"
      "RgbdSelection.enabled: 1\nRgbdSelection.thresholdRatio: 0.5\n"
      "Depth.fx: 580.0\nDepth.fy: 580.0\nDepth.cx: 320.0\nDepth.cy: 240.0\n"
      "Depth.width: 640\nDepth.height: 480\n"
      "Depth.R_color_depth: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n"
      "Depth.t_color_depth: [0.025, 0.0, 0.0]\n"
      "Trajectory.camera: \"depth\"\n";
  seeds.emplace_back(extra.begin(), extra.end());
  return seeds;
}

std::vector<std::vector<std::uint8_t>> FuzzRegressions() {
  const std::string texts[] = {
      // A top level that is a list, not keys: the first key lookup threw cv::Exception.
      "%YAML:1.0.type: \"Pin \n-H\xbaoTracking.depthAlignmentWeight:%YAML: -",
      "%YAML:1.0\n- 1\n",
      // An integer key holding a real beyond int (or NaN): converted unchecked (UBSan).
      "%YAML:1.0\nCamera.fx: 500.0\nCamera.fy: 500.0\nCamera.cx: 1.0\nCamera.cy: 1.0\n"
      "Camera.width: 1e30\n",
      "%YAML:1.0\nORBextractor.nFeatures: .nan\nCamera.height: -.inf\n",
      // Local BA iteration counts whose sum overflows int in TrackingOptions::Validate.
      "%YAML:1.0\nTracking.localBAIterations: 2147483647\n"
      "Tracking.localBARobustIterations: 2147483647\n",
      // A base64 value over a line of bytes that are not base64: OpenCV's reader looped for ever.
      "%YAML:1.0\nRgbdSelection.thresholdRatio:!!binary " + std::string(80, '\xff') + "\n",
  };
  std::vector<std::vector<std::uint8_t>> inputs;
  for (const std::string& t : texts) inputs.emplace_back(t.begin(), t.end());
  return inputs;
}

namespace {

// One file per process, removed at exit (kept alive for the exit handler).
const std::string& ScratchPath() {
  static const std::string* path = [] {
    auto* p = new std::string((std::filesystem::temp_directory_path() /
                               ("ccmd_fuzz_config_" + std::to_string(getpid()) + ".yaml"))
                                  .string());
    std::atexit([] { std::remove(ScratchPath().c_str()); });
    return p;
  }();
  return *path;
}

}  // namespace

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const std::string& path = fuzz::ScratchPath();
  {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
    if (!out) fuzz::FuzzFail("cannot write the scratch config");
  }
  StatusOr<ConfigFile> config = ConfigFile::Open(path);
  if (!config.ok()) return 0;
  if (auto camera = ReadCamera(*config); camera.ok() && !camera->Validate().ok()) {
    fuzz::FuzzFail("an accepted camera does not validate");
  }
  if (auto depth = ReadDepthToColor(*config); depth.ok() && depth->has_value()) {
    if (!(*depth)->depth.Validate().ok()) fuzz::FuzzFail("an accepted depth camera");
    if (!(*depth)->T_color_depth.matrix().allFinite()) fuzz::FuzzFail("depth pose not finite");
  }
  if (auto T = ReadTrajectoryCamera(*config); T.ok() && !T->matrix().allFinite()) {
    fuzz::FuzzFail("trajectory camera pose not finite");
  }
  if (auto options = ReadTrackingOptions(*config); options.ok() && !options->Validate().ok()) {
    fuzz::FuzzFail("accepted tracking options do not validate");
  }
  return 0;
}
