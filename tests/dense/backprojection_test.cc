#include "libccmd/dense/backprojection.h"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>

#include "libccmd/dense/label.h"

namespace ccmd {
namespace {

PinholeCamera SmallCamera() {
  PinholeCamera c;
  c.width = 4;
  c.height = 3;
  c.fx = 100.0;
  c.fy = 200.0;
  c.cx = 1.5;
  c.cy = 1.0;
  return c;
}

TEST(BackProjectionTest, PixelsFollowThePinholeModelWithColoursAsRgb) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(0));
  cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  depth.at<std::uint16_t>(0, 0) = 2000;  // u=0, v=0 at 2 m
  depth.at<std::uint16_t>(2, 3) = 500;   // u=3, v=2 at 0.5 m
  bgr.at<cv::Vec3b>(0, 0) = cv::Vec3b(10, 20, 30);
  bgr.at<cv::Vec3b>(2, 3) = cv::Vec3b(1, 2, 3);
  auto cloud = BackProjectKeyframe(depth, bgr, camera);
  ASSERT_TRUE(cloud.ok()) << cloud.status().ToString();
  ASSERT_EQ(cloud->size(), 2u);
  // X = Z (u - cx) / fx, Y = Z (v - cy) / fy by hand.
  EXPECT_NEAR(cloud->points[0].x(), 2.0 * (0 - 1.5) / 100.0, 1e-6);  // -0.03
  EXPECT_NEAR(cloud->points[0].y(), 2.0 * (0 - 1.0) / 200.0, 1e-6);  // -0.01
  EXPECT_NEAR(cloud->points[0].z(), 2.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].x(), 0.5 * 1.5 / 100.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].y(), 0.5 * 1.0 / 200.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].z(), 0.5, 1e-6);
  EXPECT_EQ(cloud->colors[0], (std::array<std::uint8_t, 3>{30, 20, 10}));
  EXPECT_EQ(cloud->colors[1], (std::array<std::uint8_t, 3>{3, 2, 1}));
}

TEST(BackProjectionTest, DepthRangeLimitsAreInclusiveAndZeroIsInvalid) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(0));
  const std::uint16_t values[] = {0, 299, 300, 1000, 3000, 3001, 65535};
  for (int i = 0; i < 7; ++i) depth.at<std::uint16_t>(i / 4, i % 4) = values[i];
  const cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  BackProjectionOptions options;
  options.min_depth_m = 0.3;
  options.max_depth_m = 3.0;
  auto cloud = BackProjectKeyframe(depth, bgr, camera, options);
  ASSERT_TRUE(cloud.ok());
  ASSERT_EQ(cloud->size(), 3u);  // 300, 1000 and 3000 mm
  EXPECT_FLOAT_EQ(cloud->points[0].z(), 0.3f);
  EXPECT_FLOAT_EQ(cloud->points[1].z(), 1.0f);
  EXPECT_FLOAT_EQ(cloud->points[2].z(), 3.0f);
}

TEST(BackProjectionTest, ReadsImagesThatAreViewsOfLargerOnes) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat big_depth(10, 10, CV_16UC1, cv::Scalar(1000));
  cv::Mat big_bgr(10, 10, CV_8UC3, cv::Scalar(5, 6, 7));
  const cv::Rect roi(2, 3, 4, 3);
  auto cloud = BackProjectKeyframe(big_depth(roi), big_bgr(roi), camera);
  ASSERT_TRUE(cloud.ok());
  EXPECT_EQ(cloud->size(), 12u);
}

TEST(BackProjectionTest, BadImagesAndCamerasAreErrors) {
  const PinholeCamera camera = SmallCamera();
  const cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(1000));
  const cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  EXPECT_TRUE(BackProjectKeyframe(depth, bgr, camera).ok());
  const auto code = [&](const cv::Mat& d, const cv::Mat& c, const PinholeCamera& cam) {
    return BackProjectKeyframe(d, c, cam).status().code();
  };
  EXPECT_EQ(code(cv::Mat(3, 4, CV_32FC1, cv::Scalar(1)), bgr, camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(3, 4, CV_8UC1, cv::Scalar(0)), camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(cv::Mat(), bgr, camera), StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(), camera), StatusCode::kInvalidArgument);
  // Sizes that disagree with the camera or with each other.
  EXPECT_EQ(code(cv::Mat(6, 8, CV_16UC1, cv::Scalar(1)), cv::Mat(6, 8, CV_8UC3), camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(4, 3, CV_8UC3), camera), StatusCode::kInvalidArgument);
  PinholeCamera broken = camera;
  broken.fx = 0;
  EXPECT_EQ(code(depth, bgr, broken), StatusCode::kInvalidArgument);
  BackProjectionOptions inverted;
  inverted.min_depth_m = 2.0;
  inverted.max_depth_m = 1.0;
  EXPECT_EQ(BackProjectKeyframe(depth, bgr, camera, inverted).status().code(),
            StatusCode::kInvalidArgument);
}

TEST(LabelTest, PacksAgentAboveKeyframeAndChecksLimits) {
  auto label = EncodeLabel({AgentId(3), KeyframeId(5)});
  ASSERT_TRUE(label.ok());
  EXPECT_EQ(*label, 0x03000005u);
  EXPECT_EQ(*EncodeLabel({AgentId(255), KeyframeId(0xFFFFFF)}), 0xFFFFFFFFu);
  const GlobalKeyframeId back = DecodeLabel(0x02ABCDEFu);
  EXPECT_EQ(back.agent, AgentId(2));
  EXPECT_EQ(back.keyframe, KeyframeId(0xABCDEF));
  EXPECT_EQ(EncodeLabel({AgentId(256), KeyframeId(0)}).status().code(), StatusCode::kOutOfRange);
  EXPECT_EQ(EncodeLabel({AgentId(0), KeyframeId(1u << 24)}).status().code(),
            StatusCode::kOutOfRange);
  // A later keyframe of an agent, or any keyframe of a larger agent, has a larger label.
  EXPECT_LT(*EncodeLabel({AgentId(1), KeyframeId(9)}), *EncodeLabel({AgentId(1), KeyframeId(10)}));
  EXPECT_LT(*EncodeLabel({AgentId(1), KeyframeId(0xFFFFFF)}),
            *EncodeLabel({AgentId(2), KeyframeId(0)}));
}

}  // namespace
}  // namespace ccmd
