#include "libccmd/features/orb_extractor.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <thread>

#include <opencv2/features2d.hpp>
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
  for (int i = 0; i < 100; ++i)
    candidates.emplace_back(cv::Point2f(i % 10 * 2.0f, i / 10 * 2.0f), 7, -1, 100.0f + i);
  for (int cy = 0; cy < 4; ++cy) {
    for (int cx = 0; cx < 4; ++cx)
      candidates.emplace_back(cv::Point2f(cx * 100 + 50.0f, cy * 100 + 50.0f), 7, -1, 1.0f);
  }
  const auto kept = DistributeKeypoints(candidates, 400, 400, 16);  // 16 cells of 100 px
  ASSERT_EQ(kept.size(), 16u);
  int weak = 0;
  for (const auto& k : kept) weak += k.response == 1.0f;
  EXPECT_EQ(weak, 15);  // every other cell's only corner, plus the best of the crowded cell
  EXPECT_EQ(std::max_element(kept.begin(), kept.end(),
                             [](auto& a, auto& b) { return a.response < b.response; })
                ->response,
            199.0f);
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
    cells[std::min(5, static_cast<int>(k.pt.y / 80)) * 8 +
          std::min(7, static_cast<int>(k.pt.x / 80))]++;
  }
  for (int level = 0; level < 8; ++level) EXPECT_GT(per_level[level], 0) << level;
  EXPECT_EQ(std::count(cells.begin(), cells.end(), 0), 0);  // no empty 80x80 cell
}

// The selection written the simple way: one FAST pass at the low threshold over each level,
// cv::cornerHarris over the whole level, the same distribution.
std::vector<cv::KeyPoint> ReferenceSelection(const cv::Mat& gray, const OrbExtractor& orb) {
  const OrbOptions& o = orb.options();
  std::vector<cv::KeyPoint> all;
  cv::Mat image = gray;
  for (int level = 0; level < o.levels; ++level) {
    if (level > 0) {
      cv::Mat smaller;
      cv::resize(image, smaller,
                 cv::Size(cvRound(gray.cols / orb.scale()[level]),
                          cvRound(gray.rows / orb.scale()[level])),
                 0, 0, cv::INTER_LINEAR);
      image = smaller;
    }
    const int e = o.edge;
    std::vector<cv::KeyPoint> corners, inside;
    cv::FAST(image(cv::Rect(e - 3, e - 3, image.cols - 2 * e + 6, image.rows - 2 * e + 6)), corners,
             o.min_fast_threshold, true);
    cv::Mat harris;
    cv::cornerHarris(image, harris, 7, 3, 0.04);
    for (cv::KeyPoint k : corners) {
      k.pt += cv::Point2f(e - 3, e - 3);
      if (k.pt.x < e || k.pt.y < e || k.pt.x >= image.cols - e || k.pt.y >= image.rows - e)
        continue;
      const bool strong = k.response >= o.fast_threshold;
      k.response = harris.at<float>(cvRound(k.pt.y), cvRound(k.pt.x)) - (strong ? 0.0f : 1e9f);
      inside.push_back(k);
    }
    for (cv::KeyPoint k :
         DistributeKeypoints(inside, image.cols, image.rows, orb.level_budget()[level])) {
      k.octave = level;
      k.pt.x = (k.pt.x + 0.5f) * gray.cols / image.cols - 0.5f;
      k.pt.y = (k.pt.y + 0.5f) * gray.rows / image.rows - 0.5f;
      all.push_back(k);
    }
  }
  return all;
}

// A textured rendered room, and an image whose left third is flat and whose right part is
// noise of growing contrast, so that cells range from no corner at all and weak corners only
// to many strong ones, and the distribution has to go past the first corner of each cell.
TEST(OrbExtractorTest, ChoosesTheKeypointsOfASinglePassWithHarrisOverTheWholeImage) {
  cv::Mat noise(480, 640, CV_32F);
  cv::RNG rng(7);
  rng.fill(noise, cv::RNG::NORMAL, 0, 1);
  cv::GaussianBlur(noise, noise, cv::Size(5, 5), 1.2);
  cv::Mat ramp(480, 640, CV_8U);
  for (int y = 0; y < ramp.rows; ++y) {
    for (int x = 0; x < ramp.cols; ++x) {
      const double contrast = x < ramp.cols / 3 ? 0.0 : 120.0 * (x - ramp.cols / 3) / ramp.cols;
      ramp.at<uchar>(y, x) = cv::saturate_cast<uchar>(128 + contrast * noise.at<float>(y, x));
    }
  }
  for (const cv::Mat& gray : {RenderGray(), ramp}) {
    const OrbExtractor orb;
    const OrbFeatures f = orb.Extract(gray);
    const std::vector<cv::KeyPoint> expected = ReferenceSelection(gray, orb);
    ASSERT_EQ(f.keypoints.size(), expected.size());
    int same = 0;
    for (std::size_t i = 0; i < expected.size(); ++i) {
      same += f.keypoints[i].octave == expected[i].octave &&
              cv::norm(f.keypoints[i].pt - expected[i].pt) < 1e-4;
    }
    // Harris values computed in another order may swap two corners of equal rank.
    EXPECT_GE(same, static_cast<int>(0.995 * expected.size()));
  }
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
    if (cv::norm(expected - b.keypoints[best_j].pt) < 1.5 * std::pow(1.2, a.keypoints[i].octave))
      ++consistent;
  }
  EXPECT_GT(matched, 500);
  EXPECT_GT(consistent, 0.95 * matched);
}

