#include "libccmd/sensors/v4l2_source.h"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "libccmd/sensors/retrying_source.h"
#include "tests/live/fake_v4l2_device.h"

namespace ccmd {
namespace {

using testing::FakeFrame;
using testing::FakeNode;
using testing::FakeOpener;
using testing::Mode;

constexpr int kW = 8;
constexpr int kH = 6;

// Grey level BT.601 limited range gives for luma y with neutral chroma: 1.164 * (y - 16).
int GreyFromLuma(int y) { return static_cast<int>(std::lround(255.0 / 219.0 * (y - 16))); }

std::vector<std::uint8_t> YuyvImage(int width, int height, int luma, int padding = 0) {
  const int stride = width * 2 + padding;
  std::vector<std::uint8_t> data(static_cast<std::size_t>(stride) * height, 0xEE);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      data[y * stride + 2 * x] = static_cast<std::uint8_t>(luma);
      data[y * stride + 2 * x + 1] = 128;
    }
  }
  return data;
}

std::vector<std::uint8_t> Z16Image(int width, int height, int value, int padding = 0) {
  const int stride = width * 2 + padding;
  std::vector<std::uint8_t> data(static_cast<std::size_t>(stride) * height, 0xEE);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      data[y * stride + 2 * x] = static_cast<std::uint8_t>(value & 0xff);
      data[y * stride + 2 * x + 1] = static_cast<std::uint8_t>(value >> 8);
    }
  }
  return data;
}

std::vector<std::uint8_t> JpegImage(int width, int height, int grey) {
  cv::Mat image(height, width, CV_8UC3, cv::Scalar::all(grey));
  std::vector<std::uint8_t> jpeg;
  cv::imencode(".jpg", image, jpeg, {cv::IMWRITE_JPEG_QUALITY, 100});
  return jpeg;
}

struct Camera {
  FakeNode color;
  FakeNode depth;

  Camera(std::uint32_t color_fourcc = kFourccYuyv, int color_w = kW, int color_h = kH) {
    color.info.path = "/dev/video4";
    color.info.card = "Fake Colour";
    color.info.streaming_capture = true;
    color.info.modes = {Mode(color_fourcc, color_w, color_h)};
    depth.info.path = "/dev/video2";
    depth.info.card = "Fake Depth";
    depth.info.streaming_capture = true;
    depth.info.modes = {Mode(kFourccZ16, kW, kH)};
  }
  V4l2DeviceOpener Opener() {
    return FakeOpener({{"/dev/video4", &color}, {"/dev/video2", &depth}});
  }
  void AddColor(double t, std::vector<std::uint8_t> data, bool error = false) {
    color.frames.push_back({t, std::move(data), error, next_color_sequence++});
  }
  void AddDepth(double t, int value, int padding = 0) {
    depth.frames.push_back({t, Z16Image(kW, kH, value, padding), false, next_depth_sequence++});
  }
  std::uint32_t next_color_sequence = 0;
  std::uint32_t next_depth_sequence = 0;
};

V4l2SourceOptions Options() {
  V4l2SourceOptions o;
  o.color_device = "/dev/video4";
  o.depth_device = "/dev/video2";
  o.width = kW;
  o.height = kH;
  o.fps = 30;
  return o;
}

PinholeCamera SmallCamera() {
  PinholeCamera c;
  c.width = kW;
  c.height = kH;
  c.fx = c.fy = 7;
  c.cx = 3.5;
  c.cy = 2.5;
  return c;
}

