#include "libccmd/io/tum_recorder.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <opencv2/core.hpp>

#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

PinholeCamera SmallCamera(double depth_map_factor) {
  PinholeCamera camera;
  camera.width = 64;
  camera.height = 48;
  camera.fx = camera.fy = 60;
  camera.cx = 31.5;
  camera.cy = 23.5;
  camera.depth_map_factor = depth_map_factor;
  return camera;
}

// Random colour and depth (with holes), from a fixed seed.
RgbdFrame RandomFrame(cv::RNG* rng, double timestamp, int max_depth_mm,
                      cv::Size colour_size = {64, 48}) {
  RgbdFrame frame;
  frame.timestamp = timestamp;
  frame.bgr.create(colour_size, CV_8UC3);
  rng->fill(frame.bgr, cv::RNG::UNIFORM, 0, 256);
  frame.depth_mm.create(48, 64, CV_16UC1);
  rng->fill(frame.depth_mm, cv::RNG::UNIFORM, 0, max_depth_mm + 1);
  for (int i = 0; i < 100; ++i)
    frame.depth_mm.at<std::uint16_t>(rng->uniform(0, 48), rng->uniform(0, 64)) = 0;
  return frame;
}

bool Identical(const cv::Mat& a, const cv::Mat& b) {
  return a.size() == b.size() && a.type() == b.type() && cv::norm(a, b, cv::NORM_INF) == 0;
}

void ExpectReadsBack(const std::string& folder, const std::vector<RgbdFrame>& frames) {
  auto sequence = TumSequence::Open(folder, std::nullopt);  // camera from camera.yaml
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_EQ(sequence->size(), frames.size());
  for (std::size_t i = 0; i < frames.size(); ++i) {
    // Names keep six decimals, as TUM's do.
    EXPECT_NEAR(sequence->frame(i).timestamp, frames[i].timestamp, 0.5e-6) << i;
    auto loaded = sequence->LoadFrame(i);
    ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
    EXPECT_TRUE(Identical(loaded->bgr, frames[i].bgr)) << "colour of frame " << i;
    EXPECT_TRUE(Identical(loaded->depth_mm, frames[i].depth_mm)) << "depth of frame " << i;
  }
}

TEST(TumRecorderTest, TumReaderReadsBackEveryFrameExactlyAt5000PerMetre) {
  testing::TempDir dir;
  const std::string folder = dir.File("run");
  auto recorder = TumRecorder::Create(folder, SmallCamera(5000));
  ASSERT_TRUE(recorder.ok()) << recorder.status().ToString();
  cv::RNG rng(7);
  std::vector<RgbdFrame> frames;
  // 5000 units per metre: 13107 mm is the farthest depth 16 bits can hold.
  for (int i = 0; i < 5; ++i)
    frames.push_back(RandomFrame(&rng, 1305031102.175304 + i / 30.0, 13107));
  for (const RgbdFrame& f : frames) ASSERT_TRUE((*recorder)->Write(f).ok());
  ASSERT_TRUE((*recorder)->Close().ok());
  EXPECT_EQ((*recorder)->frames_written(), 5);
  EXPECT_EQ((*recorder)->clipped_depth_pixels(), 0);
  ExpectReadsBack(folder, frames);
  auto camera = LoadCameraConfig(JoinPath(folder, "camera.yaml"));
  ASSERT_TRUE(camera.ok());
  EXPECT_EQ(camera->depth_map_factor, 5000);
  EXPECT_EQ(camera->width, 64);
}

