#include "libccmd/io/config.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <opencv2/core.hpp>

#include <sys/stat.h>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(ConfigTest, ReadsOrbSlamCameraKeys) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("c.yaml"),
                              "%YAML:1.0\nCamera.fx: 517.306408\nCamera.fy: 516.469215\n"
                              "Camera.cx: 318.643040\nCamera.cy: 255.313989\nCamera.k1: 0.262383\n"
                              "Camera.width: 640\nCamera.height: 480\nCamera.fps: 30.0\n"
                              "Camera.bf: 40.0\nThDepth: 40.0\nDepthMapFactor: 5000.0\n")
                  .ok());
  auto c = LoadCameraConfig(dir.File("c.yaml"));
  ASSERT_TRUE(c.ok()) << c.status().ToString();
  EXPECT_DOUBLE_EQ(c->fx, 517.306408);
  EXPECT_DOUBLE_EQ(c->cy, 255.313989);
  EXPECT_DOUBLE_EQ(c->distortion[0], 0.262383);
  EXPECT_DOUBLE_EQ(c->depth_map_factor, 5000.0);
  EXPECT_NEAR(c->far_depth_m, 40.0 * 40.0 / 517.306408, 1e-12);  // ORB-SLAM's ThDepth rule
}

TEST(ConfigTest, MissingAndWrongKeysAreClearErrors) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("a.yaml"),
                              "%YAML:1.0\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\n")
                  .ok());
  auto a = LoadCameraConfig(dir.File("a.yaml"));
  ASSERT_FALSE(a.ok());
  EXPECT_NE(a.status().message().find("Camera.cy"), std::string::npos);
  ASSERT_TRUE(WriteFileAtomic(
                  dir.File("b.yaml"),
                  "%YAML:1.0\nCamera.fx: \"big\"\nCamera.fy: 500\nCamera.cx: 320\nCamera.cy: 240\n")
                  .ok());
  EXPECT_FALSE(LoadCameraConfig(dir.File("b.yaml")).ok());
  EXPECT_EQ(LoadCameraConfig(dir.File("none.yaml")).status().code(), StatusCode::kNotFound);
  ASSERT_TRUE(WriteFileAtomic(dir.File("c.yaml"), "%YAML:1.0\n{{{{").ok());
  EXPECT_FALSE(LoadCameraConfig(dir.File("c.yaml")).ok());
}

// Found by fuzzing: a file whose top level is a list, not keys, made the first key lookup
// throw (cv::Exception), which nothing caught.
TEST(ConfigTest, TopLevelListIsAClearError) {
  testing::TempDir dir;
  for (const std::string text :
       {"%YAML:1.0\n- 1\n", "%YAML:1.0\n- Camera.fx: 500\n  Camera.fy: 500\n",
        "%YAML:1.0\n[1, 2]\n", "%YAML:1.0\n.type: \"Pin \n-H\xba\n"}) {
    ASSERT_TRUE(WriteFileAtomic(dir.File("l.yaml"), text).ok());
    auto c = LoadCameraConfig(dir.File("l.yaml"));
    ASSERT_FALSE(c.ok()) << text;
    EXPECT_EQ(c.status().code(), StatusCode::kCorrupt) << c.status().ToString();
    EXPECT_FALSE(LoadDepthToColorCalibration(dir.File("l.yaml")).ok());
    EXPECT_FALSE(LoadTrajectoryCamera(dir.File("l.yaml")).ok());
  }
}

// Nesting deep enough to overflow cv::FileStorage's recursive parser (some 20 000 levels in a
// release build, fewer under AddressSanitizer) is refused before parsing.
TEST(ConfigTest, DeepNestingIsAClearError) {
  testing::TempDir dir;
  for (const std::string level : {"[", "{a: ", "- ", "a: "}) {
    std::string text = "%YAML:1.0\nCamera.fx: ";
    for (int i = 0; i < 100000; ++i) text += level;
    ASSERT_TRUE(WriteFileAtomic(dir.File("n.yaml"), text + "1\n").ok());
    auto c = LoadCameraConfig(dir.File("n.yaml"));
    ASSERT_FALSE(c.ok()) << level;
    EXPECT_EQ(c.status().code(), StatusCode::kCorrupt) << c.status().ToString();
    EXPECT_NE(c.status().message().find("keys, list items and brackets"), std::string::npos)
        << c.status().ToString();
  }
}

