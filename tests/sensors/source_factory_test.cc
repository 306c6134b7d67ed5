#include "libccmd/sensors/source_factory.h"

#include <gtest/gtest.h>

#include <cstdio>

#include <opencv2/core.hpp>

#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/synth/renderer.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

// A 64x48 synthetic recording in the TUM layout, quick to write.
Status WriteSmallSequence(const std::string& folder, int frames) {
  SyntheticSequenceOptions o;
  o.frames = frames;
  o.width = 64;
  o.height = 48;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  return WriteSyntheticSequence(folder, o).status();
}

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
  ASSERT_TRUE(WriteSmallSequence(dir.path(), 10).ok());
  SourceOptions options;
  options.segment = std::make_pair(1, 2);
  auto source = OpenSource("tum:" + dir.path(), options);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_EQ((*source)->FrameCount(), 6);  // L = ceil(10 / 1.9) = 6, overlap 1: 0..5, 5..9
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.index, 0);
}

// A recording whose camera config has a Depth block gets its depth registered to colour, the
// same way as a live camera's; a Depth block of another size is an error on the first frame.
TEST(SourceFactoryTest, DatasetDepthIsRegisteredWhenTheConfigSaysHow) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteSmallSequence(dir.path(), 2).ok());
  auto camera_yaml = ReadFileToString(dir.File("camera.yaml"));
  ASSERT_TRUE(camera_yaml.ok());
  const PinholeCamera camera = SyntheticCamera(64, 48);
  auto write_config = [&](const std::string& name, int depth_width) {
    const std::string depth_block = "Depth.fx: " + std::to_string(camera.fx * 1.1) +
                                    "\nDepth.fy: " + std::to_string(camera.fy * 1.1) +
                                    "\nDepth.cx: " + std::to_string(camera.cx) +
                                    "\nDepth.cy: " + std::to_string(camera.cy) +
                                    "\nDepth.width: " + std::to_string(depth_width) +
                                    "\nDepth.height: 48\nDepth.t_color_depth: [0.03, 0.0, 0.0]\n";
    EXPECT_TRUE(WriteFileAtomic(dir.File(name), *camera_yaml + "\n" + depth_block).ok());
    return dir.File(name);
  };

  auto raw_source = OpenSource("tum:" + dir.path(), SourceOptions());
  ASSERT_TRUE(raw_source.ok()) << raw_source.status().ToString();
  RgbdFrame raw;
  ASSERT_TRUE((*raw_source)->Read(&raw).ok());

  SourceOptions options;
  options.camera_config = write_config("registered.yaml", 64);
  auto source = OpenSource("tum:" + dir.path(), options);
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_NE((*source)->Describe().find("registered"), std::string::npos);
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  auto calibration = LoadDepthToColorCalibration(options.camera_config);
  ASSERT_TRUE(calibration.ok() && calibration->has_value());
  const cv::Mat expected = RegisterDepthToColor(raw.depth_mm, (*calibration)->depth,
                                                (*source)->camera(), (*calibration)->T_color_depth);
  ASSERT_EQ(frame.depth_mm.size(), expected.size());
  EXPECT_EQ(cv::countNonZero(frame.depth_mm != expected), 0);
  EXPECT_GT(cv::countNonZero(frame.depth_mm != raw.depth_mm), 100);  // registration moved the depth
  // register_depth = false: the same config gives the frames as recorded.
  SourceOptions as_recorded = options;
  as_recorded.register_depth = false;
  auto unregistered = OpenSource("tum:" + dir.path(), as_recorded);
  ASSERT_TRUE(unregistered.ok()) << unregistered.status().ToString();
  EXPECT_EQ((*unregistered)->Describe().find("registered"), std::string::npos);
  RgbdFrame recorded;
  ASSERT_TRUE((*unregistered)->Read(&recorded).ok());
  EXPECT_EQ(cv::countNonZero(recorded.depth_mm != raw.depth_mm), 0);

  options.camera_config = write_config("wrong_size.yaml", 80);
  auto wrong = OpenSource("tum:" + dir.path(), options);
  ASSERT_TRUE(wrong.ok()) << wrong.status().ToString();
  const Status status = (*wrong)->Read(&frame);
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("80x48"), std::string::npos) << status.ToString();
}

