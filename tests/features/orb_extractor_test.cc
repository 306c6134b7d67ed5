#include "libccmd/features/orb_extractor.h"

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>

#include "libccmd/features/descriptor.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/random.h"

namespace ccmd {
namespace {

cv::Mat RenderGray() {
  RoomSceneOptions room;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(30, 30.0);
  RenderOptions options;
  options.noise = false;
  const RenderedFrame frame = RenderFrame(scene, SyntheticCamera(), path[10].T_world_cam, options);
  cv::Mat gray;
  cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
  return gray;
}

TEST(DistributeKeypointsTest, SpreadsOverCellsBeforeTakingSecondBest) {
  std::vector<cv::KeyPoint> candidates;
  // 100 strong corners packed in the top-left 20x20 pixels, 16 weak ones one per 4x4 cell.
  for (int i = 0; i < 100; ++i) candidates.emplace_back(cv::Point2f(i % 10 * 2.0f, i / 10 * 2.0f), 7, -1, 100.0f + i);
  for (int cy = 0; cy < 4; ++cy) {
    for (int cx = 0; cx < 4; ++cx) candidates.emplace_back(cv::Point2f(cx * 100 + 50.0f, cy * 100 + 50.0f), 7, -1, 1.0f);
  }
  const auto kept = DistributeKeypoints(candidates, 400, 400, 16);  // 16 cells of 100 px
  ASSERT_EQ(kept.size(), 16u);
  int weak = 0;
  for (const auto& k : kept) weak += k.response == 1.0f;
  EXPECT_EQ(weak, 15);  // every other cell's only corner, plus the best of the crowded cell
  EXPECT_EQ(std::max_element(kept.begin(), kept.end(), [](auto& a, auto& b) { return a.response < b.response; })->response, 199.0f);
}

TEST(OrbExtractorTest, BudgetSpreadAndLevels) {
  const OrbExtractor orb;
  int sum = 0;
  for (int n : orb.level_budget()) sum += n;
  EXPECT_EQ(sum, 1000);
  EXPECT_GT(orb.level_budget()[0], orb.level_budget()[1]);
  const OrbFeatures f = orb.Extract(RenderGray());
  EXPECT_GE(f.keypoints.size(), 950u);
  EXPECT_LE(f.keypoints.size(), 1000u);
  ASSERT_EQ(f.descriptors.rows, static_cast<int>(f.keypoints.size()));
  EXPECT_EQ(f.descriptors.cols, 32);
  std::vector<int> per_level(8, 0);
  std::vector<int> cells(48, 0);
  for (const auto& k : f.keypoints) {
    ASSERT_GE(k.octave, 0);
    ASSERT_LT(k.octave, 8);
    per_level[k.octave]++;
    cells[std::min(5, static_cast<int>(k.pt.y / 80)) * 8 + std::min(7, static_cast<int>(k.pt.x / 80))]++;
  }
  for (int level = 0; level < 8; ++level) EXPECT_GT(per_level[level], 0) << level;
  EXPECT_EQ(std::count(cells.begin(), cells.end(), 0), 0);  // no empty 80x80 cell
}

TEST(OrbExtractorTest, ShiftedImageMatchesAtShiftedPositions) {
  const cv::Mat gray = RenderGray();
  const cv::Mat shift = (cv::Mat_<double>(2, 3) << 1, 0, 7, 0, 1, -5);
  cv::Mat moved;
  cv::warpAffine(gray, moved, shift, gray.size(), cv::INTER_NEAREST, cv::BORDER_REPLICATE);
  const OrbExtractor orb;
  const OrbFeatures a = orb.Extract(gray), b = orb.Extract(moved);
  int matched = 0, consistent = 0;
  for (int i = 0; i < a.descriptors.rows; ++i) {
    int best = 1000, second = 1000, best_j = -1;
    for (int j = 0; j < b.descriptors.rows; ++j) {
      const int d = HammingDistance(a.descriptors.ptr<uint8_t>(i), b.descriptors.ptr<uint8_t>(j));
      if (d < best) {
        second = best;
        best = d;
        best_j = j;
      } else if (d < second) {
        second = d;
      }
    }
    if (best > 50 || best > 0.8 * second) continue;
    ++matched;
    const cv::Point2f expected = a.keypoints[i].pt + cv::Point2f(7, -5);
    if (cv::norm(expected - b.keypoints[best_j].pt) < 1.5 * std::pow(1.2, a.keypoints[i].octave)) ++consistent;
  }
  EXPECT_GT(matched, 500);
  EXPECT_GT(consistent, 0.95 * matched);
}

}  // namespace
}  // namespace ccmd