// Found by fuzzing: OpenCV's base64 reader ("!!binary") loops for ever on a line of bytes that
// are not base64 (the agent, which takes SIGTERM as "finish cleanly", then runs until killed). The
// tag is refused before parsing, a valid base64 matrix as well as the bytes that hang.
TEST(ConfigTest, Base64ValuesAreRefusedBeforeParsing) {
  testing::TempDir dir;
  // A matrix as OpenCV writes it in base64 (its writer takes no dots in keys: renamed after).
  cv::FileStorage written(
      "w.yaml", cv::FileStorage::WRITE | cv::FileStorage::MEMORY | cv::FileStorage::BASE64);
  written << "R" << cv::Mat::eye(3, 3, CV_64F);
  std::string valid = written.releaseAndGetString();
  const std::size_t key = valid.find("\nR:");
  ASSERT_NE(key, std::string::npos) << valid;
  ASSERT_NE(valid.find("!!binary"), std::string::npos) << valid;
  valid.replace(key, 3,
                "\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\nCamera.cy: 240\n"
                "Camera.width: 640\nCamera.height: 480\nDepth.R_color_depth:");
  const std::string hangs = "%YAML:1.0\nCamera.fx: 500\nRgbdSelection.thresholdRatio:!!binary " +
                            std::string(80, '\xff') + "\n";
  for (const std::string& text : {valid, hangs}) {
    ASSERT_TRUE(WriteFileAtomic(dir.File("b.yaml"), text).ok());
    auto c = LoadCameraConfig(dir.File("b.yaml"));
    ASSERT_FALSE(c.ok()) << text;
    EXPECT_EQ(c.status().code(), StatusCode::kCorrupt) << c.status().ToString();
    EXPECT_NE(c.status().message().find("base64 (!!binary)"), std::string::npos)
        << c.status().ToString();
  }
}

// Found by fuzzing (UBSan): a real where an integer belongs was converted before its range
// was checked. Out of range, NaN or infinite, it is an error naming the key.
TEST(ConfigTest, IntegerKeysOutsideIntAreClearErrors) {
  testing::TempDir dir;
  const std::string camera =
      "%YAML:1.0\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\n"
      "Camera.cy: 240\nCamera.height: 480\n";
  // Integer literals beyond int too: OpenCV wraps them ("4294967936" would read as 640).
  for (const std::string value : {"1e30", "-3e9", "2147483648.0", ".nan", "-.inf", "2147483648",
                                  "4294967936", "-4294967296", "99999999999999999999999"}) {
    ASSERT_TRUE(WriteFileAtomic(dir.File("w.yaml"), camera + "Camera.width: " + value + "\n").ok());
    auto c = LoadCameraConfig(dir.File("w.yaml"));
    ASSERT_FALSE(c.ok()) << value;
    EXPECT_NE(c.status().message().find("Camera.width must be an integer"), std::string::npos)
        << value << ": " << c.status().ToString();
  }
  ASSERT_TRUE(WriteFileAtomic(dir.File("w.yaml"), camera + "Camera.width: 640.0\n").ok());
  auto c = LoadCameraConfig(dir.File("w.yaml"));
  ASSERT_TRUE(c.ok()) << c.status().ToString();
  EXPECT_EQ(c->width, 640);
}

// A number key given as an integer beyond int is read as written, not wrapped; a comment or
// another key that names it is not taken for it.
TEST(ConfigTest, LargeIntegerLiteralsAreReadAsWritten) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("c.yaml"),
                              "%YAML:1.0\n# DepthMapFactor: 1\nDepthMapFactor2: 3\n"
                              "DepthMapFactor: 4294972296  # far beyond int\nSmall: -7\n")
                  .ok());
  auto config = ConfigFile::Open(dir.File("c.yaml"));
  ASSERT_TRUE(config.ok()) << config.status().ToString();
  auto factor = config->GetDouble("DepthMapFactor", 0);
  ASSERT_TRUE(factor.ok());
  EXPECT_EQ(*factor, 4294972296.0);
  auto small = config->GetInt("Small", 0);
  ASSERT_TRUE(small.ok());
  EXPECT_EQ(*small, -7);
  EXPECT_FALSE(config->GetInt("DepthMapFactor", 0).ok());
}

