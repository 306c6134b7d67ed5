#include "libccmd/io/tum_dataset.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include <opencv2/imgcodecs.hpp>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

PinholeCamera Camera() {
  PinholeCamera c;
  c.width = 8;
  c.height = 6;
  return c;
}

// A 3-frame folder: colour as .jpg and .png (names taken from the list), depth at 5000/m,
// depth 12 ms after colour, ground truth at 100 Hz.
void WriteFolder(const std::string& dir) {
  MakeDirectories(dir + "/rgb").IgnoreError();
  MakeDirectories(dir + "/depth").IgnoreError();
  std::string rgb = "# color\n", depth = "# depth\n", gt = "# gt\n";
  for (int i = 0; i < 3; ++i) {
    const double t = 10.0 + i / 30.0;
    const std::string rgb_name = "rgb/" + std::to_string(i) + (i == 1 ? ".jpg" : ".png");
    const std::string depth_name = "depth/" + std::to_string(i) + ".png";
    cv::imwrite(dir + "/" + rgb_name, cv::Mat(6, 8, CV_8UC3, cv::Scalar(10, 20, 30)));
    cv::Mat d(6, 8, CV_16UC1, cv::Scalar(5000 + 1000 * i));  // 1.0, 1.2, 1.4 m
    d.at<std::uint16_t>(0, 0) = 0;
    cv::imwrite(dir + "/" + depth_name, d);
    rgb += std::to_string(t) + " " + rgb_name + "\n";
    depth += std::to_string(t + 0.012) + " " + depth_name + "\n";
  }
  for (int k = 0; k < 12; ++k) {
    gt += std::to_string(9.99 + k * 0.01) + " " + std::to_string(k * 0.01) + " 0 0 0 0 0 1\n";
  }
  WriteFileAtomic(dir + "/rgb.txt", rgb).IgnoreError();
  WriteFileAtomic(dir + "/depth.txt", depth).IgnoreError();
  WriteFileAtomic(dir + "/groundtruth.txt", gt).IgnoreError();
}

TEST(TumDatasetTest, ReadsAssociatesAndConvertsDepth) {
  testing::TempDir dir;
  WriteFolder(dir.path());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 3u);
  EXPECT_NEAR(seq->frame(1).depth_timestamp - seq->frame(1).timestamp, 0.012, 1e-9);
  auto f = seq->LoadFrame(2);
  ASSERT_TRUE(f.ok()) << f.status().ToString();
  EXPECT_EQ(f->bgr.type(), CV_8UC3);
  EXPECT_EQ(f->depth_mm.type(), CV_16UC1);
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(1, 1), 1400);     // 7000 / 5000 m
  EXPECT_DOUBLE_EQ(f->timestamp, seq->frame(2).timestamp);  // the colour image's time
  EXPECT_NEAR(f->depth_time_offset, 0.012, 1e-9);           // and the depth's after it
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(0, 0), 0);        // invalid stays invalid
  EXPECT_TRUE(seq->LoadFrame(1).ok());                      // the .jpg frame
}

TEST(TumDatasetTest, GroundTruthInterpolatedAtColourTimestamps) {
  testing::TempDir dir;
  WriteFolder(dir.path());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok());
  // gt x = (t - 9.99), linear: at t = 10 + 1/30 it is 0.01 + 1/30.
  ASSERT_TRUE(seq->frame(1).T_world_cam_gt.has_value());
  EXPECT_NEAR(seq->frame(1).T_world_cam_gt->translation().x(), 0.01 + 1.0 / 30, 1e-6);  // us stamps
  EXPECT_EQ(seq->GroundTruthAtFrames().size(), 3u);
}