TEST(V4l2SourceTest, FramesFlowPairedByDriverTimestamps) {
  Camera camera;
  camera.color.stride_padding = 4;  // rows padded like real drivers may do
  // Pair j: colour luma 50 + 40 j, depth 1500 + j mm. A depth frame without a partner
  // comes first; a colour frame without a partner comes last.
  const double colour_times[] = {1.000, 1.0333, 1.0667, 1.100};
  const double depth_times[] = {1.004, 1.037, 1.071};
  for (int j = 0; j < 4; ++j) camera.AddColor(colour_times[j], YuyvImage(kW, kH, 50 + 40 * j, 4));
  camera.AddDepth(0.950, 9999);
  for (int j = 0; j < 3; ++j) camera.AddDepth(depth_times[j], 1500 + j);

  auto source = V4l2Source::Open(Options(), SmallCamera(), camera.Opener());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_TRUE((*source)->IsLive());
  EXPECT_EQ(camera.color.format.fourcc, kFourccYuyv);  // auto picks YUYV
  EXPECT_EQ(camera.depth.format.fourcc, kFourccZ16);
  for (int j = 0; j < 3; ++j) {
    RgbdFrame frame;
    ASSERT_TRUE((*source)->Read(&frame).ok()) << "pair " << j;
    EXPECT_EQ(frame.index, j);
    // The colour image's time, and the depth's after it (the tracker moves the depth to the
    // colour image's time).
    EXPECT_DOUBLE_EQ(frame.timestamp, colour_times[j]);
    EXPECT_NEAR(frame.depth_time_offset, depth_times[j] - colour_times[j], 1e-12);
    ASSERT_EQ(frame.depth_mm.size(), cv::Size(kW, kH));
    ASSERT_EQ(frame.bgr.size(), cv::Size(kW, kH));
    EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(5, 7), 1500 + j);
    const cv::Vec3b pixel = frame.bgr.at<cv::Vec3b>(5, 7);
    EXPECT_NEAR(pixel[1], GreyFromLuma(50 + 40 * j), 1) << "colour of pair " << j;
    // Both buffers are back with the driver after every Read.
    EXPECT_EQ(camera.color.outstanding, 0);
    EXPECT_EQ(camera.depth.outstanding, 0);
  }
  EXPECT_EQ((*source)->stats().unpaired_dropped, 1);
  // Colour 1.100 has no partner and the depth node runs dry: transient, and sticky.
  RgbdFrame frame;
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  source->reset();
  EXPECT_EQ(camera.color.closes, 1);
  EXPECT_EQ(camera.depth.closes, 1);
  EXPECT_EQ(camera.color.outstanding, 0);
}

TEST(V4l2SourceTest, LargerColourIsResizedToTheDepthSize) {
  Camera camera(kFourccYuyv, 2 * kW, 2 * kH);
  camera.AddColor(2.0, YuyvImage(2 * kW, 2 * kH, 120));
  camera.AddDepth(2.0, 800);
  V4l2SourceOptions options = Options();
  options.color_width = 2 * kW;
  options.color_height = 2 * kH;
  auto source = V4l2Source::Open(options, SmallCamera(), camera.Opener());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.bgr.size(), cv::Size(kW, kH));
  EXPECT_NEAR(frame.bgr.at<cv::Vec3b>(3, 3)[0], GreyFromLuma(120), 1);
  EXPECT_EQ((*source)->camera().width, kW);
}

TEST(V4l2SourceTest, DepthIsRegisteredToColourWhenTheConfigHasADepthBlock) {
  Camera camera;
  camera.AddColor(3.0, YuyvImage(kW, kH, 120));
  camera.AddDepth(3.0, 1500);
  // Depth imager: wider lens (f = 6 px); colour (f = 8 px), 1 cm to the side. A plane at
  // 1.5 m covers the whole colour view, at 1.5 m.
  PinholeCamera colour = SmallCamera();
  colour.fx = colour.fy = 8;
  DepthToColorCalibration registration;
  registration.depth = SmallCamera();
  registration.depth.fx = registration.depth.fy = 6;
  registration.T_color_depth.translation() = Eigen::Vector3d(0.01, 0, 0);
  auto source = V4l2Source::Open(Options(), colour, camera.Opener(), registration);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_DOUBLE_EQ((*source)->camera().fx, 8);  // frames have the colour geometry
  EXPECT_NE((*source)->Describe().find("registered to colour"), std::string::npos);
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(cv::countNonZero(frame.depth_mm == 1500), kW * kH);
}

TEST(V4l2SourceTest, MjpegColourAndDamagedFramesAreDropped) {
  Camera camera(kFourccMjpeg);
  std::vector<std::uint8_t> truncated = JpegImage(kW, kH, 90);
  truncated.resize(truncated.size() / 2);
  camera.AddColor(1.000, JpegImage(kW, kH, 60));
  camera.AddColor(1.033, truncated);                    // fails to decode
  camera.AddColor(1.066, JpegImage(kW, kH, 90), true);  // flagged by the driver
  camera.AddColor(1.100, JpegImage(kW, kH, 200));
  camera.AddDepth(1.000, 1000);
  camera.AddDepth(1.033, 1001);
  camera.AddDepth(1.100, 1003);
  auto source = V4l2Source::Open(Options(), SmallCamera(), camera.Opener());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_EQ(camera.color.format.fourcc, kFourccMjpeg);
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, 0), 1000);
  EXPECT_NEAR(frame.bgr.at<cv::Vec3b>(2, 2)[2], 60, 2);
  {
    const Status s = (*source)->Read(&frame);
    ASSERT_TRUE(s.ok()) << s.ToString();
  }
  EXPECT_EQ(frame.index, 1);
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, 0), 1003);
  EXPECT_NEAR(frame.bgr.at<cv::Vec3b>(2, 2)[2], 200, 2);
  EXPECT_EQ((*source)->stats().damaged_dropped, 2);
  EXPECT_EQ(camera.color.outstanding, 0);
}

