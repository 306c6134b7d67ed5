#include "libccmd/sensors/source_factory.h"

#include <gtest/gtest.h>

#include "libccmd/synth/sequence.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(SourceFactoryTest, SyntheticSegmentDeliversItsFramesThenEnds) {
  SourceOptions options;
  options.segment = std::make_pair(2, 3);
  auto source = OpenSource("synth:frames=30,width=160,height=120,seed=2", options);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  // 30 frames in 3 segments: L = ceil(30 / 2.8) = 11 with overlap 2 reaches only 29 frames,
  // so L = 12, overlap ceil(1.2) = 2, stride 10: 0..11, 10..21, 20..29.
  EXPECT_EQ((*source)->FrameCount(), 12);
  const Trajectory gt = (*source)->GroundTruth();
  ASSERT_EQ(gt.size(), 12u);
  RgbdFrame frame;
  int count = 0;
  Status status;
  while ((status = (*source)->Read(&frame)).ok()) {
    if (count == 0) {
      EXPECT_EQ(frame.index, 10);
    }
    EXPECT_NEAR(frame.timestamp, gt[count].timestamp, 1e-12);
    EXPECT_EQ(frame.depth_mm.cols, 160);
    ++count;
  }
  EXPECT_EQ(status.code(), StatusCode::kEndOfStream);
  EXPECT_EQ(count, 12);
}

TEST(SourceFactoryTest, DatasetSegmentFromAWrittenSequence) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 10;
  o.width = 64;
  o.height = 48;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  SourceOptions options;
  options.segment = std::make_pair(1, 2);
  auto source = OpenSource("tum:" + dir.path(), options);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_EQ((*source)->FrameCount(), 6);  // L = ceil(10 / 1.9) = 6, overlap 1: 0..5, 5..9
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.index, 0);
}

TEST(SourceFactoryTest, BadSpecsAreExplained) {
  auto unknown = OpenSource("kinect9000", SourceOptions());
  ASSERT_FALSE(unknown.ok());
  EXPECT_NE(unknown.status().message().find("tum:DIR"), std::string::npos);
  auto missing = OpenSource("tum:/no/such/folder", SourceOptions());
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.status().message().find("/no/such/folder"), std::string::npos);
  EXPECT_FALSE(OpenSource("synth:frames=-3", SourceOptions()).ok());
  SourceOptions too_many;
  too_many.segment = std::make_pair(1, 20);
  EXPECT_FALSE(OpenSource("synth:frames=10", too_many).ok());
}

}  // namespace
}  // namespace ccmd
