// Live camera specs through the source factory (the same path ccmd_agent and ccmd_camera
// take), with the real device layers: V4L2 on nodes that are not cameras, OpenNI2 on its
// test driver.

#include <gtest/gtest.h>

#include "libccmd/io/config.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/source_factory.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

SourceOptions WithConfigsDir() {
  SourceOptions options;
  options.configs_dir = CCMD_CONFIG_DIR;
  return options;
}

TEST(LiveSourceSpecTest, V4l2NodesThatDoNotExistAreNotFound) {
  const auto source =
      OpenSource("v4l2:color=/dev/ccmd_no_video98,depth=/dev/ccmd_no_video99", WithConfigsDir());
  EXPECT_EQ(source.status().code(), StatusCode::kNotFound);
  EXPECT_NE(source.status().message().find("plugged in"), std::string::npos)
      << source.status().message();
}

TEST(LiveSourceSpecTest, V4l2NodeThatIsNotAVideoDeviceIsUnsupported) {
  const auto source = OpenSource("v4l2:color=/dev/null,depth=/dev/null", WithConfigsDir());
  EXPECT_EQ(source.status().code(), StatusCode::kUnsupported);
  EXPECT_NE(source.status().message().find("not a V4L2 device"), std::string::npos)
      << source.status().message();
}

TEST(LiveSourceSpecTest, V4l2SpecErrors) {
  EXPECT_EQ(OpenSource("v4l2:color=/dev/video4", WithConfigsDir()).status().code(),
            StatusCode::kInvalidArgument);
  // No config and nowhere to find the default one.
  EXPECT_EQ(OpenSource("v4l2:color=/dev/video4,depth=/dev/video2", {}).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(OpenSource("v4l2:color=/dev/video4,depth=/dev/video2,config=/no/such.yaml", {})
                .status()
                .code(),
            StatusCode::kNotFound);
  const Status unknown = OpenSource("kinect", {}).status();
  EXPECT_EQ(unknown.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(unknown.message().find("openni2"), std::string::npos);
}

TEST(LiveSourceSpecTest, ShippedD435V4l2ConfigDescribesBothImagers) {
  const std::string path = std::string(CCMD_CONFIG_DIR) + "/realsense_d435_v4l2.yaml";
  auto colour = LoadCameraConfig(path);
  ASSERT_TRUE(colour.ok()) << colour.status().ToString();
  EXPECT_EQ(colour->depth_map_factor, 1000);  // Z16 in millimetres
  auto registration = LoadDepthToColorCalibration(path);
  ASSERT_TRUE(registration.ok()) << registration.status().ToString();
  ASSERT_TRUE(registration->has_value());
  // The depth imager has the wider lens: a shorter focal length at the same size.
  EXPECT_LT((*registration)->depth.fx, colour->fx);
  EXPECT_NEAR((*registration)->T_color_depth.translation().norm(), 0.015, 1e-9);
}

TEST(LiveSourceSpecTest, OpenNI2RecordingThatDoesNotExist) {
  EXPECT_EQ(OpenSource("openni2:/no/such/recording.oni", {}).status().code(),
            StatusCode::kNotFound);
}

TEST(LiveSourceSpecTest, OpenNI2TestDriverWithAConfigAndRetry) {
  // The config sets the mode (the test driver only has 320x240 at 30 fps) and intrinsics.
  testing::TempDir dir;
  PinholeCamera camera;
  camera.width = 320;
  camera.height = 240;
  camera.fx = camera.fy = 270;
  camera.cx = 160;
  camera.cy = 120;
  camera.depth_map_factor = 1000;
  ASSERT_TRUE(WriteCameraConfig(camera, dir.File("dummy.yaml")).ok());
  SourceOptions options;
  options.camera_config = dir.File("dummy.yaml");
  auto source = OpenSourceWithRetry("openni2:Dummy", options);
  if (source.status().code() == StatusCode::kNotFound) {
    GTEST_SKIP() << "OpenNI2 test driver not installed";
  }
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_TRUE((*source)->IsLive());
  EXPECT_NE((*source)->Describe().find("reopened on failure"), std::string::npos);
  EXPECT_DOUBLE_EQ((*source)->camera().fx, 270);
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, 100), 2000);
}

TEST(LiveSourceSpecTest, RetryLeavesDatasetsAlone) {
  auto source = OpenSourceWithRetry("synth:frames=2,width=64,height=48", {});
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_FALSE((*source)->IsLive());
  EXPECT_EQ((*source)->Describe().find("reopened"), std::string::npos);
  EXPECT_EQ((*source)->FrameCount(), 2);
}

}  // namespace
}  // namespace ccmd