// ccmd_synth with a Depth block records depth as the depth imager sees it (its own focal
// length, 15 mm to the side); read back through the sequence's camera.yaml, the depth is
// registered into the colour view and agrees with the colour camera's own exact depth.
TEST(SourceFactoryTest, SyntheticDepthImagerIsRegisteredBackToTheColourView) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 2;
  o.noise = false;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  PinholeCamera colour = SyntheticCamera(320, 240);
  colour.fx = colour.fy = 307.5;  // the D435's colour lens at 320x240
  o.camera = colour;
  DepthToColorCalibration depth;
  depth.depth = SyntheticCamera(320, 240);
  depth.depth.fx = depth.depth.fy = 192.5;  // its wider depth imager
  depth.T_color_depth.translation() = Eigen::Vector3d(0.015, 0, 0);
  o.depth_camera = depth;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  auto registration = LoadDepthToColorCalibration(dir.File("camera.yaml"));
  ASSERT_TRUE(registration.ok() && registration->has_value())
      << "camera.yaml keeps the Depth block";
  EXPECT_NEAR((*registration)->depth.fx, 192.5, 1e-6);

  auto source = OpenSource("tum:" + dir.path(), SourceOptions());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  RoomSceneOptions room = o.room;
  room.seed = o.seed;
  RenderOptions exact;
  exact.noise = false;
  const RenderedFrame truth =
      RenderFrame(SyntheticScene::MakeRoom(room), colour,
                  MakeLoopPath(2, colour.fps, o.path)[0].T_world_cam, exact);
  int both = 0, agree = 0;
  for (int v = 0; v < truth.depth_mm.rows; ++v) {
    for (int u = 0; u < truth.depth_mm.cols; ++u) {
      const int a = frame.depth_mm.at<std::uint16_t>(v, u),
                b = truth.depth_mm.at<std::uint16_t>(v, u);
      if (a == 0 || b == 0) continue;
      ++both;
      // A depth pixel's value fills its whole footprint (1.6 colour pixels here): on slanted
      // surfaces that is a percent or so of depth, beside the millimetre roundings.
      agree += std::abs(a - b) <= 3 + b / 100;
    }
  }
  EXPECT_GT(both, 0.8 * 320 * 240);
  EXPECT_GT(agree, 0.97 * both);
  // As recorded (no registration), the depth image is another view.
  SourceOptions as_recorded;
  as_recorded.register_depth = false;
  auto raw_source = OpenSource("tum:" + dir.path(), as_recorded);
  ASSERT_TRUE(raw_source.ok());
  RgbdFrame raw;
  ASSERT_TRUE((*raw_source)->Read(&raw).ok());
  EXPECT_GT(cv::countNonZero(cv::abs(raw.depth_mm - truth.depth_mm) > 50), 0.3 * 320 * 240);
}

// A recording whose ground truth is the depth camera's (7-Scenes): ccmd_synth writes the depth
// imager's poses and says so in camera.yaml (Trajectory.camera), and the source read through
// it gives trajectories of that camera: the colour camera's poses times T_color_depth.
TEST(SourceFactoryTest, GroundTruthOfTheDepthCameraNamesItsCamera) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 3;
  o.noise = false;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  o.camera = SyntheticCamera(160, 120);
  DepthToColorCalibration depth;
  depth.depth = SyntheticCamera(160, 120);
  depth.T_color_depth.translation() = Eigen::Vector3d(-0.025, 0.004, 0);
  o.depth_camera = depth;
  o.ground_truth_of_depth_camera = true;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  auto source = OpenSource("tum:" + dir.path(), SourceOptions());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  EXPECT_TRUE((*source)->T_color_trajectory().isApprox(depth.T_color_depth));
  const Trajectory colour_path = MakeLoopPath(3, o.camera->fps, o.path);
  const Trajectory gt = (*source)->GroundTruth();
  ASSERT_EQ(gt.size(), 3u);
  for (int i = 0; i < 3; ++i) {
    const Pose expected = colour_path[i].T_world_cam * depth.T_color_depth;
    EXPECT_LT((gt[i].T_world_cam.translation() - expected.translation()).norm(), 1e-5) << i;
    // 25 mm apart from the colour camera's, as the rig puts them.
    EXPECT_NEAR((gt[i].T_world_cam.translation() - colour_path[i].T_world_cam.translation()).norm(),
                depth.T_color_depth.translation().norm(), 1e-5);
  }

  // The same imager without the flag: the colour camera's ground truth and trajectories.
  testing::TempDir plain_dir;
  o.ground_truth_of_depth_camera = false;
  ASSERT_TRUE(WriteSyntheticSequence(plain_dir.path(), o).ok());
  auto plain = OpenSource("tum:" + plain_dir.path(), SourceOptions());
  ASSERT_TRUE(plain.ok());
  EXPECT_TRUE((*plain)->T_color_trajectory().isApprox(Pose::Identity()));
  EXPECT_LT(((*plain)->GroundTruth()[1].T_world_cam.translation() -
             colour_path[1].T_world_cam.translation())
                .norm(),
            1e-5);
}