// A level's image size is rounded to whole pixels (640 / 1.2^7 = 178.6 -> 179), so its true
// ratio to the full image differs from the nominal 1.2^level by up to 0.2 %: mapped with the
// nominal one, keypoints of coarse octaves sit up to 1.4 pixels off at the far side of the
// image. Flipping the image flips every level (the resize maps pixel centres symmetrically), so
// each keypoint of the flipped image must come back at the mirror image of one of the
// original's, on every octave.
TEST(OrbExtractorTest, EveryOctaveMirrorsItsKeypointsWhenTheImageIsFlipped) {
  const cv::Mat gray = RenderGray();
  const OrbExtractor orb;
  const OrbFeatures a = orb.Extract(gray);
  for (const int flip : {0, 1}) {  // about the horizontal axis, the vertical one
    cv::Mat flipped;
    cv::flip(gray, flipped, flip);
    const OrbFeatures b = orb.Extract(flipped);
    std::vector<std::vector<float>> offsets(8);  // per octave, along the flipped axis
    for (const cv::KeyPoint& p : a.keypoints) {
      const cv::Point2f mirror = flip == 1 ? cv::Point2f(gray.cols - 1 - p.pt.x, p.pt.y)
                                           : cv::Point2f(p.pt.x, gray.rows - 1 - p.pt.y);
      const cv::KeyPoint* nearest = nullptr;
      for (const cv::KeyPoint& q : b.keypoints) {
        if (q.octave == p.octave && cv::norm(q.pt - mirror) < 3 &&
            (!nearest || cv::norm(q.pt - mirror) < cv::norm(nearest->pt - mirror))) {
          nearest = &q;
        }
      }
      if (nearest) {
        offsets[p.octave].push_back(flip == 1 ? nearest->pt.x - mirror.x
                                              : nearest->pt.y - mirror.y);
      }
    }
    for (int octave = 0; octave < 8; ++octave) {
      std::vector<float>& o = offsets[octave];
      ASSERT_GE(o.size(), 10u) << "octave " << octave << ", flip " << flip;
      std::nth_element(o.begin(), o.begin() + o.size() / 2, o.end());
      EXPECT_LT(std::abs(o[o.size() / 2]), 0.05f) << "octave " << octave << ", flip " << flip;
    }
  }
}

bool SameFeatures(const OrbFeatures& a, const OrbFeatures& b) {
  if (a.keypoints.size() != b.keypoints.size() || a.descriptors.size() != b.descriptors.size())
    return false;
  for (std::size_t i = 0; i < a.keypoints.size(); ++i) {
    const cv::KeyPoint &p = a.keypoints[i], &q = b.keypoints[i];
    if (p.pt != q.pt || p.octave != q.octave || p.angle != q.angle || p.response != q.response)
      return false;
  }
  return a.descriptors.empty() || cv::norm(a.descriptors, b.descriptors, cv::NORM_L1) == 0;
}

TEST(OrbExtractorTest, ThreadBuffersCarryNothingFromOneImageToTheNext) {
  // Each thread keeps its pyramid and gradient buffers between calls: an image of another size
  // and content in between, or another thread, must not change what an image gives.
  const cv::Mat gray = RenderGray();
  cv::Mat other;
  cv::resize(gray(cv::Rect(100, 50, 400, 300)), other, cv::Size(333, 251));
  cv::flip(other, other, 1);
  const OrbExtractor orb;
  const OrbFeatures first = orb.Extract(gray);
  ASSERT_GT(first.keypoints.size(), 500u);
  const OrbFeatures between = orb.Extract(other);
  EXPECT_FALSE(SameFeatures(first, between));
  EXPECT_TRUE(SameFeatures(first, orb.Extract(gray)));
  OrbFeatures elsewhere;
  std::thread([&] { elsewhere = orb.Extract(gray); }).join();
  EXPECT_TRUE(SameFeatures(first, elsewhere));
  // The smaller image gives the same after the larger one as on a thread that saw only it.
  OrbFeatures alone;
  std::thread([&] { alone = orb.Extract(other); }).join();
  EXPECT_TRUE(SameFeatures(between, alone));
}

}  // namespace
}  // namespace ccmd
