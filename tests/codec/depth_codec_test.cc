#include "libccmd/codec/depth_codec.h"

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "libccmd/codec/depth_quantizer.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/random.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

// A depth image like a Kinect's: a tilted floor, a wall, a box in front (depth edges),
// holes, noise, and values snapped to disparity steps (few distinct values).
cv::Mat MakeDepth(int width, int height, std::uint64_t seed) {
  Rng rng(seed);
  cv::Mat depth(height, width, CV_16UC1);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      double z = 2500.0 + 8.0 * x - 3.0 * y;                            // wall
      if (y > height / 2) z = 1200.0 + 4000.0 * (height - y) / height;  // floor
      if (x > width / 3 && x < width / 2 && y > height / 4 && y < height / 2) z = 900.0;
      z += rng.Normal(0, 0.002 * z);
      const double disparity = std::round(8 * 580.0 * 75.0 / z);  // 1/8 px steps
      z = 8 * 580.0 * 75.0 / disparity;
      const bool hole = (x / 17 + y / 13) % 11 == 0 || rng.Bernoulli(0.01);
      depth.at<std::uint16_t>(y, x) = hole ? 0 : static_cast<std::uint16_t>(std::lround(z));
    }
  }
  return depth;
}

DepthEncodeOptions Options(DepthMode mode, int bound_e4 = kDefaultBoundE4) {
  DepthEncodeOptions o;
  o.mode = mode;
  o.bound_e4 = bound_e4;
  return o;
}

// Checks a decoded image against the original with bounds computed from each mode's
// definition (not from the codec): exact, eq. 6 bins, or the relative bound.
void ExpectWithinModeBound(const cv::Mat& original, const cv::Mat& decoded, DepthMode mode,
                           int bound_e4) {
  ASSERT_EQ(decoded.size(), original.size());
  ASSERT_EQ(decoded.type(), CV_16UC1);
  for (int y = 0; y < original.rows; ++y) {
    for (int x = 0; x < original.cols; ++x) {
      const int d = original.at<std::uint16_t>(y, x);
      const int e = decoded.at<std::uint16_t>(y, x);
      const bool eq6 = mode == DepthMode::kEq6Rle || mode == DepthMode::kEq6RleLz77 ||
                       mode == DepthMode::kQuantised;
      if (eq6 && (d <= 200 || d > 24000)) {
        ASSERT_EQ(e, 0) << x << "," << y;
        continue;
      }
      if (d == 0) {
        ASSERT_EQ(e, 0) << x << "," << y;
        continue;
      }
      ASSERT_NE(e, 0) << x << "," << y;
      if (mode == DepthMode::kBounded) {
        ASSERT_LE(10000LL * std::abs(e - d), static_cast<long long>(bound_e4) * d) << d;
      } else if (eq6) {
        ASSERT_LE(std::abs(e - d), d < 3000 ? 0 : d < 6000 ? 1 : d < 12000 ? 2 : 4) << d;
      } else {
        ASSERT_EQ(e, d) << x << "," << y;
      }
    }
  }
}

class DepthModeTest : public ::testing::TestWithParam<DepthMode> {};

TEST_P(DepthModeTest, RoundTripWithinTheModesBound) {
  const DepthMode mode = GetParam();
  const cv::Mat depth = MakeDepth(160, 120, 1);
  auto bytes = EncodeDepth(depth, Options(mode));
  ASSERT_TRUE(bytes.ok()) << bytes.status().ToString();
  DepthHeader header;
  auto decoded = DecodeDepth(*bytes, {}, &header);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  EXPECT_EQ(header.mode, mode);
  EXPECT_EQ(header.width, 160);
  EXPECT_EQ(header.height, 120);
  ExpectWithinModeBound(depth, *decoded, mode, kDefaultBoundE4);
}

TEST_P(DepthModeTest, EveryTruncationIsAnError) {
  const cv::Mat depth = MakeDepth(24, 16, 2);
  const Bytes bytes = *EncodeDepth(depth, Options(GetParam()));
  for (std::size_t n = 0; n < bytes.size(); ++n) {
    EXPECT_FALSE(DecodeDepth(std::span(bytes.data(), n)).ok()) << n << " of " << bytes.size();
  }
  Bytes longer = bytes;
  longer.push_back(0);
  EXPECT_FALSE(DecodeDepth(longer).ok());
}

