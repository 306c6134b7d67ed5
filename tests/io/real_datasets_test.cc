// Checks the readers on the real recordings in ../shared/datasets (skipped when absent).

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

PinholeCamera Config(const std::string& name) {
  auto c = LoadCameraConfig(std::string(CCMD_CONFIG_DIR) + "/" + name);
  EXPECT_TRUE(c.ok()) << c.status().ToString();
  return c.ok() ? *c : PinholeCamera();
}

TEST(RealDatasetsTest, TumFr1DeskExcerptMatchesShippedAssociations) {
  CCMD_REQUIRE_DATASET(dir, "tum_fr1_desk_9");
  auto seq = TumSequence::Open(dir, Config("tum_fr1.yaml"));
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 9u);
  // Independent reference: the associations.txt shipped with the excerpt.
  auto text = ReadFileToString(dir + "/associations.txt");
  ASSERT_TRUE(text.ok());
  std::size_t i = 0;
  for (const std::string& line : Split(*text, '\n')) {
    const auto f = SplitWhitespace(line);
    if (f.size() < 4) continue;
    ASSERT_LT(i, seq->size());
    EXPECT_NEAR(seq->frame(i).timestamp, *ParseDouble(f[0]), 1e-6);
    EXPECT_NEAR(seq->frame(i).depth_timestamp, *ParseDouble(f[2]), 1e-6);
    ++i;
  }
  EXPECT_EQ(i, 9u);
  // Ground truth (100 Hz motion capture) is found for every frame, near the raw samples.
  for (std::size_t k = 0; k < seq->size(); ++k) {
    ASSERT_TRUE(seq->frame(k).T_world_cam_gt.has_value()) << k;
    double best = 1e9;
    Eigen::Vector3d nearest = Eigen::Vector3d::Zero();
    for (const auto& g : seq->groundtruth()) {
      if (std::abs(g.timestamp - seq->frame(k).timestamp) < best) {
        best = std::abs(g.timestamp - seq->frame(k).timestamp);
        nearest = g.T_world_cam.translation();
      }
    }
    EXPECT_LT(best, 0.01);
    EXPECT_LT((seq->frame(k).T_world_cam_gt->translation() - nearest).norm(), 0.01);
  }
  // Depth conversion: the file's units / 5 = millimetres.
  auto frame = seq->LoadFrame(0);
  ASSERT_TRUE(frame.ok());
  const cv::Mat raw = cv::imread(seq->frame(0).depth_path, cv::IMREAD_UNCHANGED);
  int checked = 0;
  for (int y = 0; y < raw.rows; y += 37) {
    for (int x = 0; x < raw.cols; x += 41) {
      const int r = raw.at<std::uint16_t>(y, x);
      EXPECT_NEAR(frame->depth_mm.at<std::uint16_t>(y, x), r / 5.0, 0.5);
      checked += r > 0;
    }
  }
  EXPECT_GT(checked, 50);
}

TEST(RealDatasetsTest, SevenScenesHasAPosePerFrame) {
  CCMD_REQUIRE_DATASET(dir, "7scenes_redkitchen_0000_0599");
  auto seq = TumSequence::Open(dir, Config("7scenes.yaml"));
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 600u);
  EXPECT_EQ(seq->GroundTruthAtFrames().size(), 600u);
  // First line of groundtruth.txt: 1.000000 -0.3404563 0.0164698 0.2965692 ...
  EXPECT_NEAR(seq->frame(0).T_world_cam_gt->translation().x(), -0.3404563, 1e-7);
  auto f = seq->LoadFrame(599);
  ASSERT_TRUE(f.ok()) << f.status().ToString();  // colour is JPEG
  EXPECT_EQ(f->bgr.cols, 640);
  EXPECT_EQ(f->depth_mm.rows, 480);
}

}  // namespace
}  // namespace ccmd