TEST(TumDatasetTest, MissingPiecesGiveClearErrors) {
  testing::TempDir dir;
  EXPECT_EQ(TumSequence::Open(dir.path() + "/nope", Camera()).status().code(),
            StatusCode::kNotFound);
  EXPECT_EQ(TumSequence::Open(dir.path(), Camera()).status().code(), StatusCode::kNotFound);
  WriteFolder(dir.path());
  EXPECT_FALSE(TumSequence::Open(dir.path(), std::nullopt).ok());  // no camera, no camera.yaml
  std::remove((dir.path() + "/depth/1.png").c_str());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok());
  auto f = seq->LoadFrame(1);
  ASSERT_FALSE(f.ok());
  EXPECT_NE(f.status().message().find("depth/1.png"), std::string::npos);
}

TEST(TumDatasetTest, AssociationsOnlyFolderWithDepthFirst) {
  // ICL-NUIM's TUM-compatible release lists "t depth/i.png t rgb/i.png".
  testing::TempDir dir;
  WriteFolder(dir.path());
  std::remove((dir.path() + "/rgb.txt").c_str());
  std::remove((dir.path() + "/depth.txt").c_str());
  ASSERT_TRUE(WriteFileAtomic(dir.File("associations.txt"),
                              "0 depth/0.png 0 rgb/0.png\n1 depth/2.png 1 rgb/2.png\n")
                  .ok());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 2u);
  EXPECT_NE(seq->frame(1).rgb_path.find("rgb/2.png"), std::string::npos);
  EXPECT_EQ(seq->LoadFrame(1)->depth_mm.at<std::uint16_t>(3, 3), 1400);
}

// ICL-NUIM's release as it unpacks: frames numbered where timestamps go, in associations.txt
// and in its ground truth (traj0.gt.freiburg, no pose for frame 0), no groundtruth.txt. Read
// as frames at the camera's 30 Hz, as fetch_icl_nuim.sh converts them, ground truth included.
TEST(TumDatasetTest, IclNuimReleaseAsItUnpacksIsReadAtTheCamerasRate) {
  testing::TempDir dir;
  WriteFolder(dir.path());
  for (const char* f : {"/rgb.txt", "/depth.txt", "/groundtruth.txt"})
    std::remove((dir.path() + f).c_str());
  ASSERT_TRUE(WriteFileAtomic(dir.File("associations.txt"),
                              "0 depth/0.png 0 rgb/0.png\n1 depth/1.png 1 rgb/1.jpg\n"
                              "2 depth/2.png 2 rgb/2.png\n")
                  .ok());
  ASSERT_TRUE(
      WriteFileAtomic(dir.File("traj0.gt.freiburg"), "1 0.1 0 -2.5 0 0 0 1\n2 0.2 0 -2.5 0 0 0 1\n")
          .ok());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 3u);
  EXPECT_NEAR(seq->frame(1).timestamp, 1.0 / 30, 1e-12);
  EXPECT_NEAR(seq->frame(2).depth_timestamp, 2.0 / 30, 1e-12);
  ASSERT_EQ(seq->groundtruth().size(), 2u);
  EXPECT_NEAR(seq->groundtruth().back().timestamp, 2.0 / 30, 1e-12);
  EXPECT_FALSE(seq->frame(0).T_world_cam_gt.has_value());
  ASSERT_TRUE(seq->frame(2).T_world_cam_gt.has_value());
  EXPECT_NEAR(seq->frame(2).T_world_cam_gt->translation().x(), 0.2, 1e-12);

  // Two ground-truth files: which one is meant is not clear, so neither is taken.
  ASSERT_TRUE(WriteFileAtomic(dir.File("traj1.gt.freiburg"), "1 0 0 0 0 0 0 1\n").ok());
  EXPECT_TRUE(TumSequence::Open(dir.path(), Camera())->groundtruth().empty());
  // Times that are not consecutive frame numbers stay times.
  ASSERT_TRUE(WriteFileAtomic(dir.File("associations.txt"),
                              "10 depth/0.png 10 rgb/0.png\n12 depth/1.png 12 rgb/1.jpg\n")
                  .ok());
  EXPECT_EQ(TumSequence::Open(dir.path(), Camera())->frame(1).timestamp, 12.0);
}

