// ccmd_camera as a user runs it: listing without a camera, statistics, recording that the
// TUM reader replays frame for frame, and Ctrl-C during a recording.

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <opencv2/core.hpp>

#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

int RunCamera(const std::string& arguments, std::string* output) {
  return testing::RunCommand(testing::ProgramPath("ccmd_camera") + " " + arguments + " 2>&1",
                             output);
}

int CountListed(const std::string& path) {
  std::ifstream in(path);
  std::string line;
  int count = 0;
  while (std::getline(in, line)) count += !line.empty() && line[0] != '#';
  return count;
}

TEST(CameraCliTest, ListsWithoutACamera) {
  std::string output;
  ASSERT_EQ(RunCamera("--list", &output), 0) << output;
  EXPECT_NE(output.find("V4L2 video nodes:"), std::string::npos) << output;
  EXPECT_NE(output.find("OpenNI2 devices:"), std::string::npos) << output;
}

TEST(CameraCliTest, PrintsFrameStatistics) {
  std::string output;
  ASSERT_EQ(RunCamera("--source synth:frames=5,width=64,height=48 --frames 3", &output), 0)
      << output;
  EXPECT_NE(output.find("frame 2  t=1.066667 s  dt= 33.3 ms  colour 64x48  depth 64x48"),
            std::string::npos)
      << output;
  EXPECT_NE(output.find("3 frames over 0.067 s of device time"), std::string::npos) << output;
  EXPECT_NE(output.find("30.00 fps"), std::string::npos) << output;
}

TEST(CameraCliTest, ClearErrors) {
  std::string output;
  EXPECT_EQ(RunCamera("--frames 3", &output), 2) << output;
  EXPECT_EQ(
      RunCamera("--source v4l2:color=/dev/ccmd_no_video98,depth=/dev/ccmd_no_video99", &output), 1);
  EXPECT_NE(output.find("not found"), std::string::npos) << output;
  EXPECT_NE(output.find("plugged in"), std::string::npos) << output;
}

