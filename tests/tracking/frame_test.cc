// A tracking frame's features with lens distortion: detected and given depth on the image as
// recorded, then moved to the ideal pinhole camera's pixels, as ORB-SLAM does.

#include "libccmd/tracking/frame.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "libccmd/sensors/synthetic_source.h"
#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

TEST(TrackingFrameTest, KeypointsAreUndistortedAfterTheDepthLookupAtTheRecordedPixel) {
  SyntheticSource source(SyntheticSequenceOptions{});
  RgbdFrame frame;
  ASSERT_TRUE(source.Read(&frame).ok());
  cv::Mat gray;
  cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
  PinholeCamera plain = source.camera();
  PinholeCamera distorted = plain;
  distorted.distortion = testing::TumFr1Camera().distortion;
  const OrbExtractor orb;
  const FrameFeatures raw = ComputeFeatures(gray, frame.depth_mm, orb, plain, 0.1, 10.0);
  const FrameFeatures undistorted = ComputeFeatures(gray, frame.depth_mm, orb, distorted, 0.1, 10.0);
  ASSERT_EQ(raw.keypoints.size(), undistorted.keypoints.size());
  ASSERT_GT(raw.keypoints.size(), 500u);
  double largest_shift = 0;
  for (std::size_t i = 0; i < raw.keypoints.size(); ++i) {
    const cv::Point2f& r = raw.keypoints[i].pt;
    const cv::Point2f& k = undistorted.keypoints[i].pt;
    // The keypoint is the recorded pixel seen through the lens model backwards...
    const Eigen::Vector2d back = distorted.DistortPixel({k.x, k.y});
    EXPECT_NEAR(back.x(), r.x, 1e-3);
    EXPECT_NEAR(back.y(), r.y, 1e-3);
    largest_shift = std::max(largest_shift, std::hypot(double{k.x - r.x}, double{k.y - r.y}));
    // ... its depth is the one at the recorded pixel, and the virtual right coordinate follows
    // the undistorted u.
    EXPECT_EQ(undistorted.depth[i], raw.depth[i]);
    if (raw.depth[i] > 0) EXPECT_NEAR(undistorted.u_right[i], k.x - plain.bf / raw.depth[i], 1e-3);
  }
  EXPECT_GT(largest_shift, 3.0);  // pixels near the corners move
}

}  // namespace
}  // namespace ccmd