// A 7-Scenes sequence folder as its archive unpacks: depth in millimetres with 65535 for no
// depth, a 4x4 camera-to-world matrix per frame written to 6 digits; frames numbered from
// `first`.
void WriteSevenScenesFolder(const std::string& dir, int frames, int first = 0) {
  MakeDirectories(dir).IgnoreError();
  for (int i = first; i < first + frames; ++i) {
    char stem[32];
    std::snprintf(stem, sizeof(stem), "/frame-%06d.", i);
    cv::imwrite(dir + stem + "color.png", cv::Mat(6, 8, CV_8UC3, cv::Scalar(10, 20, 30)));
    cv::Mat d(6, 8, CV_16UC1, cv::Scalar(1500 + 100 * i));
    d.at<std::uint16_t>(0, 0) = 65535;
    d.at<std::uint16_t>(0, 1) = 0;
    cv::imwrite(dir + stem + "depth.png", d);
    // 10 degrees about z, x = 0.1 * i.
    const double c = std::cos(10 * M_PI / 180), sn = std::sin(10 * M_PI / 180);
    char pose[256];
    std::snprintf(pose, sizeof(pose), "%.6e %.6e 0 %.6e\n%.6e %.6e 0 0\n0 0 1 0\n0 0 0 1\n", c, -sn,
                  0.1 * i, sn, c);
    WriteFileAtomic(dir + stem + "pose.txt", pose).IgnoreError();
  }
}

TEST(TumDatasetTest, SevenScenesFolderIsReadAsItUnpacks) {
  testing::TempDir dir;
  WriteSevenScenesFolder(dir.path(), 3);
  EXPECT_TRUE(TumSequence::IsSevenScenesFolder(dir.path()));
  PinholeCamera camera = Camera();
  camera.depth_map_factor = 5000;  // the converted copies' units: not these files'
  auto seq = TumSequence::Open(dir.path(), camera);
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 3u);
  EXPECT_DOUBLE_EQ(seq->frame(0).timestamp, 1.0);
  EXPECT_NEAR(seq->frame(2).timestamp, 1.0 + 2.0 / 30, 1e-12);
  auto f = seq->LoadFrame(1);
  ASSERT_TRUE(f.ok()) << f.status().ToString();
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(3, 3), 1600);  // millimetres as written
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(0, 0), 0);     // 65535: no depth
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(0, 1), 0);
  ASSERT_EQ(seq->GroundTruthAtFrames().size(), 3u);
  const Pose& T = *seq->frame(2).T_world_cam_gt;
  EXPECT_NEAR(T.translation().x(), 0.2, 1e-9);
  EXPECT_NEAR((T.linear().transpose() * T.linear() - Eigen::Matrix3d::Identity()).norm(), 0, 1e-12);
  EXPECT_NEAR(Eigen::AngleAxisd(T.linear()).angle(), 10 * M_PI / 180, 1e-6);
  EXPECT_NEAR(T.linear()(1, 0), std::sin(10 * M_PI / 180), 1e-6);  // camera-to-world, as written
}

