// Checks the readers on the real recordings in ../shared/datasets (skipped when absent).

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <vector>

#include <opencv2/imgcodecs.hpp>

#include "libccmd/eval/depth_agreement.h"
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

// The same frames in the layout 7-Scenes' archives unpack to (written here from the converted
// copy: colour files as they are, depth back in millimetres with 65535 for none, each pose a
// 4x4 matrix to 7 decimals) read as the converted copy: the same images, depth and poses.
TEST(RealDatasetsTest, SevenScenesAsUnpackedReadsAsTheConvertedCopy) {
  CCMD_REQUIRE_DATASET(dir, "7scenes_redkitchen_0000_0599");
  auto converted = TumSequence::Open(dir, Config("7scenes.yaml"));
  ASSERT_TRUE(converted.ok()) << converted.status().ToString();
  testing::TempDir unpacked;
  constexpr int kFrames = 12;
  for (int i = 0; i < kFrames; ++i) {
    char stem[32];
    std::snprintf(stem, sizeof(stem), "/frame-%06d.", i);
    const TumFrameInfo& info = converted->frame(i);
    auto colour = ReadFileToString(info.rgb_path);
    ASSERT_TRUE(colour.ok());
    ASSERT_TRUE(WriteFileAtomic(unpacked.path() + stem + "color.jpg", *colour).ok());
    const cv::Mat raw = cv::imread(info.depth_path, cv::IMREAD_UNCHANGED);  // 5000 per metre
    cv::Mat mm(raw.size(), CV_16UC1);
    for (int v = 0; v < raw.rows; ++v)
      for (int u = 0; u < raw.cols; ++u) {
        const int value = raw.at<std::uint16_t>(v, u);
        mm.at<std::uint16_t>(v, u) = value == 0 ? 65535 : static_cast<std::uint16_t>(value / 5);
      }
    ASSERT_TRUE(cv::imwrite(unpacked.path() + stem + "depth.png", mm));
    const Eigen::Matrix4d m = info.T_world_cam_gt->matrix();
    std::string pose;
    for (int r = 0; r < 4; ++r) {
      char row[128];
      std::snprintf(row, sizeof(row), "%.7f %.7f %.7f %.7f\n", m(r, 0), m(r, 1), m(r, 2), m(r, 3));
      pose += row;
    }
    ASSERT_TRUE(WriteFileAtomic(unpacked.path() + stem + "pose.txt", pose).ok());
  }
  auto native = TumSequence::Open(unpacked.path(), Config("7scenes.yaml"));
  ASSERT_TRUE(native.ok()) << native.status().ToString();
  ASSERT_EQ(native->size(), static_cast<std::size_t>(kFrames));
  for (int i = 0; i < kFrames; i += 5) {
    EXPECT_NEAR(native->frame(i).timestamp, converted->frame(i).timestamp, 1e-6);
    auto a = native->LoadFrame(i), b = converted->LoadFrame(i);
    ASSERT_TRUE(a.ok() && b.ok());
    EXPECT_EQ(cv::norm(a->bgr, b->bgr, cv::NORM_INF), 0) << i;
    EXPECT_EQ(cv::norm(a->depth_mm, b->depth_mm, cv::NORM_INF), 0) << i;
    const Pose& Ta = *native->frame(i).T_world_cam_gt;
    const Pose& Tb = *converted->frame(i).T_world_cam_gt;
    EXPECT_LT((Ta.translation() - Tb.translation()).norm(), 1e-6) << i;
    EXPECT_LT((Ta.linear() - Tb.linear()).cwiseAbs().maxCoeff(), 1e-6) << i;
  }
}

// Median distance between frame `a`'s depth, moved by the ground truth into frame `b`, and
// frame b's own depth where it lands (pixels on a 16-pixel grid; within 5 cm: agreeing).
double MedianReprojectedDepthError(const TumSequence& seq, const PinholeCamera& camera, int a,
                                   int b, int* agreeing) {
  auto fa = seq.LoadFrame(a), fb = seq.LoadFrame(b);
  EXPECT_TRUE(fa.ok() && fb.ok());
  DepthAgreementOptions options;
  options.step = 16;
  const DepthAgreement agreement =
      CompareDepthByGroundTruth(fa->depth_mm, fb->depth_mm, camera, *seq.frame(a).T_world_cam_gt,
                                *seq.frame(b).T_world_cam_gt, Pose::Identity(), options);
  *agreeing = agreement.agreeing;
  return agreement.compared > 0 ? agreement.median_error : 1e9;
}

// ICL-NUIM's TUM release: fy < 0 is its convention. With it, depth moved by the ground truth
// from one frame into another lands on the same surfaces (rendered images: within
// millimetres, 3.5 here); with fy > 0 the geometry is mirrored against the ground truth and is
// off by decimetres.
TEST(RealDatasetsTest, IclNuimGroundTruthNeedsTheNegativeFocalLength) {
  CCMD_REQUIRE_DATASET(dir, "iclnuim_office_traj0_0000_0449");
  const PinholeCamera camera = Config("icl_nuim.yaml");
  ASSERT_LT(camera.fy, 0);
  auto seq = TumSequence::Open(dir, camera);
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 450u);
  EXPECT_EQ(seq->GroundTruthAtFrames().size(), 450u);
  auto f = seq->LoadFrame(449);
  ASSERT_TRUE(f.ok()) << f.status().ToString();  // colour is JPEG here
  EXPECT_EQ(f->bgr.cols, 640);
  EXPECT_EQ(f->depth_mm.rows, 480);
  int agreeing = 0, mirrored_agreeing = 0;
  EXPECT_LT(MedianReprojectedDepthError(*seq, camera, 100, 160, &agreeing), 0.01);
  PinholeCamera mirrored = camera;
  mirrored.fy = -camera.fy;
  EXPECT_GT(MedianReprojectedDepthError(*seq, mirrored, 100, 160, &mirrored_agreeing), 0.02);
  EXPECT_GT(agreeing, 2 * mirrored_agreeing);
}

}  // namespace
}  // namespace ccmd
