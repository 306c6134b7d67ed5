#include "libccmd/codec/colour_codec.h"

#include <cmath>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/util/random.h"

namespace ccmd {
namespace {

// Smooth colour gradients plus a few shapes: what a JPEG codes well.
cv::Mat MakeColour(int width, int height) {
  cv::Mat bgr(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const bool box = x > width / 3 && x < width / 2 && y > height / 4 && y < height / 2;
      bgr.at<cv::Vec3b>(y, x) = box ? cv::Vec3b(30, 200, 40)
                                    : cv::Vec3b(static_cast<uchar>(255 * x / width),
                                                static_cast<uchar>(255 * y / height), 128);
    }
  }
  return bgr;
}

TEST(ColourCodecTest, RoundTripKeepsTheImage) {
  const cv::Mat bgr = MakeColour(320, 240);
  ColourEncodeOptions o;
  o.quality = 90;
  auto jpeg = EncodeColour(bgr, bgr.size(), o);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status().ToString();
  EXPECT_LT(jpeg->size(), 320u * 240u * 3u / 10u);  // far below raw
  auto back = DecodeColour(*jpeg);
  ASSERT_TRUE(back.ok()) << back.status().ToString();
  ASSERT_EQ(back->size(), bgr.size());
  EXPECT_GT(cv::PSNR(*back, bgr), 30.0);
}

TEST(ColourCodecTest, ResizesToTheDepthThenDownsamples) {
  const cv::Mat hd = MakeColour(1920, 1080);
  ColourEncodeOptions o;
  o.downsample = 2;
  auto jpeg = EncodeColour(hd, cv::Size(640, 480), o);
  ASSERT_TRUE(jpeg.ok());
  auto back = DecodeColour(*jpeg);
  ASSERT_TRUE(back.ok());
  EXPECT_EQ(back->size(), cv::Size(320, 240));
  auto prepared = PrepareColour(hd, cv::Size(640, 480), 2);
  ASSERT_TRUE(prepared.ok());
  EXPECT_GT(cv::PSNR(*back, *prepared), 30.0);
}

TEST(ColourCodecTest, BadInputAndCorruptBytesAreErrors) {
  ColourEncodeOptions o;
  o.quality = 0;
  EXPECT_EQ(EncodeColour(MakeColour(8, 8), {}, o).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(EncodeColour(cv::Mat(8, 8, CV_16UC1), {}, {}).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(DecodeColour({}).status().code(), StatusCode::kCorrupt);
  const std::vector<std::uint8_t> junk = {0xFF, 0xD8, 0xFF, 0x00, 1, 2, 3};
  EXPECT_FALSE(DecodeColour(junk).ok());
  auto jpeg = *EncodeColour(MakeColour(64, 48), {}, {});
  ColourDecodeOptions tight;
  tight.max_pixels = 64 * 48 - 1;
  EXPECT_EQ(DecodeColour(jpeg, tight).status().code(), StatusCode::kOutOfRange);
  jpeg.resize(jpeg.size() / 2);
  EXPECT_FALSE(DecodeColour(jpeg).ok());
}

TEST(RgbdPayloadTest, PacksAndUnpacksAKeyframesImages) {
  RgbdFrame frame;
  frame.bgr = MakeColour(1280, 960);
  frame.depth_mm = cv::Mat(480, 640, CV_16UC1);
  Rng rng(4);
  for (int y = 0; y < 480; ++y) {
    for (int x = 0; x < 640; ++x) {
      frame.depth_mm.at<std::uint16_t>(y, x) =
          static_cast<std::uint16_t>(x % 50 == 0 ? 0 : 1500 + 2 * x + y + rng.UniformInt(0, 3));
    }
  }
  RgbdEncodeOptions o;
  o.downsample = 4;
  auto payload = EncodeRgbdPayload(frame, o);
  ASSERT_TRUE(payload.ok()) << payload.status().ToString();
  EXPECT_EQ(payload->downsample, 4);
  EXPECT_EQ(payload->depth_mode, static_cast<std::uint8_t>(DepthMode::kBounded));
  auto decoded = DecodeRgbdPayload(*payload);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(decoded->bgr.size(), cv::Size(160, 120));
  EXPECT_EQ(decoded->depth_mm.size(), cv::Size(160, 120));
  EXPECT_EQ(decoded->downsample, 4);
  // The payload's fields must agree with the depth bitstream.
  RgbdPayload wrong = *payload;
  wrong.downsample = 2;
  EXPECT_EQ(DecodeRgbdPayload(wrong).status().code(), StatusCode::kCorrupt);
}

}  // namespace
}  // namespace ccmd