TEST(V4l2SourceTest, ClearErrorsForMissingBusyAndWrongNodes) {
  {
    Camera camera;
    V4l2SourceOptions options = Options();
    options.color_device = "/dev/video9";
    auto source = V4l2Source::Open(options, SmallCamera(), camera.Opener());
    EXPECT_EQ(source.status().code(), StatusCode::kNotFound);
    EXPECT_NE(source.status().message().find("/dev/video9"), std::string::npos);
  }
  {
    Camera camera;
    camera.color.open_error = Unavailable("/dev/video4: open: Device or resource busy");
    EXPECT_EQ(V4l2Source::Open(Options(), SmallCamera(), camera.Opener()).status().code(),
              StatusCode::kUnavailable);
  }
  {
    Camera camera;  // the user swapped the nodes: the "depth" one is the colour camera
    camera.depth.info.modes = {Mode(kFourccYuyv, kW, kH)};
    const Status status = V4l2Source::Open(Options(), SmallCamera(), camera.Opener()).status();
    EXPECT_EQ(status.code(), StatusCode::kUnsupported);
    EXPECT_NE(status.message().find("Z16"), std::string::npos) << status.message();
    EXPECT_NE(status.message().find("YUYV 8x6"), std::string::npos) << status.message();
  }
  {
    Camera camera(MakeFourcc('R', 'G', 'B', '3'));
    const Status status = V4l2Source::Open(Options(), SmallCamera(), camera.Opener()).status();
    EXPECT_EQ(status.code(), StatusCode::kUnsupported);
    EXPECT_NE(status.message().find("RGB3 8x6"), std::string::npos) << status.message();
  }
  {
    Camera camera;
    V4l2SourceOptions options = Options();
    options.color_format = "mjpeg";
    EXPECT_EQ(V4l2Source::Open(options, SmallCamera(), camera.Opener()).status().code(),
              StatusCode::kUnsupported);
  }
  {
    Camera camera;
    camera.depth.info.streaming_capture = false;  // a metadata node
    EXPECT_EQ(V4l2Source::Open(Options(), SmallCamera(), camera.Opener()).status().code(),
              StatusCode::kUnsupported);
  }
}

TEST(V4l2SourceTest, StreamsThatNeverMeetGiveUpWithAClearMessage) {
  Camera camera;
  for (int k = 0; k < 2; ++k) camera.AddColor(1000.0 + k / 30.0, YuyvImage(kW, kH, 100));
  for (int k = 0; k < 400; ++k) camera.AddDepth(5.0 + k / 30.0, 700);
  auto source = V4l2Source::Open(Options(), SmallCamera(), camera.Opener());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  const Status status = (*source)->Read(&frame);
  EXPECT_EQ(status.code(), StatusCode::kUnsupported);
  EXPECT_NE(status.message().find("one camera"), std::string::npos) << status.message();
}

TEST(V4l2SourceTest, DriverSequenceGapsAreCounted) {
  Camera camera;
  for (int j = 0; j < 3; ++j) camera.AddColor(1.0 + j / 30.0, YuyvImage(kW, kH, 100));
  camera.color.frames[2].sequence = 7;  // the driver skipped sequence numbers 2..6
  for (int j = 0; j < 3; ++j) camera.AddDepth(1.0 + j / 30.0, 700);
  auto source = V4l2Source::Open(Options(), SmallCamera(), camera.Opener());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  for (int j = 0; j < 3; ++j) ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ((*source)->stats().driver_gaps, 5);
}