// A camera whose depth comes apart from its colour (RgbdFrame::depth_time_offset) is recorded as
// TUM RGB-D lists one: each image under its own time, so that playback has the same offset.
TEST(TumRecorderTest, DepthTakenApartFromColourKeepsItsOwnTime) {
  testing::TempDir dir;
  const std::string folder = dir.File("run");
  auto recorder = TumRecorder::Create(folder, SmallCamera(5000));
  ASSERT_TRUE(recorder.ok()) << recorder.status().ToString();
  cv::RNG rng(3);
  std::vector<RgbdFrame> frames;
  for (int i = 0; i < 4; ++i) {
    frames.push_back(RandomFrame(&rng, 20.0 + i / 30.0, 9000));
    frames.back().depth_time_offset = i == 2 ? -0.004 : 0.0125;
  }
  for (const RgbdFrame& f : frames) ASSERT_TRUE((*recorder)->Write(f).ok());
  RgbdFrame bad = RandomFrame(&rng, 30.0, 9000);
  bad.depth_time_offset = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE((*recorder)->Write(bad).ok());
  ASSERT_TRUE((*recorder)->Close().ok());
  ExpectReadsBack(folder, frames);
  auto sequence = TumSequence::Open(folder, std::nullopt);
  ASSERT_TRUE(sequence.ok());
  for (std::size_t i = 0; i < frames.size(); ++i) {
    auto loaded = sequence->LoadFrame(i);
    ASSERT_TRUE(loaded.ok());
    EXPECT_NEAR(loaded->depth_time_offset, frames[i].depth_time_offset, 1.5e-6) << i;
  }
}

TEST(TumRecorderTest, MillimetreFilesHoldTheWholeSixteenBitRange) {
  testing::TempDir dir;
  auto recorder = TumRecorder::Create(dir.path(), SmallCamera(1000));  // a D435 config
  ASSERT_TRUE(recorder.ok());
  cv::RNG rng(8);
  std::vector<RgbdFrame> frames = {RandomFrame(&rng, 3.0, 65535), RandomFrame(&rng, 3.5, 65535)};
  // Colour larger than depth is recorded as delivered; the reader accepts it.
  frames.push_back(RandomFrame(&rng, 4.0, 65535, cv::Size(128, 96)));
  for (const RgbdFrame& f : frames) ASSERT_TRUE((*recorder)->Write(f).ok());
  ASSERT_TRUE((*recorder)->Close().ok());
  ExpectReadsBack(dir.path(), frames);
}

TEST(TumRecorderTest, DepthBeyondTheFileRangeBecomesNoDepth) {
  testing::TempDir dir;
  auto recorder = TumRecorder::Create(dir.path(), SmallCamera(5000));
  ASSERT_TRUE(recorder.ok());
  RgbdFrame frame;
  frame.timestamp = 1;
  frame.bgr = cv::Mat(48, 64, CV_8UC3, cv::Scalar::all(9));
  frame.depth_mm = cv::Mat(48, 64, CV_16UC1, cv::Scalar(1000));
  frame.depth_mm.at<std::uint16_t>(10, 10) = 20000;  // 100000 units: does not fit
  frame.depth_mm.at<std::uint16_t>(10, 11) = 13107;  // 65535 units: fits exactly
  ASSERT_TRUE((*recorder)->Write(frame).ok());
  ASSERT_TRUE((*recorder)->Close().ok());
  EXPECT_EQ((*recorder)->clipped_depth_pixels(), 1);
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok());
  auto loaded = sequence->LoadFrame(0);
  ASSERT_TRUE(loaded.ok());
  EXPECT_EQ(loaded->depth_mm.at<std::uint16_t>(10, 10), 0);
  EXPECT_EQ(loaded->depth_mm.at<std::uint16_t>(10, 11), 13107);
  EXPECT_EQ(loaded->depth_mm.at<std::uint16_t>(0, 0), 1000);
}

TEST(TumRecorderTest, AnInterruptedRecordingIsReadableUpToTheLastFrame) {
  testing::TempDir dir;
  auto recorder = TumRecorder::Create(dir.path(), SmallCamera(5000));
  ASSERT_TRUE(recorder.ok());
  cv::RNG rng(9);
  std::vector<RgbdFrame> frames = {RandomFrame(&rng, 10, 5000), RandomFrame(&rng, 11, 5000)};
  for (const RgbdFrame& f : frames) ASSERT_TRUE((*recorder)->Write(f).ok());
  // Not closed (as after a crash): what was written is already listed and complete.
  ExpectReadsBack(dir.path(), frames);
}