// Part of a sequence copied out of its archive keeps the archive's numbers, here 600 on with
// one frame left out: each frame keeps its time in the whole sequence and its own pose.
TEST(TumDatasetTest, SevenScenesFramesNeedNotStartAtZero) {
  testing::TempDir dir;
  WriteSevenScenesFolder(dir.path(), 4, 600);
  for (const char* suffix : {"color.png", "depth.png", "pose.txt"})
    std::remove(dir.File(std::string("frame-000601.") + suffix).c_str());
  // Names the reader would not open do not count as frames.
  ASSERT_TRUE(WriteFileAtomic(dir.File("frame-604.color.png"), "x").ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("frame-000605.color.bmp"), "x").ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("frame-000606.color.png.bak"), "x").ok());
  EXPECT_TRUE(TumSequence::IsSevenScenesFolder(dir.path()));
  EXPECT_EQ(GuessCameraConfigName(dir.path()), "7scenes.yaml");
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 3u);
  const int numbers[] = {600, 602, 603};
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(seq->frame(k).timestamp, 1.0 + numbers[k] / 30.0, 1e-12) << k;
    ASSERT_TRUE(seq->frame(k).T_world_cam_gt.has_value()) << k;
    EXPECT_NEAR(seq->frame(k).T_world_cam_gt->translation().x(), 0.1 * numbers[k], 1e-6) << k;
  }
  auto f = seq->LoadFrame(1);
  ASSERT_TRUE(f.ok()) << f.status().ToString();
  EXPECT_EQ(f->depth_mm.at<std::uint16_t>(3, 3), 1500 + 100 * 602);
  EXPECT_EQ(seq->GroundTruthAtFrames().size(), 3u);
  // A folder with colour but no depth at all is not a sequence.
  testing::TempDir colour_only;
  ASSERT_TRUE(WriteFileAtomic(colour_only.File("frame-000600.color.png"), "x").ok());
  EXPECT_FALSE(TumSequence::IsSevenScenesFolder(colour_only.path()));
}

TEST(TumDatasetTest, SevenScenesFolderErrorsNameTheFile) {
  testing::TempDir dir;
  WriteSevenScenesFolder(dir.path(), 2);
  // The layout chooses the 7-Scenes config, and without a camera the error points at it.
  EXPECT_EQ(GuessCameraConfigName(dir.path()), "7scenes.yaml");
  const Status no_camera = TumSequence::Open(dir.path(), std::nullopt).status();
  EXPECT_NE(no_camera.message().find("7scenes.yaml"), std::string::npos) << no_camera.ToString();
  ASSERT_TRUE(WriteFileAtomic(dir.File("frame-000001.pose.txt"), "1 0 0 0\n0 1 0 0\n0 0 1\n").ok());
  Status bad = TumSequence::Open(dir.path(), Camera()).status();
  EXPECT_EQ(bad.code(), StatusCode::kCorrupt);
  EXPECT_NE(bad.message().find("frame-000001.pose.txt"), std::string::npos) << bad.ToString();
  ASSERT_TRUE(WriteFileAtomic(dir.File("frame-000001.pose.txt"),
                              "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
                  .ok());  // a scale, not a rotation
  EXPECT_EQ(TumSequence::Open(dir.path(), Camera()).status().code(), StatusCode::kCorrupt);
  std::remove(dir.File("frame-000001.pose.txt").c_str());  // a frame without a pose
  std::remove(dir.File("frame-000001.depth.png").c_str());
  auto seq = TumSequence::Open(dir.path(), Camera());
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  EXPECT_EQ(seq->GroundTruthAtFrames().size(), 1u);
  auto f = seq->LoadFrame(1);
  ASSERT_FALSE(f.ok());
  EXPECT_NE(f.status().message().find("frame-000001.depth.png"), std::string::npos);
}

TEST(TumDatasetTest, GuessesConfigFromFolderName) {
  EXPECT_EQ(GuessCameraConfigName("/d/rgbd_dataset_freiburg1_desk/"), "tum_fr1.yaml");
  EXPECT_EQ(GuessCameraConfigName("rgbd_dataset_freiburg3_long_office_household"), "tum_fr3.yaml");
  EXPECT_EQ(GuessCameraConfigName("/x/living_room_traj2_frei_png"), "icl_nuim.yaml");
  // The office room's archives unpack as traj<N>_frei_png.
  EXPECT_EQ(GuessCameraConfigName("/x/traj0_frei_png"), "icl_nuim.yaml");
  EXPECT_EQ(GuessCameraConfigName("/x/office_room_traj0_frei_png"), "icl_nuim.yaml");
  EXPECT_EQ(GuessCameraConfigName("/x/7scenes_redkitchen_0000_0599"), "7scenes.yaml");
  EXPECT_EQ(GuessCameraConfigName("/x/my_recording"), "");
}

}  // namespace
}  // namespace ccmd
