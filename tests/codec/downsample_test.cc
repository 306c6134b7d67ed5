#include "libccmd/codec/depth_downsample.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

cv::Mat Block(std::initializer_list<std::uint16_t> values, int rows, int cols) {
  cv::Mat m(rows, cols, CV_16UC1);
  auto it = values.begin();
  for (int y = 0; y < rows; ++y) {
    for (int x = 0; x < cols; ++x) m.at<std::uint16_t>(y, x) = *it++;
  }
  return m;
}

TEST(DownsampleTest, PicksARealDepthNeverAnAverage) {
  // A block across a depth edge: two pixels at 1000, two at 3000. An average would invent
  // 2000 mm, a depth no surface has.
  const cv::Mat edge = Block({1000, 3000, 1000, 3000}, 2, 2);
  EXPECT_EQ(DownsampleDepth(edge, 2, DownsampleMethod::kMedianValid)->at<std::uint16_t>(0, 0),
            1000);
  EXPECT_EQ(DownsampleDepth(edge, 2, DownsampleMethod::kNearestValid)->at<std::uint16_t>(0, 0),
            1000);
  // Majority wins for the median: three far, one near.
  const cv::Mat mostly_far = Block({1000, 3000, 3000, 3000}, 2, 2);
  EXPECT_EQ(DownsampleDepth(mostly_far, 2)->at<std::uint16_t>(0, 0), 3000);
  EXPECT_EQ(
      DownsampleDepth(mostly_far, 2, DownsampleMethod::kNearestValid)->at<std::uint16_t>(0, 0),
      1000);
  // Invalid pixels are ignored; an all-invalid block stays invalid.
  const cv::Mat holes = Block({0, 2000, 0, 0, 0, 0, 0, 0}, 2, 4);
  const cv::Mat out = *DownsampleDepth(holes, 2);
  EXPECT_EQ(out.at<std::uint16_t>(0, 0), 2000);
  EXPECT_EQ(out.at<std::uint16_t>(0, 1), 0);
  EXPECT_EQ(DownsampleDepth(holes, 2, DownsampleMethod::kTopLeft)->at<std::uint16_t>(0, 0), 0);
}

TEST(DownsampleTest, OnASlantedPlaneGivesTheDepthAtTheBlockCentre) {
  // A floor seen obliquely: depth 2000 mm + 7 mm per column + 3 mm per row, the steps of a
  // plane at about 60 degrees. The output pixel's ray passes through the block's centre
  // (resized cameras keep pixel centres), so it must carry the depth there; any one pixel of
  // the block is off by up to half a pixel's step.
  cv::Mat plane(8, 8, CV_16UC1);
  for (int y = 0; y < 8; ++y) {
    for (int x = 0; x < 8; ++x) plane.at<std::uint16_t>(y, x) = 2000 + 7 * x + 3 * y;
  }
  for (const int factor : {2, 4}) {
    const cv::Mat out = *DownsampleDepth(plane, factor);
    for (int y = 0; y < out.rows; ++y) {
      for (int x = 0; x < out.cols; ++x) {
        const double centre_u = factor * x + (factor - 1) / 2.0;
        const double centre_v = factor * y + (factor - 1) / 2.0;
        EXPECT_NEAR(out.at<std::uint16_t>(y, x), 2000 + 7 * centre_u + 3 * centre_v, 0.5)
            << "factor " << factor << " block " << x << "," << y;
      }
    }
  }
  // Halves round to even: 2001 and 2002 give 2002, 2002 and 2003 give 2002.
  EXPECT_EQ(DownsampleDepth(Block({2000, 2001, 2002, 2009}, 2, 2), 2)->at<std::uint16_t>(0, 0),
            2002);
  EXPECT_EQ(DownsampleDepth(Block({2000, 2002, 2003, 2009}, 2, 2), 2)->at<std::uint16_t>(0, 0),
            2002);
  // Middle depths 10 % apart are two surfaces: the nearer, never a depth between them.
  EXPECT_EQ(DownsampleDepth(Block({1000, 1000, 1100, 1100}, 2, 2), 2)->at<std::uint16_t>(0, 0),
            1000);
}

TEST(DownsampleTest, FactorFourAndSizes) {
  cv::Mat m(8, 12, CV_16UC1);
  for (int y = 0; y < 8; ++y) {
    for (int x = 0; x < 12; ++x)
      m.at<std::uint16_t>(y, x) = static_cast<std::uint16_t>(100 + y * 12 + x);
  }
  const cv::Mat out = *DownsampleDepth(m, 4);
  ASSERT_EQ(out.size(), cv::Size(3, 2));
  // Block (0, 0) holds 100..103, 112..115, 124..127, 136..139: sixteen values whose middle
  // two (115 and 124) are too far apart to be one surface, so the nearer, 115.
  EXPECT_EQ(out.at<std::uint16_t>(0, 0), 115);
  EXPECT_EQ(DownsampleDepth(m, 1)->size(), m.size());
  EXPECT_EQ(DownsampleDepth(m, 3).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(DownsampleDepth(cv::Mat(4, 4, CV_32F), 2).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(DownsampleFactorForRate(0.25), 4);
  EXPECT_EQ(DownsampleFactorForRate(0.3), 0);
}

}  // namespace
}  // namespace ccmd
