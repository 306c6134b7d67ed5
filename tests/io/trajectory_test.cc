#include "libccmd/io/trajectory.h"

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(TrajectoryTest, WriteThenReadKeepsPosesAndMicroseconds) {
  Trajectory t;
  for (int i = 0; i < 5; ++i) {
    t.push_back({1305031453.359684 + i * 0.033,
                 PoseFromTranslationQuaternion(
                     {0.1 * i, -0.2, 1.5}, Eigen::Quaterniond(Eigen::AngleAxisd(
                                               0.1 * i, Eigen::Vector3d(0, 1, 1).normalized())))});
  }
  testing::TempDir dir;
  ASSERT_TRUE(WriteTumTrajectory(t, dir.File("t.txt"), "test").ok());
  auto r = ReadTumTrajectory(dir.File("t.txt"));
  ASSERT_TRUE(r.ok());
  ASSERT_EQ(r->size(), t.size());
  for (std::size_t i = 0; i < t.size(); ++i) {
    EXPECT_NEAR((*r)[i].timestamp, t[i].timestamp, 1e-6);
    EXPECT_LT(TranslationDistance((*r)[i].T_world_cam, t[i].T_world_cam), 1e-8);
    EXPECT_LT(RotationDistance((*r)[i].T_world_cam, t[i].T_world_cam), 1e-8);
  }
}

// Found by fuzzing: a line read with a huge (finite) number was written cut short.
TEST(TrajectoryTest, HugeNumbersAreWrittenWhole) {
  const std::string text =
      "2.2e216 0.1 0 0 0 1 0 0\n"
      "3 -1e300 1e300 -1.5e308 0 0 0 1\n"
      "4 1 2 3 0 0 0 1\n";
  auto t = ParseTumTrajectory(text, "huge");
  ASSERT_TRUE(t.ok()) << t.status().ToString();
  auto again = ParseTumTrajectory(FormatTumTrajectory(*t), "again");
  ASSERT_TRUE(again.ok()) << again.status().ToString();
  ASSERT_EQ(again->size(), 3u);
  for (std::size_t i = 0; i < 3; ++i) {
    EXPECT_EQ((*again)[i].timestamp, (*t)[i].timestamp);
    EXPECT_EQ((*again)[i].T_world_cam.translation(), (*t)[i].T_world_cam.translation());
  }
}

// Found by fuzzing: a quaternion with huge components was read as the identity.
TEST(TrajectoryTest, HugeQuaternionsGiveTheirRotation) {
  auto t = ParseTumTrajectory("0 0 0 0 0 1e200 0 1e200\n1 0 0 0 0 1 0 1\n", "huge");
  ASSERT_TRUE(t.ok()) << t.status().ToString();
  ASSERT_EQ(t->size(), 2u);
  EXPECT_NEAR(RotationAngle((*t)[0].T_world_cam), M_PI / 2, 1e-12);
  EXPECT_LT(RotationDistance((*t)[0].T_world_cam, (*t)[1].T_world_cam), 1e-12);
}

TEST(TrajectoryTest, BadLinesReportFileAndLine) {
  auto r = ParseTumTrajectory("# c\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", "gt.txt");
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("gt.txt:3"), std::string::npos);
  EXPECT_FALSE(ParseTumTrajectory("1 0 0 0 0 0 0 0\n", "zero-q").ok());
}

TEST(TrajectoryTest, InterpolatesWithinGapOnly) {
  const Trajectory t = {
      {1.0, PoseFromTranslationQuaternion({0, 0, 0}, Eigen::Quaterniond::Identity())},
      {1.1, PoseFromTranslationQuaternion({1, 0, 0}, Eigen::Quaterniond::Identity())},
      {2.0, PoseFromTranslationQuaternion({2, 0, 0}, Eigen::Quaterniond::Identity())}};
  const auto mid = InterpolateTrajectory(t, 1.025, 0.2);
  ASSERT_TRUE(mid.has_value());
  EXPECT_NEAR(mid->translation().x(), 0.25, 1e-12);
  EXPECT_FALSE(InterpolateTrajectory(t, 1.5, 0.2).has_value());  // samples 0.9 s apart
  EXPECT_FALSE(InterpolateTrajectory(t, 0.5, 0.2).has_value());  // before the first sample
  EXPECT_TRUE(InterpolateTrajectory(t, 2.0, 0.2).has_value());   // exactly the last sample
}

}  // namespace
}  // namespace ccmd