TEST_P(DepthModeTest, BitFlipsNeverCrash) {
  const cv::Mat depth = MakeDepth(40, 30, 3);
  const Bytes bytes = *EncodeDepth(depth, Options(GetParam()));
  Rng rng(static_cast<std::uint64_t>(GetParam()) + 11);
  for (int trial = 0; trial < 300; ++trial) {
    Bytes flipped = bytes;
    const int bit = rng.UniformInt(0, static_cast<int>(bytes.size()) * 8 - 1);
    flipped[bit / 8] ^= static_cast<std::uint8_t>(1u << (bit % 8));
    auto result = DecodeDepth(flipped);  // an error or some image; never a crash
    if (result.ok()) {
      EXPECT_EQ(result->type(), CV_16UC1);
    }
  }
}

INSTANTIATE_TEST_SUITE_P(AllModes, DepthModeTest,
                         ::testing::Values(DepthMode::kRaw, DepthMode::kRle, DepthMode::kRleLz77,
                                           DepthMode::kEq6Rle, DepthMode::kEq6RleLz77,
                                           DepthMode::kLossless, DepthMode::kQuantised,
                                           DepthMode::kBounded),
                         [](const auto& info) {
                           std::string name = DepthModeName(info.param);
                           for (char& c : name) {
                             if (c == '+' || c == '-') c = '_';
                           }
                           return name;
                         });

TEST(DepthCodecTest, BoundedModeHoldsItsBoundForSeveralBounds) {
  const cv::Mat depth = MakeDepth(160, 120, 4);
  for (int bound : {10, 50, 100, 300, 2000}) {
    auto bytes = EncodeDepth(depth, Options(DepthMode::kBounded, bound));
    ASSERT_TRUE(bytes.ok());
    auto decoded = DecodeDepth(*bytes);
    ASSERT_TRUE(decoded.ok()) << bound;
    ExpectWithinModeBound(depth, *decoded, DepthMode::kBounded, bound);
  }
}

TEST(DepthCodecTest, ExtremeValuesSurvive) {
  cv::Mat depth(8, 9, CV_16UC1);
  const std::uint16_t values[] = {0, 1, 2, 199, 200, 201, 65534, 65535, 30000};
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) depth.at<std::uint16_t>(y, x) = values[(x + y) % 9];
  }
  for (DepthMode mode : {DepthMode::kRaw, DepthMode::kRle, DepthMode::kRleLz77,
                         DepthMode::kLossless, DepthMode::kBounded, DepthMode::kQuantised}) {
    auto decoded = DecodeDepth(*EncodeDepth(depth, Options(mode)));
    ASSERT_TRUE(decoded.ok()) << DepthModeName(mode);
    ExpectWithinModeBound(depth, *decoded, mode, kDefaultBoundE4);
  }
  const cv::Mat empty_frame = cv::Mat::zeros(10, 10, CV_16UC1);
  for (DepthMode mode : {DepthMode::kLossless, DepthMode::kBounded, DepthMode::kQuantised}) {
    auto decoded = DecodeDepth(*EncodeDepth(empty_frame, Options(mode)));
    ASSERT_TRUE(decoded.ok());
    EXPECT_EQ(cv::countNonZero(*decoded), 0);
  }
}

// Noise-like depths: a dense histogram (about 1750 of the 2000 values in range are used, so
// no value table) and residuals far beyond a byte (escapes) in every mode that predicts.
TEST(DepthCodecTest, DenseValuesAndLargeResiduals) {
  Rng rng(12);
  cv::Mat depth(64, 64, CV_16UC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      depth.at<std::uint16_t>(y, x) =
          static_cast<std::uint16_t>(x % 13 == 5 ? 0 : rng.UniformInt(1000, 2999));
    }
  }
  for (DepthMode mode : {DepthMode::kLossless, DepthMode::kQuantised, DepthMode::kBounded}) {
    auto bytes = EncodeDepth(depth, Options(mode));
    ASSERT_TRUE(bytes.ok());
    if (mode == DepthMode::kLossless) {
      EXPECT_EQ((*bytes)[kDepthHeaderSize], 0);  // plain depths, not packed
    }
    auto decoded = DecodeDepth(*bytes);
    ASSERT_TRUE(decoded.ok()) << DepthModeName(mode) << ": " << decoded.status().ToString();
    ExpectWithinModeBound(depth, *decoded, mode, kDefaultBoundE4);
  }
}