TEST(TumRecorderTest, WriterThreadsRecordCopiesOfTheFrames) {
  testing::TempDir dir;
  TumRecorderOptions options;
  options.queue_frames = 2;
  options.writer_threads = 3;
  auto recorder = TumRecorder::Create(dir.path(), SmallCamera(5000), options);
  ASSERT_TRUE(recorder.ok());
  cv::RNG rng(10);
  std::vector<RgbdFrame> frames;
  for (int i = 0; i < 8; ++i) {
    frames.push_back(RandomFrame(&rng, 20 + i * 0.1, 9000));
    RgbdFrame reused;  // a source reusing its buffers: overwritten right after Write
    reused.timestamp = frames.back().timestamp;
    reused.bgr = frames.back().bgr.clone();
    reused.depth_mm = frames.back().depth_mm.clone();
    ASSERT_TRUE((*recorder)->Write(reused).ok());
    reused.bgr.setTo(cv::Scalar::all(0));
    reused.depth_mm.setTo(cv::Scalar(0));
  }
  ASSERT_TRUE((*recorder)->Close().ok());
  EXPECT_EQ((*recorder)->frames_written(), 8);
  EXPECT_EQ((*recorder)->frames_dropped(), 0);
  ExpectReadsBack(dir.path(), frames);
}

TEST(TumRecorderTest, GroundTruthIsWrittenForTheReader) {
  testing::TempDir dir;
  auto recorder = TumRecorder::Create(dir.path(), SmallCamera(5000));
  ASSERT_TRUE(recorder.ok());
  cv::RNG rng(11);
  ASSERT_TRUE((*recorder)->Write(RandomFrame(&rng, 1.0, 3000)).ok());
  ASSERT_TRUE((*recorder)->Write(RandomFrame(&rng, 2.0, 3000)).ok());
  Trajectory gt;
  for (int i = 0; i <= 2; ++i) {
    Pose pose = Pose::Identity();
    pose.translation() = Eigen::Vector3d(0.5 * i, 0, 0);
    gt.push_back({1.0 + i * 0.5, pose});
  }
  ASSERT_TRUE((*recorder)->WriteGroundTruth(gt).ok());
  ASSERT_TRUE((*recorder)->Close().ok());
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok());
  const Trajectory at_frames = sequence->GroundTruthAtFrames();
  ASSERT_EQ(at_frames.size(), 2u);
  EXPECT_NEAR(at_frames[1].T_world_cam.translation().x(), 1.0, 1e-9);
}

TEST(TumRecorderTest, RefusesBadFramesAndAnExistingRecording) {
  testing::TempDir dir;
  {
    auto recorder = TumRecorder::Create(dir.path(), SmallCamera(5000));
    ASSERT_TRUE(recorder.ok());
    cv::RNG rng(12);
    ASSERT_TRUE((*recorder)->Write(RandomFrame(&rng, 5.0, 3000)).ok());
    EXPECT_EQ((*recorder)->Write(RandomFrame(&rng, 5.0, 3000)).code(),
              StatusCode::kInvalidArgument);  // same timestamp: same file names
    EXPECT_EQ((*recorder)->Write(RandomFrame(&rng, 4.0, 3000)).code(),
              StatusCode::kInvalidArgument);
    RgbdFrame wrong = RandomFrame(&rng, 6.0, 3000);
    wrong.depth_mm = wrong.depth_mm(cv::Rect(0, 0, 32, 24)).clone();
    EXPECT_EQ((*recorder)->Write(wrong).code(), StatusCode::kInvalidArgument);
    RgbdFrame empty;
    empty.timestamp = 7;
    EXPECT_EQ((*recorder)->Write(empty).code(), StatusCode::kInvalidArgument);
  }
  EXPECT_EQ(TumRecorder::Create(dir.path(), SmallCamera(5000)).status().code(),
            StatusCode::kInvalidArgument);
  TumRecorderOptions overwrite;
  overwrite.overwrite = true;
  EXPECT_TRUE(TumRecorder::Create(dir.path(), SmallCamera(5000), overwrite).ok());
}

}  // namespace
}  // namespace ccmd