TEST(ConfigTest, TrajectoriesAreOfTheColourCameraUnlessTheConfigNamesTheDepthCamera) {
  testing::TempDir dir;
  const std::string camera =
      "%YAML:1.0\nCamera.fx: 525\nCamera.fy: 525\nCamera.cx: 320\nCamera.cy: 240\n"
      "Camera.width: 640\nCamera.height: 480\n";
  const std::string depth =
      "Depth.fx: 585\nDepth.fy: 585\nDepth.cx: 320\nDepth.cy: 240\nDepth.width: 640\n"
      "Depth.height: 480\nDepth.t_color_depth: [-0.025, 0.0, 0.01]\n";
  auto write = [&](const std::string& name, const std::string& text) {
    EXPECT_TRUE(WriteFileAtomic(dir.File(name), text).ok());
    return dir.File(name);
  };
  // Without the key, or naming the colour camera: identity, with a Depth block or not.
  for (const std::string& text :
       {camera, camera + depth, camera + depth + "Trajectory.camera: \"colour\"\n",
        camera + "Trajectory.camera: \"color\"\n"}) {
    auto T = LoadTrajectoryCamera(write("c.yaml", text));
    ASSERT_TRUE(T.ok()) << T.status().ToString();
    EXPECT_TRUE(T->isApprox(Pose::Identity())) << text;
  }
  // The depth camera: the Depth block's pose in the colour frame.
  auto T = LoadTrajectoryCamera(write("d.yaml", camera + depth + "Trajectory.camera: \"depth\"\n"));
  ASSERT_TRUE(T.ok()) << T.status().ToString();
  EXPECT_TRUE(T->translation().isApprox(Eigen::Vector3d(-0.025, 0, 0.01)));
  EXPECT_TRUE(T->linear().isIdentity(1e-12));
  // "depth" without a Depth block, and any other camera, are errors naming the key.
  for (const std::string& text : {camera + "Trajectory.camera: \"depth\"\n",
                                  camera + depth + "Trajectory.camera: \"infrared\"\n"}) {
    auto bad = LoadTrajectoryCamera(write("e.yaml", text));
    ASSERT_FALSE(bad.ok()) << text;
    EXPECT_NE(bad.status().message().find("Trajectory.camera"), std::string::npos);
  }
}

TEST(ConfigTest, WrittenConfigReadsBackTheSameCamera) {
  testing::TempDir dir;
  PinholeCamera c;
  c.fx = 481.2;
  c.fy = -480.0;
  c.far_depth_m = 3.5;
  c.depth_map_factor = 1000;
  ASSERT_TRUE(WriteCameraConfig(c, dir.File("w.yaml")).ok());
  auto r = LoadCameraConfig(dir.File("w.yaml"));
  ASSERT_TRUE(r.ok());
  EXPECT_NEAR(r->fx, 481.2, 1e-6);
  EXPECT_NEAR(r->fy, -480.0, 1e-6);
  EXPECT_NEAR(r->far_depth_m, 3.5, 1e-6);
  EXPECT_EQ(r->depth_map_factor, 1000);
}

// A written camera reads back as the same doubles, however many digits they need: the file
// held six decimals, so a small distortion term or a calibrated focal length came back changed.
TEST(ConfigTest, WrittenConfigKeepsEveryDigit) {
  testing::TempDir dir;
  PinholeCamera c;
  c.fx = 616.3745727539062;
  c.fy = -615.9876543210987;
  c.cx = 319.50000000000006;
  c.cy = 241.1234567;
  c.distortion = {0.2624 + 1.2345678901234e-7, -0.9531, -0.0054 + 1e-9, 3e-12, 1.1633};
  c.depth_map_factor = 5208.3;
  DepthToColorCalibration depth;
  depth.depth = c;
  depth.depth.fx = 585.0000001;
  depth.T_color_depth = Eigen::Translation3d(-0.025, 1e-9, 0.0) *
                        Eigen::AngleAxisd(0.0123456789, Eigen::Vector3d(0.6, 0.8, 0.0));
  ASSERT_TRUE(WriteCameraConfig(c, dir.File("w.yaml"), depth).ok());
  auto r = LoadCameraConfig(dir.File("w.yaml"));
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  EXPECT_EQ(r->fx, c.fx);
  EXPECT_EQ(r->fy, c.fy);
  EXPECT_EQ(r->cx, c.cx);
  EXPECT_EQ(r->cy, c.cy);
  for (int i = 0; i < 5; ++i) {
    EXPECT_EQ(r->distortion[i], c.distortion[i]) << i;
  }
  EXPECT_EQ(r->depth_map_factor, c.depth_map_factor);
  EXPECT_EQ(r->far_depth_m, c.far_depth_m);
  auto d = LoadDepthToColorCalibration(dir.File("w.yaml"));
  ASSERT_TRUE(d.ok() && d->has_value()) << d.status().ToString();
  EXPECT_EQ((*d)->depth.fx, depth.depth.fx);
  EXPECT_EQ((*d)->T_color_depth.translation(), depth.T_color_depth.translation());
  EXPECT_TRUE((*d)->T_color_depth.linear().isApprox(depth.T_color_depth.linear(), 1e-15));
}