TEST(V4l2SourceTest, UnpluggedMidRunIsUnavailableAndTheRetryWrapperReopens) {
  Camera camera;
  for (int j = 0; j < 4; ++j) camera.AddColor(10.0 + j / 30.0, YuyvImage(kW, kH, 100));
  for (int j = 0; j < 4; ++j) camera.AddDepth(10.0 + j / 30.0, 600 + j);
  camera.depth.unplug_after = 2;

  std::vector<double> waits;
  std::vector<RetryEvent::Kind> events;
  RetryHooks hooks;
  hooks.wait = [&](double s) {
    waits.push_back(s);
    return true;
  };
  hooks.now = [] { return 0.0; };
  hooks.report = [&](const RetryEvent& e) { events.push_back(e.kind); };
  auto opener = [&]() -> StatusOr<std::unique_ptr<RgbdSource>> {
    CCMD_ASSIGN_OR_RETURN(auto source, V4l2Source::Open(Options(), SmallCamera(), camera.Opener()));
    return std::unique_ptr<RgbdSource>(std::move(source));
  };
  auto source = RetryingSource::Open(opener, {}, hooks);
  ASSERT_TRUE(source.ok()) << source.status().ToString();

  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, 0), 601);
  // Unplugged: the wrapper reports it, closes both nodes and hands the error on.
  const Status lost = (*source)->Read(&frame);
  EXPECT_EQ(lost.code(), StatusCode::kUnavailable);
  EXPECT_NE(lost.message().find("unplugged"), std::string::npos) << lost.message();
  EXPECT_EQ(camera.depth.closes, 1);
  EXPECT_EQ(camera.color.closes, 1);
  EXPECT_FALSE((*source)->connected());

  // Still unplugged: the node is gone, the reopen attempt fails after the first delay.
  camera.depth.open_error = NotFound("/dev/video2: open: No such file or directory");
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  // Plugged back in with fresh frames.
  camera.depth.open_error = Status::Ok();
  camera.depth.unplug_after = -1;
  camera.depth.delivered = 0;
  camera.color.frames.clear();
  camera.depth.frames.clear();
  camera.AddColor(20.0, YuyvImage(kW, kH, 100));
  camera.AddDepth(20.0, 900);
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.index, 2);  // numbering continues across the outage
  EXPECT_DOUBLE_EQ(frame.timestamp, 20.0);
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(0, 0), 900);
  EXPECT_EQ(waits, (std::vector<double>{0.5, 1.0}));
  EXPECT_EQ(events,
            (std::vector<RetryEvent::Kind>{RetryEvent::Kind::kLost, RetryEvent::Kind::kRetryFailed,
                                           RetryEvent::Kind::kReconnected}));
  EXPECT_EQ((*source)->reconnects(), 1);
}

TEST(V4l2SpecTest, ParsesEveryOption) {
  auto options = ParseV4l2Spec(
      "color=/dev/video4,depth=/dev/video2,config=/c.yaml,width=848,height=480,fps=15,"
      "color_width=1920,color_height=1080,color_format=mjpeg,depth_unit=0.0001,timeout=5,"
      "pair_tolerance=0.01,buffers=6");
  ASSERT_TRUE(options.ok()) << options.status().ToString();
  EXPECT_EQ(options->color_device, "/dev/video4");
  EXPECT_EQ(options->depth_device, "/dev/video2");
  EXPECT_EQ(options->config, "/c.yaml");
  EXPECT_EQ(options->width, 848);
  EXPECT_EQ(options->height, 480);
  EXPECT_EQ(options->fps, 15);
  EXPECT_EQ(options->color_width, 1920);
  EXPECT_EQ(options->color_height, 1080);
  EXPECT_EQ(options->color_format, "mjpeg");
  EXPECT_DOUBLE_EQ(options->depth_unit_m, 0.0001);
  EXPECT_EQ(options->timeout_s, 5);
  EXPECT_DOUBLE_EQ(options->pair_tolerance_s, 0.01);
  EXPECT_EQ(options->buffers, 6);

  auto defaults = ParseV4l2Spec("color=/dev/video4,depth=/dev/video2");
  ASSERT_TRUE(defaults.ok());
  EXPECT_EQ(defaults->width, 640);
  EXPECT_EQ(defaults->color_format, "auto");
}

TEST(V4l2SpecTest, RejectsIncompleteOrWrongSpecs) {
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4").status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4,depth=/dev/video2,gain=3").status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4,depth=/dev/video2,fps=fast").status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4,depth=/dev/video2,width=99999").status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4,depth=/dev/video2,color_width=1920").status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color=/dev/video4,depth=/dev/video2,color_format=h264").status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseV4l2Spec("color,depth").status().code(), StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace ccmd