TEST(CameraCliTest, RecordingReplaysFrameForFrame) {
  testing::TempDir dir;
  const std::string folder = dir.File("rec");
  std::string output;
  ASSERT_EQ(RunCamera("--source synth:frames=4,width=64,height=48 --frames 4 --record " + folder,
                      &output),
            0)
      << output;
  EXPECT_NE(output.find("recorded 4 frames"), std::string::npos) << output;

  // The same frames rendered directly are the independent reference.
  auto options = ParseSyntheticSpec("frames=4,width=64,height=48");
  ASSERT_TRUE(options.ok());
  SyntheticSource reference(*options);
  auto sequence = TumSequence::Open(folder, std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_EQ(sequence->size(), 4u);
  for (std::size_t i = 0; i < 4; ++i) {
    RgbdFrame expected;
    ASSERT_TRUE(reference.Read(&expected).ok());
    auto loaded = sequence->LoadFrame(i);
    ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
    EXPECT_NEAR(loaded->timestamp, expected.timestamp, 0.5e-6);
    EXPECT_EQ(cv::norm(loaded->bgr, expected.bgr, cv::NORM_INF), 0) << i;
    EXPECT_EQ(cv::norm(loaded->depth_mm, expected.depth_mm, cv::NORM_INF), 0) << i;
  }
  EXPECT_EQ(sequence->GroundTruthAtFrames().size(), 4u);
}

// Re-recording a recording with a damaged frame: the frame is dropped and counted, the others
// are recorded as they were.
TEST(CameraCliTest, ADamagedFrameIsDroppedAndCounted) {
  testing::TempDir dir;
  std::string output;
  ASSERT_EQ(
      RunCamera("--source synth:frames=4,width=64,height=48 --frames 4 --record " + dir.File("rec"),
                &output),
      0)
      << output;
  auto sequence = TumSequence::Open(dir.File("rec"), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_EQ(std::remove(sequence->frame(2).depth_path.c_str()), 0);
  ASSERT_EQ(
      RunCamera("--source tum:" + dir.File("rec") + " --frames 4 --record " + dir.File("again"),
                &output),
      0)
      << output;
  EXPECT_NE(output.find("damaged, unreadable or unpaired: 1"), std::string::npos) << output;
  EXPECT_NE(output.find("recorded 3 frames"), std::string::npos) << output;
  EXPECT_EQ(CountListed(dir.File("again/depth.txt")), 3);
}

// A recording carries the depth noise of the config its camera was opened with (a D435's,
// here), so that replaying the folder without --config tracks with the same sensor model:
// before, its camera.yaml held the camera only, and the replay fell back to a Kinect's noise.
TEST(CameraCliTest, ARecordingKeepsTheSensorsDepthNoise) {
  testing::TempDir dir;
  const auto recorded_noise = [&dir](const std::string& folder) -> StatusOr<DepthNoise> {
    CCMD_ASSIGN_OR_RETURN(const ConfigFile file,
                          ConfigFile::Open(dir.File(folder + "/camera.yaml")));
    return ReadDepthNoise(file, DepthNoise{0.1, 0.1, 9});
  };
  std::string output;
  ASSERT_EQ(RunCamera("--source synth:frames=3,width=64,height=48 --frames 3 --record " +
                          dir.File("first"),
                      &output),
            0)
      << output;
  // A camera opened without a config: the recording states the default the agent tracks with.
  auto first = recorded_noise("first");
  ASSERT_TRUE(first.ok()) << first.status().ToString();
  EXPECT_EQ(first->sigma_0, DepthNoise().sigma_0);
  EXPECT_EQ(first->sigma_2, DepthNoise().sigma_2);

  // The same camera with a D435's noise in its config.
  auto text = ReadFileToString(dir.File("first/camera.yaml"));
  ASSERT_TRUE(text.ok());
  std::string config;
  for (const std::string& line : Split(*text, '\n')) {
    if (!line.empty() && !StartsWith(line, "DepthNoise.")) config += line + "\n";
  }
  config += "DepthNoise.sigma0: 0.001\nDepthNoise.sigma2: 0.004\nDepthNoise.keypointOffset: 0.5\n";
  ASSERT_TRUE(WriteFileAtomic(dir.File("d435.yaml"), config).ok());
  ASSERT_EQ(RunCamera("--source tum:" + dir.File("first") + " --config " + dir.File("d435.yaml") +
                          " --frames 3 --record " + dir.File("second"),
                      &output),
            0)
      << output;
  // And that recording replayed without --config, recorded again: the noise goes along.
  ASSERT_EQ(
      RunCamera("--source tum:" + dir.File("second") + " --frames 3 --record " + dir.File("third"),
                &output),
      0)
      << output;
  for (const char* folder : {"second", "third"}) {
    auto noise = recorded_noise(folder);
    ASSERT_TRUE(noise.ok()) << folder << ": " << noise.status().ToString();
    EXPECT_EQ(noise->sigma_0, 0.001) << folder;
    EXPECT_EQ(noise->sigma_2, 0.004) << folder;
    EXPECT_EQ(noise->keypoint_offset, 0.5) << folder;
  }
}

// --check-registration on rendered frames, whose depth and colour are exactly registered: with a
// Depth block that puts the depth camera 20 mm off, the check finds the true offset (0) best.
TEST(CameraCliTest, RegistrationCheckFindsTheTrueOffset) {
  testing::TempDir dir;
  const std::string folder = dir.File("rec");
  std::string output;
  ASSERT_EQ(RunCamera("--source synth:frames=10 --frames 10 --record " + folder, &output), 0)
      << output;
  auto camera_yaml = ReadFileToString(folder + "/camera.yaml");
  ASSERT_TRUE(camera_yaml.ok());
  auto camera = LoadCameraConfig(folder + "/camera.yaml");
  ASSERT_TRUE(camera.ok());
  const std::string config = dir.File("registered.yaml");
  const std::string depth_block =
      "\nDepth.fx: " + std::to_string(camera->fx) + "\nDepth.fy: " + std::to_string(camera->fy) +
      "\nDepth.cx: " + std::to_string(camera->cx) + "\nDepth.cy: " + std::to_string(camera->cy) +
      "\nDepth.width: 640\nDepth.height: 480\nDepth.t_color_depth: [0.02, 0.0, 0.0]\n";
  ASSERT_TRUE(WriteFileAtomic(config, *camera_yaml + depth_block).ok());
  ASSERT_EQ(RunCamera("--check-registration --source tum:" + folder + " --config " + config +
                          " --frames 5",
                      &output),
            0)
      << output;
  EXPECT_NE(output.find("best: t_color_depth.x +0.000 m (config +0.020 m)"), std::string::npos)
      << output;

  // Without a Depth block there is nothing to check.
  EXPECT_EQ(RunCamera("--check-registration --source tum:" + folder + " --config " + folder +
                          "/camera.yaml",
                      &output),
            2);
  EXPECT_NE(output.find("needs a --config with a Depth block"), std::string::npos) << output;
}

// --check-ground-truth on a rig rendered both ways: a Kinect-like colour camera with a depth
// imager 25 mm to its side, the ground truth written once for the depth imager
// (Trajectory.camera: "depth", as 7-Scenes) and once for the colour camera. From the depth and
// the poses alone, the check names the camera each ground truth gives.
TEST(CameraCliTest, GroundTruthCheckNamesTheCameraThePosesGive) {
  testing::TempDir dir;
  const std::string rig =
      "%YAML:1.0\nCamera.fx: 262.5\nCamera.fy: 262.5\nCamera.cx: 160.0\nCamera.cy: 120.0\n"
      "Camera.width: 320\nCamera.height: 240\nCamera.fps: 30.0\nCamera.bf: 20.0\n"
      "ThDepth: 40.0\nDepthMapFactor: 5000.0\nDepth.fx: 292.5\nDepth.fy: 292.5\n"
      "Depth.cx: 160.0\nDepth.cy: 120.0\nDepth.width: 320\nDepth.height: 240\n"
      "Depth.t_color_depth: [-0.025, 0.0, 0.0]\n";
  for (const bool depth_truth : {true, false}) {
    const std::string config = dir.File(depth_truth ? "depth.yaml" : "colour.yaml");
    ASSERT_TRUE(
        WriteFileAtomic(config, rig + (depth_truth ? "Trajectory.camera: \"depth\"\n" : "")).ok());
    const std::string folder = dir.File(depth_truth ? "depth_truth" : "colour_truth");
    std::string output;
    ASSERT_EQ(
        testing::RunCommand(testing::ProgramPath("ccmd_synth") + " --config " + config +
                                " --frames 120 --surface-spacing 0.05 --out " + folder + " 2>&1",
                            &output),
        0)
        << output;
    ASSERT_EQ(
        RunCamera("--check-ground-truth --source tum:" + folder + " --config " + config, &output),
        0)
        << output;
    EXPECT_NE(output.find(depth_truth ? "closest to the depth camera (best s +0.0)"
                                      : "closest to the colour camera (best s +1.0)"),
              std::string::npos)
        << output;
  }
  // One imager: there is no other camera the poses could give.
  std::string output;
  EXPECT_EQ(RunCamera("--check-ground-truth --source synth:frames=3 --config " + dir.File("none"),
                      &output),
            2);
  EXPECT_NE(output.find("needs a --config with a Depth block"), std::string::npos) << output;
}

// --check-noise on the synthetic room, whose depth is rendered with the default model's noise
// (the one a config without DepthNoise keys gives) or twice it: the ratio it prints reads which.
TEST(CameraCliTest, NoiseCheckReadsACameraNoisierThanItsConfig) {
  for (const double scale : {1.0, 2.0}) {
    std::string output;
    ASSERT_EQ(RunCamera("--check-noise --frames 5 --source synth:frames=10,noise=" +
                            std::to_string(scale),
                        &output),
              0)
        << output;
    const std::size_t at = output.find("measured / config: ");
    ASSERT_NE(at, std::string::npos) << output;
    const double ratio = std::atof(output.c_str() + at + 19);
    EXPECT_NEAR(ratio, scale, 0.12 * scale) << output;
    // The keys it fits read back as a config.
    EXPECT_NE(output.find("DepthNoise.sigma2: "), std::string::npos) << output;
  }
  std::string output;
  EXPECT_EQ(RunCamera("--check-noise", &output), 2);
  EXPECT_NE(output.find("--check-noise needs --source"), std::string::npos) << output;
}

// A camera with a separate depth imager (the D435 over V4L2: a Depth block) rendered with its
// config's noise: the check reads the imager's own pixels, as the model describes them. On
// depth registered to colour the nearest of colliding depths wins and it would read 0.87.
TEST(CameraCliTest, NoiseCheckReadsTheDepthImagersOwnPixels) {
  testing::TempDir dir;
  const std::string config = std::string(CCMD_CONFIG_DIR) + "/realsense_d435_v4l2.yaml";
  std::string output;
  ASSERT_EQ(testing::RunCommand(testing::ProgramPath("ccmd_synth") + " --config " + config +
                                    " --frames 20 --surface-spacing 0.05 --out " +
                                    dir.File("d435") + " 2>&1",
                                &output),
            0)
      << output;
  ASSERT_EQ(RunCamera("--check-noise --frames 10 --source tum:" + dir.File("d435") + " --config " +
                          config,
                      &output),
            0)
      << output;
  const std::size_t at = output.find("measured / config: ");
  ASSERT_NE(at, std::string::npos) << output;
  EXPECT_NEAR(std::atof(output.c_str() + at + 19), 1.0, 0.06) << output;
}

// --check-shutter on the fast path rendered with a 30 ms readout names that readout as the key
// to set; on a global shutter (the synth: source) it does not name 30 ms.
TEST(CameraCliTest, ShutterCheckNamesTheReadoutARecordingWasMadeWith) {
  testing::TempDir dir;
  std::string output;
  ASSERT_EQ(testing::RunCommand(testing::ProgramPath("ccmd_synth") +
                                    " --frames 90 --width 320 --height 240 --loop-period 6 "
                                    "--rolling-shutter 30 --out " +
                                    dir.File("rs") + " 2>&1",
                                &output),
            0)
      << output;
  ASSERT_EQ(RunCamera("--check-shutter --readouts 0,30,60 --source tum:" + dir.File("rs"), &output),
            0)
      << output;
  EXPECT_NE(output.find("readout  60.0 ms: rotation"), std::string::npos) << output;
  const std::size_t key = output.find("Camera.rollingShutterReadout: ");
  ASSERT_NE(key, std::string::npos) << output;
  EXPECT_NEAR(std::atof(output.c_str() + key + 30), 0.03, 0.008) << output;

  ASSERT_EQ(
      RunCamera("--check-shutter --readouts 0,30 --source synth:frames=90,width=320,height=240",
                &output),
      0)
      << output;
  EXPECT_NE(output.find("readout  30.0 ms: rotation"), std::string::npos) << output;
  // Either 0 is best, or no candidate beats it by enough to be named; never a readout.
  EXPECT_TRUE(output.find("Camera.rollingShutterReadout: 0\n") != std::string::npos ||
              output.find("these frames do not show a readout") != std::string::npos)
      << output;
  EXPECT_EQ(output.find("Camera.rollingShutterReadout: 0.0"), std::string::npos) << output;

  // Images too small to align: it says so and names no readout.
  EXPECT_EQ(RunCamera("--check-shutter --readouts 0,30 --source synth:frames=70,width=64,height=48",
                      &output),
            1);
  EXPECT_NE(output.find("too few to read a readout from"), std::string::npos) << output;
  EXPECT_EQ(output.find("Camera.rollingShutterReadout:"), std::string::npos) << output;

  EXPECT_EQ(RunCamera("--check-shutter", &output), 2);
  EXPECT_NE(output.find("--check-shutter needs --source"), std::string::npos) << output;
  EXPECT_EQ(RunCamera("--check-shutter --source synth:frames=20,width=64,height=48", &output), 1);
  EXPECT_NE(output.find("20 frames are too few"), std::string::npos) << output;
}

TEST(CameraCliTest, RecordsTheOpenNI2TestDriver) {
  testing::TempDir dir;
  const std::string folder = dir.File("rec");
  std::string output;
  const int code = RunCamera("--source openni2:Dummy --frames 3 --record " + folder, &output);
  if (code != 0 && output.find("not found") != std::string::npos) {
    GTEST_SKIP() << "OpenNI2 test driver not installed";
  }
  ASSERT_EQ(code, 0) << output;
  auto sequence = TumSequence::Open(folder, std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_EQ(sequence->size(), 3u);
  auto frame = sequence->LoadFrame(2);
  ASSERT_TRUE(frame.ok());
  EXPECT_EQ(frame->depth_mm.at<std::uint16_t>(0, 50), 2000);  // the driver's first row
  EXPECT_EQ(sequence->camera().depth_map_factor, 1000);
}

// Starts the program with its output on a pipe; returns the pid and the read end.
pid_t Spawn(const std::vector<std::string>& arguments, int* read_fd) {
  int fds[2];
  if (pipe(fds) != 0) return -1;
  const pid_t pid = fork();
  if (pid == 0) {
    dup2(fds[1], 1);
    dup2(fds[1], 2);
    close(fds[0]);
    close(fds[1]);
    std::vector<char*> argv;
    for (const std::string& a : arguments) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    execv(argv[0], argv.data());
    _exit(127);
  }
  close(fds[1]);
  *read_fd = fds[0];
  return pid;
}

TEST(CameraCliTest, CtrlCFinishesTheFrameAndClosesTheRecording) {
  testing::TempDir dir;
  const std::string folder = dir.File("rec");
  int fd = -1;
  const pid_t pid =
      Spawn({testing::ProgramPath("ccmd_camera"), "--source",
             "synth:frames=100000,width=64,height=48", "--record", folder, "--every", "1"},
            &fd);
  ASSERT_GT(pid, 0);
  FILE* out = fdopen(fd, "r");
  ASSERT_NE(out, nullptr);
  // Synchronise on the program's own output: once it has reported a recorded frame,
  // interrupt it.
  std::string output;
  char line[512];
  bool recording = false;
  while (std::fgets(line, sizeof(line), out) != nullptr) {
    output += line;
    if (std::string(line).rfind("frame 0 ", 0) == 0) {
      recording = true;
      break;
    }
  }
  ASSERT_TRUE(recording) << output;
  ASSERT_EQ(kill(pid, SIGINT), 0);
  while (std::fgets(line, sizeof(line), out) != nullptr) output += line;
  fclose(out);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status)) << "killed by signal " << WTERMSIG(status) << "\n" << output;
  EXPECT_EQ(WEXITSTATUS(status), 0) << output;
  EXPECT_NE(output.find("(stopped by signal)"), std::string::npos) << output;

  // Every listed frame is complete and readable; both lists agree.
  const int listed = CountListed(JoinPath(folder, "rgb.txt"));
  EXPECT_GE(listed, 1);
  EXPECT_EQ(CountListed(JoinPath(folder, "depth.txt")), listed);
  EXPECT_NE(output.find("recorded " + std::to_string(listed) + " frames"), std::string::npos)
      << output;
  auto sequence = TumSequence::Open(folder, std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_EQ(static_cast<int>(sequence->size()), listed);
  EXPECT_TRUE(sequence->LoadFrame(sequence->size() - 1).ok());
}

}  // namespace
}  // namespace ccmd
