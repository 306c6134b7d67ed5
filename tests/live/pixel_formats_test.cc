#include "libccmd/sensors/pixel_formats.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <vector>

namespace ccmd {
namespace {

// ITU-R BT.601, limited range (Y 16..235, Cb/Cr 16..240 around 128), computed in double:
// the reference the converters are checked against.
cv::Vec3b Bt601ToBgr(int y, int u, int v) {
  const double c = 1.164383 * (y - 16);
  const double r = c + 1.596027 * (v - 128);
  const double g = c - 0.391762 * (u - 128) - 0.812968 * (v - 128);
  const double b = c + 2.017232 * (u - 128);
  auto clamp = [](double x) { return static_cast<uchar>(std::lround(std::clamp(x, 0.0, 255.0))); };
  return {clamp(b), clamp(g), clamp(r)};
}

void ExpectNear(const cv::Vec3b& actual, const cv::Vec3b& expected, int tolerance,
                const std::string& where) {
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(actual[k], expected[k], tolerance) << where << " channel " << k;
  }
}

TEST(PixelFormatsTest, YuyvKnownColoursAndPaddedRows) {
  // Two rows of 4 pixels, 12-byte stride (4 bytes of padding filled with junk).
  // Row 0: black, white (one pair each: U, V shared), row 1: BT.601 100% red, then an
  // arbitrary pair whose two pixels share chroma but not luma.
  const int stride = 12;
  std::vector<std::uint8_t> buffer(stride * 2, 0xEE);
  const std::uint8_t row0[8] = {16, 128, 16, 128, 235, 128, 235, 128};
  const std::uint8_t row1[8] = {81, 90, 81, 240, 60, 100, 200, 170};
  std::copy(row0, row0 + 8, buffer.begin());
  std::copy(row1, row1 + 8, buffer.begin() + stride);
  cv::Mat bgr;
  ASSERT_TRUE(ConvertYuyvToBgr(buffer.data(), buffer.size(), {4, 2, stride}, &bgr).ok());
  ASSERT_EQ(bgr.type(), CV_8UC3);
  ASSERT_EQ(bgr.size(), cv::Size(4, 2));
  ExpectNear(bgr.at<cv::Vec3b>(0, 0), {0, 0, 0}, 0, "black");
  ExpectNear(bgr.at<cv::Vec3b>(0, 1), {0, 0, 0}, 0, "black");
  ExpectNear(bgr.at<cv::Vec3b>(0, 2), {255, 255, 255}, 0, "white");
  ExpectNear(bgr.at<cv::Vec3b>(0, 3), {255, 255, 255}, 0, "white");
  ExpectNear(bgr.at<cv::Vec3b>(1, 0), {0, 0, 255}, 2, "red");  // BGR order: red is last
  ExpectNear(bgr.at<cv::Vec3b>(1, 2), Bt601ToBgr(60, 100, 170), 1, "pair pixel 0");
  ExpectNear(bgr.at<cv::Vec3b>(1, 3), Bt601ToBgr(200, 100, 170), 1, "pair pixel 1");
}

TEST(PixelFormatsTest, UyvyIsTheSameColourInAnotherByteOrder) {
  const std::uint8_t uyvy[4] = {100, 60, 170, 200};  // U Y0 V Y1
  cv::Mat bgr;
  ASSERT_TRUE(ConvertUyvyToBgr(uyvy, 4, {2, 1, 4}, &bgr).ok());
  ExpectNear(bgr.at<cv::Vec3b>(0, 0), Bt601ToBgr(60, 100, 170), 1, "pixel 0");
  ExpectNear(bgr.at<cv::Vec3b>(0, 1), Bt601ToBgr(200, 100, 170), 1, "pixel 1");
}

TEST(PixelFormatsTest, YuyvRejectsShortBuffersOddWidthAndBadStride) {
  std::vector<std::uint8_t> buffer(16, 0);
  cv::Mat bgr;
  // 4x2 needs stride*(h-1) + 8 = 16 bytes with stride 8: one byte less must fail.
  EXPECT_TRUE(ConvertYuyvToBgr(buffer.data(), 16, {4, 2, 8}, &bgr).ok());
  EXPECT_EQ(ConvertYuyvToBgr(buffer.data(), 15, {4, 2, 8}, &bgr).code(), StatusCode::kCorrupt);
  EXPECT_EQ(ConvertYuyvToBgr(buffer.data(), 16, {3, 2, 8}, &bgr).code(), StatusCode::kCorrupt);
  EXPECT_EQ(ConvertYuyvToBgr(buffer.data(), 16, {4, 2, 6}, &bgr).code(), StatusCode::kCorrupt);
  EXPECT_EQ(ConvertYuyvToBgr(buffer.data(), 16, {0, 2, 8}, &bgr).code(), StatusCode::kOutOfRange);
  EXPECT_EQ(ConvertYuyvToBgr(buffer.data(), 16, {100000, 1, 200000}, &bgr).code(),
            StatusCode::kOutOfRange);
}

TEST(PixelFormatsTest, Rgb24SwapsToBgrAndSkipsPadding) {
  const std::uint8_t rgb[2 * 8] = {1, 2, 3, 4,  5,  6,  99, 99,  // row 0 + 2 junk bytes
                                   7, 8, 9, 10, 11, 12, 99, 99};
  cv::Mat bgr;
  ASSERT_TRUE(ConvertRgb24ToBgr(rgb, sizeof(rgb), {2, 2, 8}, &bgr).ok());
  EXPECT_EQ(bgr.at<cv::Vec3b>(0, 0), cv::Vec3b(3, 2, 1));
  EXPECT_EQ(bgr.at<cv::Vec3b>(0, 1), cv::Vec3b(6, 5, 4));
  EXPECT_EQ(bgr.at<cv::Vec3b>(1, 1), cv::Vec3b(12, 11, 10));
}

TEST(PixelFormatsTest, Z16LittleEndianUnitsToMillimetres) {
  // Row stride 6 bytes for 2 pixels: 2 bytes of padding per row.
  const std::uint8_t z16[12] = {0x34, 0x12, 0x39, 0x30, 0xFF, 0xFF,   // 0x1234, 12345
                                0x00, 0x00, 0xFF, 0xFF, 0xAA, 0xAA};  // 0, 65535
  cv::Mat mm;
  ASSERT_TRUE(ConvertZ16ToMillimetres(z16, sizeof(z16), {2, 2, 6}, 0.001, &mm).ok());
  ASSERT_EQ(mm.type(), CV_16UC1);
  EXPECT_EQ(mm.at<std::uint16_t>(0, 0), 0x1234);
  EXPECT_EQ(mm.at<std::uint16_t>(0, 1), 12345);
  EXPECT_EQ(mm.at<std::uint16_t>(1, 0), 0);
  EXPECT_EQ(mm.at<std::uint16_t>(1, 1), 65535);

  // 100 micrometre units (OpenNI2 DEPTH_100_UM): 4660 -> 466.0 mm, 12345 -> 1234.5 -> 1235.
  ASSERT_TRUE(ConvertZ16ToMillimetres(z16, sizeof(z16), {2, 2, 6}, 0.0001, &mm).ok());
  EXPECT_EQ(mm.at<std::uint16_t>(0, 0), 466);
  EXPECT_EQ(mm.at<std::uint16_t>(0, 1), 1235);
  EXPECT_EQ(mm.at<std::uint16_t>(1, 1), 6554);  // 6553.5 rounds up

  // Centimetre units: 12345 cm does not fit 16-bit millimetres and becomes "no depth".
  ASSERT_TRUE(ConvertZ16ToMillimetres(z16, sizeof(z16), {2, 2, 6}, 0.01, &mm).ok());
  EXPECT_EQ(mm.at<std::uint16_t>(0, 0), 46600);
  EXPECT_EQ(mm.at<std::uint16_t>(0, 1), 0);

  EXPECT_EQ(ConvertZ16ToMillimetres(z16, 9, {2, 2, 6}, 0.001, &mm).code(), StatusCode::kCorrupt);
  EXPECT_EQ(ConvertZ16ToMillimetres(z16, 12, {2, 2, 6}, 0.0, &mm).code(),
            StatusCode::kInvalidArgument);
}

std::vector<std::uint8_t> EncodeJpeg(const cv::Mat& bgr) {
  std::vector<std::uint8_t> jpeg;
  EXPECT_TRUE(cv::imencode(".jpg", bgr, jpeg, {cv::IMWRITE_JPEG_QUALITY, 100}));
  return jpeg;
}

TEST(PixelFormatsTest, MjpegDecodesAFrameEncodedElsewhere) {
  // Two flat 16x16 patches (whole MCUs, so chroma subsampling changes nothing).
  cv::Mat original(16, 32, CV_8UC3);
  original(cv::Rect(0, 0, 16, 16)).setTo(cv::Scalar(30, 60, 200));
  original(cv::Rect(16, 0, 16, 16)).setTo(cv::Scalar(220, 180, 20));
  const std::vector<std::uint8_t> jpeg = EncodeJpeg(original);
  MjpegDecoder decoder;
  cv::Mat bgr;
  ASSERT_TRUE(decoder.Decode(jpeg.data(), jpeg.size(), 32, 16, &bgr).ok());
  ASSERT_EQ(bgr.size(), cv::Size(32, 16));
  ExpectNear(bgr.at<cv::Vec3b>(8, 8), {30, 60, 200}, 3, "left patch");
  ExpectNear(bgr.at<cv::Vec3b>(8, 24), {220, 180, 20}, 3, "right patch");
}

TEST(PixelFormatsTest, MjpegRejectsWrongSizeTruncatedAndGarbageFrames) {
  cv::Mat original(32, 32, CV_8UC3);
  cv::randu(original, 0, 255);
  const std::vector<std::uint8_t> jpeg = EncodeJpeg(original);
  MjpegDecoder decoder;
  cv::Mat bgr;
  EXPECT_EQ(decoder.Decode(jpeg.data(), jpeg.size(), 64, 32, &bgr).code(), StatusCode::kCorrupt);
  EXPECT_EQ(decoder.Decode(jpeg.data(), jpeg.size() / 2, 32, 32, &bgr).code(),
            StatusCode::kCorrupt);
  std::vector<std::uint8_t> garbage(jpeg.size(), 0x5A);
  EXPECT_EQ(decoder.Decode(garbage.data(), garbage.size(), 32, 32, &bgr).code(),
            StatusCode::kCorrupt);
  EXPECT_EQ(decoder.Decode(nullptr, 0, 32, 32, &bgr).code(), StatusCode::kCorrupt);
  EXPECT_TRUE(decoder.Decode(jpeg.data(), jpeg.size(), 32, 32, &bgr).ok());
  // A frame cut inside its headers (before the scan), then a good frame: the decoder must
  // not carry the failure over.
  EXPECT_EQ(decoder.Decode(jpeg.data(), 200, 32, 32, &bgr).code(), StatusCode::kCorrupt);
  const Status after = decoder.Decode(jpeg.data(), jpeg.size(), 32, 32, &bgr);
  EXPECT_TRUE(after.ok()) << after.ToString();
}

TEST(PixelFormatsTest, ColourLargerThanDepthIsResizedToTheDepthSize) {
  cv::Mat hd(1080, 1920, CV_8UC3, cv::Scalar(10, 20, 30));
  const cv::Mat resized = ResizeColorToDepth(hd, cv::Size(640, 480));
  ASSERT_EQ(resized.size(), cv::Size(640, 480));
  EXPECT_EQ(resized.at<cv::Vec3b>(240, 320), cv::Vec3b(10, 20, 30));

  // Shrinking averages (no aliasing): a 0/200 checkerboard halves to a flat 100.
  cv::Mat checker(4, 4, CV_8UC3);
  for (int y = 0; y < 4; ++y)
    for (int x = 0; x < 4; ++x) checker.at<cv::Vec3b>(y, x) = cv::Vec3b::all((x + y) % 2 ? 200 : 0);
  const cv::Mat half = ResizeColorToDepth(checker, cv::Size(2, 2));
  for (int y = 0; y < 2; ++y)
    for (int x = 0; x < 2; ++x) EXPECT_EQ(half.at<cv::Vec3b>(y, x), cv::Vec3b::all(100));

  // Same size: the very same image, no copy.
  const cv::Mat same = ResizeColorToDepth(checker, cv::Size(4, 4));
  EXPECT_EQ(same.data, checker.data);
}

TEST(PixelFormatsTest, FourccText) {
  EXPECT_EQ(FourccToString(0x56595559u), "YUYV");
  EXPECT_EQ(FourccToString(0x2036315Au), "Z16 ");
}

}  // namespace
}  // namespace ccmd