// The far depth, which the file gives as ThDepth * bf / |fx|, reads back to the last bit
// where a ThDepth can give it: printed in full (4.17 * 455.6 / 40 = 47.496300000000005),
// ThDepth gave it back one bit off; 47.4963 gives it exactly.
TEST(ConfigTest, WrittenConfigKeepsTheFarDepth) {
  testing::TempDir dir;
  PinholeCamera c;
  c.fx = 455.6;
  c.bf = 40;
  c.far_depth_m = 4.17;
  c.depth_map_factor = 5000;
  ASSERT_TRUE(WriteCameraConfig(c, dir.File("w.yaml")).ok());
  auto r = LoadCameraConfig(dir.File("w.yaml"));
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  EXPECT_EQ(r->far_depth_m, 4.17);
  auto text = ReadFileToString(dir.File("w.yaml"));
  ASSERT_TRUE(text.ok());
  EXPECT_NE(text->find("ThDepth: 47.4963\n"), std::string::npos) << *text;
}

// Every value of an accepted camera is written whole, however long it prints: the file was
// cut at 1 kB, and read back with defaults for the keys after the cut.
TEST(ConfigTest, HugeValuesAreWrittenWhole) {
  testing::TempDir dir;
  PinholeCamera c;
  c.fx = 1e300;
  c.fy = -1e300;
  c.cx = -1.5e300;
  c.cy = 2e300;
  c.width = 123;
  c.height = 45;
  c.depth_map_factor = 1000;
  DepthToColorCalibration depth;
  depth.depth = c;
  depth.depth.width = 67;
  depth.depth.height = 89;
  ASSERT_TRUE(WriteCameraConfig(c, dir.File("w.yaml"), depth).ok());
  auto r = LoadCameraConfig(dir.File("w.yaml"));
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  EXPECT_EQ(r->fx, 1e300);
  EXPECT_EQ(r->cy, 2e300);
  EXPECT_EQ(r->width, 123);
  EXPECT_EQ(r->height, 45);
  EXPECT_EQ(r->depth_map_factor, 1000);
  auto d = LoadDepthToColorCalibration(dir.File("w.yaml"));
  ASSERT_TRUE(d.ok()) << d.status().ToString();
  ASSERT_TRUE(d->has_value());
  EXPECT_EQ((*d)->depth.width, 67);
  EXPECT_EQ((*d)->depth.height, 89);
}

// A config given through a pipe, as a shell's --config <(...) gives it: the programs read a
// config more than once, so a pipe would be empty or block the second time. It is refused at
// once with a clear error (nothing opens it: opening a pipe with no writer would block).
TEST(ConfigTest, AConfigThroughAPipeIsAClearError) {
  testing::TempDir dir;
  const std::string fifo = dir.File("config.fifo");
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  auto c = LoadCameraConfig(fifo);
  ASSERT_FALSE(c.ok());
  EXPECT_NE(c.status().message().find("not a regular file"), std::string::npos)
      << c.status().ToString();
}

TEST(ConfigTest, EveryShippedConfigLoads) {
  int count = 0;
  for (const auto& entry : std::filesystem::directory_iterator(CCMD_CONFIG_DIR)) {
    if (entry.path().extension() != ".yaml") continue;
    auto c = LoadCameraConfig(entry.path().string());
    EXPECT_TRUE(c.ok()) << entry.path() << ": " << c.status().ToString();
    ++count;
  }
  EXPECT_GE(count, 7);  // TUM fr1-3, ICL-NUIM, 7-Scenes, D435, synthetic
}

}  // namespace
}  // namespace ccmd
