#include "libccmd/eval/plot.h"

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

#include "tests/support/test_support.h"

namespace ccmd {
namespace {

int CountColour(const cv::Mat& img, const cv::Scalar& colour, const cv::Rect& area) {
  int n = 0;
  for (int y = area.y; y < area.y + area.height; ++y) {
    for (int x = area.x; x < area.x + area.width; ++x) {
      const cv::Vec3b p = img.at<cv::Vec3b>(y, x);
      if (p[0] == colour[0] && p[1] == colour[1] && p[2] == colour[2]) ++n;
    }
  }
  return n;
}

TEST(PlotTest, LinesLandWhereTheDataIs) {
  PlotSeries diagonal;
  diagonal.label = "diagonal";
  diagonal.x = {0, 1};
  diagonal.y = {0, 1};
  diagonal.color = SeriesColor(2);
  PlotOptions o;
  o.equal_aspect = true;
  const cv::Mat img = PlotLines({diagonal}, o);
  ASSERT_EQ(img.size(), cv::Size(900, 600));
  // The line rises to the right: the lower-left quarter of the plot area has it, the
  // upper-left quarter does not.
  EXPECT_GT(CountColour(img, diagonal.color, cv::Rect(90, 330, 390, 200)), 100);
  EXPECT_EQ(CountColour(img, diagonal.color, cv::Rect(90, 60, 250, 150)), 0);
}

TEST(PlotTest, BarsScaleWithTheirValues) {
  const cv::Scalar c = SeriesColor(0);
  const cv::Mat img = PlotBars({{"small", {1}}, {"large", {4}}}, {"bytes"}, {c}, PlotOptions());
  // Column of each bar: count bar pixels in the left and right halves of the plot.
  const int small = CountColour(img, c, cv::Rect(90, 0, 390, 600));
  const int large = CountColour(img, c, cv::Rect(480, 0, 390, 600));
  EXPECT_NEAR(static_cast<double>(large) / small, 4.0, 0.3);
}

TEST(PlotTest, WritesAPngThatReadsBack) {
  testing::TempDir dir;
  PlotSeries s;
  s.x = {0, 1, 2};
  s.y = {1, 3, 2};
  ASSERT_TRUE(WritePng(PlotLines({s}, PlotOptions()), dir.File("p.png")).ok());
  const cv::Mat back = cv::imread(dir.File("p.png"));
  EXPECT_EQ(back.cols, 900);
}

}  // namespace
}  // namespace ccmd