TEST(DepthCodecTest, DownsamplesBeforeCoding) {
  const cv::Mat depth = MakeDepth(160, 120, 5);
  DepthEncodeOptions o = Options(DepthMode::kLossless);
  o.downsample = 4;
  DepthHeader header;
  auto decoded = DecodeDepth(*EncodeDepth(depth, o), {}, &header);
  ASSERT_TRUE(decoded.ok());
  EXPECT_EQ(header.downsample, 4);
  EXPECT_EQ(decoded->cols, 40);
  EXPECT_EQ(decoded->rows, 30);
  o.downsample = 3;
  EXPECT_EQ(EncodeDepth(depth, o).status().code(), StatusCode::kInvalidArgument);
}

TEST(DepthCodecTest, HeaderErrorsAreClear) {
  const Bytes bytes = *EncodeDepth(MakeDepth(16, 8, 6), Options(DepthMode::kLossless));
  Bytes bad_magic = bytes;
  bad_magic[0] = 0;
  EXPECT_EQ(DecodeDepth(bad_magic).status().code(), StatusCode::kCorrupt);
  Bytes bad_version = bytes;
  bad_version[1] = 9;
  EXPECT_EQ(DecodeDepth(bad_version).status().code(), StatusCode::kUnsupported);
  Bytes bad_mode = bytes;
  bad_mode[2] = 99;
  EXPECT_EQ(DecodeDepth(bad_mode).status().code(), StatusCode::kCorrupt);
  Bytes huge = bytes;
  huge[4] = huge[5] = huge[6] = huge[7] = 0xFF;  // 65535 x 65535
  EXPECT_EQ(DecodeDepth(huge).status().code(), StatusCode::kOutOfRange);
  DepthDecodeOptions tight;
  tight.max_pixels = 100;
  EXPECT_EQ(DecodeDepth(bytes, tight).status().code(), StatusCode::kOutOfRange);
  EXPECT_EQ(ParseDepthHeader(bytes)->width, 16);
}

TEST(DepthCodecTest, ModeNamesRoundTrip) {
  for (int m = 0; m < kNumDepthModes; ++m) {
    const auto mode = static_cast<DepthMode>(m);
    EXPECT_EQ(*ParseDepthMode(DepthModeName(mode)), mode);
  }
  EXPECT_FALSE(ParseDepthMode("jpeg").ok());
}

// The paper's depth on real frames: the modes keep their bounds and the sizes keep their
// order (lossless well below the raw size, bounded far below lossless).
TEST(DepthCodecTest, RealFramesRoundTrip) {
  CCMD_REQUIRE_DATASET(folder, "tum_fr1_desk_9");
  auto seq = TumSequence::Open(folder, PinholeCamera{}, TumOptions{});
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  auto frame = seq->LoadFrame(4);
  ASSERT_TRUE(frame.ok());
  auto half = DownsampleDepth(frame->depth_mm, 2);
  ASSERT_TRUE(half.ok());
  std::size_t lossless = 0, bounded = 0;
  for (DepthMode mode : {DepthMode::kLossless, DepthMode::kQuantised, DepthMode::kBounded}) {
    auto bytes = EncodeDepth(*half, Options(mode));
    ASSERT_TRUE(bytes.ok());
    auto decoded = DecodeDepth(*bytes);
    ASSERT_TRUE(decoded.ok());
    ExpectWithinModeBound(*half, *decoded, mode, kDefaultBoundE4);
    if (mode == DepthMode::kLossless) lossless = bytes->size();
    if (mode == DepthMode::kBounded) bounded = bytes->size();
  }
  EXPECT_LT(lossless, 2u * 320u * 240u / 4u);
  EXPECT_LT(bounded, lossless / 2);
}

}  // namespace
}  // namespace ccmd
