#include "libccmd/sensors/openni2_source.h"

#include <gtest/gtest.h>

#include <cmath>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

// OpenNI2 ships a test driver ("Dummy", libDummyDevice) that opens by that URI and streams
// 320x240 depth and colour at 30 fps with a fixed pattern: the first depth row is 2000 mm,
// the first colour pixel pure blue, timestamps frame number x 33 ms.
constexpr int kDummyWidth = 320;
constexpr int kDummyHeight = 240;

OpenNI2Options DummyOptions() {
  OpenNI2Options options;
  options.uri = "Dummy";
  options.width = kDummyWidth;
  options.height = kDummyHeight;
  options.fps = 30;
  return options;
}

TEST(OpenNI2SourceTest, NoDeviceIsNotFound) {
  auto devices = ListOpenNI2Devices();
  ASSERT_TRUE(devices.ok()) << devices.status().ToString();
  if (!devices->empty()) GTEST_SKIP() << "an OpenNI2 camera is connected; skipping";
  auto source = OpenNI2Source::Open({});
  EXPECT_EQ(source.status().code(), StatusCode::kNotFound);
  EXPECT_NE(source.status().message().find("no device"), std::string::npos)
      << source.status().message();

  OpenNI2Options named;
  named.uri = "1d27/0601@9/9";
  EXPECT_EQ(OpenNI2Source::Open(named).status().code(), StatusCode::kNotFound);
}

TEST(OpenNI2SourceTest, MissingOrBrokenRecordings) {
  OpenNI2Options options;
  options.uri = "/nonexistent/walk.oni";
  const Status missing = OpenNI2Source::Open(options).status();
  EXPECT_EQ(missing.code(), StatusCode::kNotFound);
  EXPECT_NE(missing.message().find("/nonexistent/walk.oni"), std::string::npos);

  testing::TempDir dir;
  options.uri = dir.File("broken.oni");
  ASSERT_TRUE(WriteFileAtomic(options.uri, std::string(4096, 'x')).ok());
  EXPECT_EQ(OpenNI2Source::Open(options).status().code(), StatusCode::kCorrupt);
}

TEST(OpenNI2SourceTest, RejectsBadModes) {
  OpenNI2Options options = DummyOptions();
  options.width = 0;
  EXPECT_EQ(OpenNI2Source::Open(options).status().code(), StatusCode::kInvalidArgument);
}

TEST(OpenNI2SourceTest, TestDriverStreamsPairedMillimetreFrames) {
  auto source = OpenNI2Source::Open(DummyOptions());
  if (source.status().code() == StatusCode::kNotFound) {
    GTEST_SKIP() << "OpenNI2 test driver not installed: " << source.status().ToString();
  }
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_TRUE((*source)->IsLive());
  const PinholeCamera& camera = (*source)->camera();
  EXPECT_EQ(camera.width, kDummyWidth);
  EXPECT_EQ(camera.height, kDummyHeight);
  EXPECT_DOUBLE_EQ(camera.cx, 159.5);
  EXPECT_DOUBLE_EQ(camera.cy, 119.5);
  // The driver reports no field of view: the 58 degree fallback, fx = 160 / tan(29 deg).
  EXPECT_NEAR(camera.fx, 160.0 / std::tan(29.0 * M_PI / 180.0), 1e-9);

  double last = -1;
  for (int i = 0; i < 3; ++i) {
    RgbdFrame frame;
    const Status status = (*source)->Read(&frame);
    ASSERT_TRUE(status.ok()) << status.ToString();
    EXPECT_EQ(frame.index, i);
    ASSERT_EQ(frame.depth_mm.type(), CV_16UC1);
    ASSERT_EQ(frame.depth_mm.size(), cv::Size(kDummyWidth, kDummyHeight));
    ASSERT_EQ(frame.bgr.size(), cv::Size(kDummyWidth, kDummyHeight));
    for (int x = 0; x < kDummyWidth; x += 40) {
      EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, x), 2000) << "x " << x;
    }
    // RGB (0, 0, 255) from the device is BGR (255, 0, 0) here.
    EXPECT_EQ(frame.bgr.at<cv::Vec3b>(0, 0), cv::Vec3b(255, 0, 0));
    // Microseconds to seconds: a whole number of 33 ms ticks, increasing.
    const double ticks = frame.timestamp / 0.033;
    EXPECT_NEAR(ticks, std::round(ticks), 1e-6) << frame.timestamp;
    EXPECT_GT(frame.timestamp, last);
    last = frame.timestamp;
  }
}

TEST(OpenNI2SourceTest, ModeTheDeviceDoesNotOfferIsUnsupported) {
  OpenNI2Options options = DummyOptions();
  options.width = 640;
  options.height = 480;
  auto source = OpenNI2Source::Open(options);
  if (source.status().code() == StatusCode::kNotFound) {
    GTEST_SKIP() << "OpenNI2 test driver not installed";
  }
  EXPECT_EQ(source.status().code(), StatusCode::kUnsupported);
  EXPECT_NE(source.status().message().find("320x240@30 DEPTH_1_MM"), std::string::npos)
      << source.status().message();
}

}  // namespace
}  // namespace ccmd