// The files of frame i: its colour image made unreadable, or its depth image removed.
void DamageColour(const TumSequence& sequence, int i) {
  ASSERT_TRUE(WriteFileAtomic(sequence.frame(i).rgb_path, "not an image").ok());
}
void RemoveDepth(const TumSequence& sequence, int i) {
  ASSERT_EQ(std::remove(sequence.frame(i).depth_path.c_str()), 0);
}

// A recording with a damaged frame is still the recording: the frame is dropped, as a camera
// drops one, and counted; the frames after it come as they would have.
TEST(SourceFactoryTest, ARecordingDropsItsUnreadableFramesAndGoesOn) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteSmallSequence(dir.path(), 8).ok());
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  DamageColour(*sequence, 2);
  RemoveDepth(*sequence, 5);
  RemoveDepth(*sequence, 6);
  auto source = OpenSource("tum:" + dir.path(), SourceOptions());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  std::vector<int> read;
  RgbdFrame frame;
  Status status;
  while ((status = (*source)->Read(&frame)).ok()) {
    EXPECT_FALSE(frame.bgr.empty());
    EXPECT_FALSE(frame.depth_mm.empty());
    read.push_back(frame.index);
  }
  EXPECT_EQ(status.code(), StatusCode::kEndOfStream) << status.ToString();
  EXPECT_EQ(read, (std::vector<int>{0, 1, 3, 4, 7}));
  EXPECT_EQ((*source)->DroppedFrames(), 3);
}

// Unreadable for three seconds of frames in a row, or throughout, a recording is an error
// that names its frames and why, not an empty run.
TEST(SourceFactoryTest, ARecordingThatCannotBeReadIsAnError) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteSmallSequence(dir.path(), 100).ok());  // 30 frames/s
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  for (int i = 3; i < 100; ++i) RemoveDepth(*sequence, i);
  auto source = OpenSource("tum:" + dir.path(), SourceOptions());
  ASSERT_TRUE(source.ok()) << source.status().ToString();
  RgbdFrame frame;
  for (int i = 0; i < 3; ++i) ASSERT_TRUE((*source)->Read(&frame).ok());
  const Status gave_up = (*source)->Read(&frame);
  EXPECT_EQ(gave_up.code(), StatusCode::kCorrupt);
  EXPECT_NE(gave_up.message().find("frames 3-92"), std::string::npos) << gave_up.ToString();
  EXPECT_NE(gave_up.message().find(sequence->frame(92).depth_path), std::string::npos)
      << gave_up.ToString();
  EXPECT_EQ((*source)->DroppedFrames(), 90);

  testing::TempDir short_dir;
  ASSERT_TRUE(WriteSmallSequence(short_dir.path(), 6).ok());
  auto short_sequence = TumSequence::Open(short_dir.path(), std::nullopt);
  ASSERT_TRUE(short_sequence.ok());
  for (int i = 0; i < 6; ++i) DamageColour(*short_sequence, i);
  auto unreadable = OpenSource("tum:" + short_dir.path(), SourceOptions());
  ASSERT_TRUE(unreadable.ok()) << unreadable.status().ToString();
  const Status none = (*unreadable)->Read(&frame);
  EXPECT_EQ(none.code(), StatusCode::kCorrupt);
  EXPECT_NE(none.message().find("none of the 6 frames"), std::string::npos) << none.ToString();
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
