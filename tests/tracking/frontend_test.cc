// The front-end on short synthetic sequences with exact ground truth.

#include "libccmd/tracking/frontend.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <optional>
#include <set>
#include <utility>
#include <vector>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/synth/sequence.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

struct Collector : KeyframeSink {
  std::vector<KeyframeSnapshot> keyframes;
  std::vector<PoseUpdate> updates;
  void OnKeyframe(KeyframeSnapshot k) override { keyframes.push_back(std::move(k)); }
  void OnPoseUpdates(std::vector<PoseUpdate> u) override {
    updates.insert(updates.end(), u.begin(), u.end());
  }
};

struct RunResult {
  Trajectory trajectory, keyframe_trajectory, ground_truth;
  // The largest |R^T R - I| of a tracked frame's pose as tracking gave it (the trajectory is
  // rebuilt from records whose rotations are stored normalised).
  double max_shear = 0;
  FrontendStats stats;
  Collector sink;
};

// `blank`: frames [first, last] with their colour made one flat grey, as a camera facing a
// blank wall or smeared by a fast turn records them: no features, depth intact.
// `inverted_from`: from that frame on, the colour inverted (255 - value): every descriptor
// differs from the map's, so the frames that follow show texture the map does not hold.
// `edit`: any other change to frame i before it is tracked.
void RunSequence(int frames, const TrackingOptions& options, RunResult* out,
                 bool sensor_noise = true, std::optional<std::pair<int, int>> blank = std::nullopt,
                 int inverted_from = -1,
                 const std::function<void(int, RgbdFrame*)>& edit = nullptr) {
  SyntheticSequenceOptions synth;
  synth.frames = frames;
  synth.seed = 1;
  synth.noise = sensor_noise;
  SyntheticSource source(synth);
  auto frontend = Frontend::Create(source.camera(), options, &out->sink);
  ASSERT_TRUE(frontend.ok()) << frontend.status().ToString();
  RgbdFrame frame;
  for (int i = 0; source.Read(&frame).ok(); ++i) {
    if (blank && i >= blank->first && i <= blank->second)
      frame.bgr.setTo(cv::Scalar(128, 128, 128));
    if (inverted_from >= 0 && i >= inverted_from) cv::bitwise_not(frame.bgr, frame.bgr);
    if (edit) edit(i, &frame);
    const TrackResult tracked = (*frontend)->ProcessFrame(frame);
    if (tracked.T_world_cam) {
      const Eigen::Matrix3d R = tracked.T_world_cam->linear();
      out->max_shear =
          std::max(out->max_shear, (R.transpose() * R - Eigen::Matrix3d::Identity()).norm());
    }
  }
  (*frontend)->Finish();
  out->trajectory = (*frontend)->FrameTrajectory();
  out->keyframe_trajectory = (*frontend)->KeyframeTrajectory();
  out->ground_truth = source.GroundTruth();
  out->stats = (*frontend)->stats();
}

TrackingOptions Synchronous() {
  TrackingOptions o;
  o.synchronous_mapping = true;
  return o;
}

// Every frame of a written sequence through a front-end with `options`, each first shown to
// `check`: the frame trajectory's ATE RMSE (1 m where a step failed), nothing lost.
double FrameAteOf(const TumSequence& sequence, const TrackingOptions& options,
                  const std::function<void(const RgbdFrame&)>& check = nullptr) {
  auto frontend = Frontend::Create(sequence.camera(), options, nullptr);
  EXPECT_TRUE(frontend.ok());
  if (!frontend.ok()) return 1.0;
  for (std::size_t i = 0; i < sequence.size(); ++i) {
    auto frame = sequence.LoadFrame(i);
    EXPECT_TRUE(frame.ok()) << frame.status().ToString();
    if (!frame.ok()) return 1.0;
    if (check) check(*frame);
    (*frontend)->ProcessFrame(*frame);
  }
  (*frontend)->Finish();
  EXPECT_EQ((*frontend)->stats().lost_frames, 0);
  auto ate = ComputeAte(sequence.GroundTruthAtFrames(), (*frontend)->FrameTrajectory());
  EXPECT_TRUE(ate.ok());
  return ate.ok() ? ate->error.rmse : 1.0;
}

TEST(FrontendTest, TracksAShortSequenceWithinAFewMillimetres) {
  RunResult r;
  RunSequence(120, Synchronous(), &r);
  EXPECT_EQ(r.stats.lost_frames, 0);
  EXPECT_EQ(r.stats.tracked_frames, 120);
  ASSERT_EQ(r.trajectory.size(), 120u);
  auto ate = ComputeAte(r.ground_truth, r.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
  // The map frame is the first camera: the first pose is (close to) the identity.
  EXPECT_LT(r.trajectory.front().T_world_cam.translation().norm(), 0.005);
  EXPECT_GE(r.stats.keyframes, 4);
}

// Motion blur, as a hand-held camera in dim light records it: colour exposed for 20 ms while
// the camera turns at 45 degrees a second (a smear of about 4 pixels at 320x240), depth sharp. Blur
// takes corners and makes descriptors differ from frame to frame, but tracking must hold, and stay
// within a few millimetres (docs/benchmarks/frontend.md#motion-blur).
TEST(FrontendTest, TracksThroughMotionBlur) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 90;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 8;
  synth.exposure_s = 0.02;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), synth).ok());
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  Collector sink;
  auto frontend = Frontend::Create(sequence->camera(), Synchronous(), &sink);
  ASSERT_TRUE(frontend.ok());
  Trajectory ground_truth;
  for (std::size_t i = 0; i < sequence->size(); ++i) {
    auto frame = sequence->LoadFrame(i);
    ASSERT_TRUE(frame.ok()) << frame.status().ToString();
    (*frontend)->ProcessFrame(*frame);
    ground_truth.push_back({sequence->frame(i).timestamp, *sequence->frame(i).T_world_cam_gt});
  }
  (*frontend)->Finish();
  EXPECT_EQ((*frontend)->stats().lost_frames, 0);
  auto ate = ComputeAte(ground_truth, (*frontend)->FrameTrajectory());
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
}

// A Kinect v1's depth comes 10-15 ms after its colour (TUM RGB-D). On a fast path (1.2 m/s,
// 63 degrees a second) 13 ms move the view by about 1.5 cm and 0.8 degrees, which the depth as
// taken puts into every keypoint and keyframe; moved to the colour image's time by the motion
// model, the error falls to what the sequence without the lag gives, within a few millimetres
// (docs/benchmarks/frontend.md#depth-taken-after-colour). The keypoints' depths are looked up
// again once the frame's own motion is solved: 14.2 mm as taken, 6.4 mm moved by the predicted
// motion alone, 3.5 mm with the second lookup.
TEST(FrontendTest, DepthTakenAfterColourIsMovedToTheColourImagesTime) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 240;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 6;
  synth.depth_lag_s = 0.013;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), synth).ok());
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  const auto rmse = [&](bool compensate) {
    TrackingOptions options = Synchronous();
    options.compensate_depth_lag = compensate;
    return FrameAteOf(*sequence, options, [](const RgbdFrame& frame) {
      EXPECT_NEAR(frame.depth_time_offset, 0.013, 1e-6);
    });
  };
  const double as_taken = rmse(false), moved = rmse(true);
  EXPECT_LT(moved, 0.4 * as_taken) << "as taken " << as_taken << " m";
  EXPECT_LT(moved, 0.005);
}

// A map's first keyframe is made before any motion is known, so on a fast path (1.2 m/s) with
// depth taken 13 ms after colour nothing can move its depth image when it is made. It waits for
// the next frame's solved motion and its keypoints' depths are then looked up again in the
// depth image moved to the colour image's time; as taken, they carry the camera's motion over
// the lag. Compared with the depth the same renderer gives without the lag (exact depth).
TEST(FrontendTest, FirstKeyframeDepthsAreMovedWithTheNextFramesMotion) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 4;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.noise = false;
  synth.path.loop_period_s = 6;
  SyntheticSequenceOptions lagged = synth;
  lagged.depth_lag_s = 0.013;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("together"), synth).ok());
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("lagged"), lagged).ok());
  auto together = TumSequence::Open(dir.File("together"), std::nullopt);
  auto sequence = TumSequence::Open(dir.File("lagged"), std::nullopt);
  ASSERT_TRUE(together.ok() && sequence.ok());
  auto truth = together->LoadFrame(0);
  ASSERT_TRUE(truth.ok());
  // Median |depth sent - depth at the colour image's time| over the first keyframe's keypoints.
  const auto median_error = [&](bool compensate) {
    TrackingOptions options = Synchronous();
    options.compensate_depth_lag = compensate;
    Collector sink;
    auto frontend = Frontend::Create(sequence->camera(), options, &sink);
    EXPECT_TRUE(frontend.ok());
    if (!frontend.ok()) return 1.0;
    for (std::size_t i = 0; i < sequence->size(); ++i) {
      auto frame = sequence->LoadFrame(i);
      EXPECT_TRUE(frame.ok());
      if (frame.ok()) (*frontend)->ProcessFrame(*frame);
    }
    (*frontend)->Finish();
    EXPECT_FALSE(sink.keyframes.empty());
    if (sink.keyframes.empty()) return 1.0;
    const KeyframeSnapshot& first = sink.keyframes.front();
    EXPECT_EQ(first.frame_index, 0);
    std::vector<double> errors;
    for (std::size_t k = 0; k < first.keypoints.size(); ++k) {
      const cv::Point2f& pt = first.keypoints[k].pt;
      const int x = cvRound(pt.x), y = cvRound(pt.y);
      if (first.depth[k] <= 0 || x < 0 || y < 0 || x >= truth->depth_mm.cols ||
          y >= truth->depth_mm.rows)
        continue;
      const std::uint16_t z = truth->depth_mm.at<std::uint16_t>(y, x);
      if (z > 0) errors.push_back(std::abs(first.depth[k] - z * 1e-3));
    }
    EXPECT_GT(errors.size(), 100u);
    if (errors.empty()) return 1.0;
    std::nth_element(errors.begin(), errors.begin() + errors.size() / 2, errors.end());
    return errors[errors.size() / 2];
  };
  const double as_taken = median_error(false), moved = median_error(true);
  EXPECT_GT(as_taken, 0.002) << "the lag must move the depths for this test to mean anything";
  EXPECT_LT(moved, 0.1 * as_taken) << "as taken " << as_taken << " m";  // 0.4 against 12 mm
}

// A rolling shutter read out over 30 ms, on a fast path (a loop every 6 s: 60 degrees and
// 1.2 m a second): the first and last rows see the scene from 35 mm and 1.8 degrees apart, 8
// pixels at this resolution. Each keypoint moved to the frame's time by the motion model takes
// the error back to the global shutter's; as detected, it is several times that (when written:
// 3.0 mm with a global shutter, 11.8 mm as detected, 2.8 mm moved; 2.7 mm since each frame's
// keypoints are moved again by its own solved motion).
TEST(FrontendTest, RollingShutterKeypointsAreMovedToTheFramesTime) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 150;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 6;
  SyntheticSequenceOptions rolling = synth;
  rolling.rolling_shutter_s = 0.03;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("global"), synth).ok());
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("rolling"), rolling).ok());
  const auto rmse = [&](const std::string& name, double readout) {
    auto sequence = TumSequence::Open(dir.File(name), std::nullopt);
    EXPECT_TRUE(sequence.ok()) << sequence.status().ToString();
    if (!sequence.ok()) return 1.0;
    TrackingOptions options = Synchronous();
    options.rolling_shutter_readout = readout;
    return FrameAteOf(*sequence, options);
  };
  const double global = rmse("global", 0), as_read = rmse("rolling", 0),
               moved = rmse("rolling", 0.03);
  EXPECT_GT(as_read, 2 * global) << "global shutter " << global << " m";
  EXPECT_LT(moved, 0.5 * as_read) << "as read " << as_read << " m";
  EXPECT_LT(moved, 1.5 * global) << "global shutter " << global << " m";
}

// A camera that drops frames (a USB link, an agent behind the sensor) delivers them at uneven
// intervals. Two frames kept of every six, alternately 1/30 s and 5/30 s apart: a velocity per
// frame predicts every frame 4/30 s of motion off, and the search around that prediction misses
// the last frame's points; a velocity per second predicts where the camera is.
TEST(FrontendTest, TheMotionModelPredictsByTheTimeSinceTheLastFrame) {
  SyntheticSequenceOptions synth;
  synth.frames = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 8;
  SyntheticSource source(synth);
  auto frontend = Frontend::Create(source.camera(), Synchronous(), nullptr);
  ASSERT_TRUE(frontend.ok()) << frontend.status().ToString();
  RgbdFrame frame;
  int kept = 0;
  for (int i = 0; source.Read(&frame).ok(); ++i) {
    if (i % 6 > 1) continue;
    (*frontend)->ProcessFrame(frame);
    ++kept;
  }
  (*frontend)->Finish();
  const FrontendStats stats = (*frontend)->stats();
  EXPECT_EQ(stats.lost_frames, 0);
  EXPECT_EQ(stats.tracked_frames, kept);
  auto ate = ComputeAte(source.GroundTruth(), (*frontend)->FrameTrajectory());
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.003);
  // A velocity per frame: 15 of the 80 frames (docs/benchmarks/frontend.md#frames-dropped).
  EXPECT_LE(stats.motion_model_misses, 2);
}

// Two thirds of a second without features (frames 12-31), on exact depth: the room's depth
// places each of those frames against the newest keyframe's, or the frame before's where the
// view has left the keyframe, and when the colour comes back the local map is found again from
// there. Nothing is lost, the trajectory stays within millimetres of the truth, and its
// rotations stay rotations: each bridged pose predicts the next, and a product's rounding fed
// back so grew frame after frame (1e-4 off orthonormal after these 20 frames; on ICL-NUIM a 1 %
// shear after a second, when the alignments stopped converging). Without the bridge the same
// frames are lost, and the camera is found again by relocalisation.
TEST(FrontendTest, DepthCarriesTrackingThroughFramesWithoutFeatures) {
  constexpr int kFrames = 90, kFirst = 12, kBlank = 20;
  TrackingOptions with = Synchronous();
  with.depth_noise.sigma_2 = 0;  // a renderer's depth, as configs/icl_nuim.yaml gives it
  TrackingOptions without = with;
  without.depth_bridge_seconds = 0;
  RunResult bridged, lost;
  const std::pair<int, int> blank{kFirst, kFirst + kBlank - 1};
  RunSequence(kFrames, with, &bridged, /*sensor_noise=*/false, blank);
  RunSequence(kFrames, without, &lost, /*sensor_noise=*/false, blank);
  EXPECT_GE(lost.stats.lost_frames, kBlank);
  EXPECT_EQ(lost.stats.depth_only_frames, 0);
  EXPECT_EQ(bridged.stats.lost_frames, 0);
  EXPECT_EQ(bridged.stats.tracked_frames, kFrames);
  EXPECT_GE(bridged.stats.depth_only_frames, kBlank);
  ASSERT_EQ(bridged.trajectory.size(), static_cast<std::size_t>(kFrames));
  auto ate = ComputeAte(bridged.ground_truth, bridged.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.005);
  EXPECT_LT(ate->error.max, 0.01);
  EXPECT_LT(bridged.max_shear, 1e-12);
}

// Features come back after two thirds of a second placed by depth, but in a view the map does
// not hold (the colour inverted from then on). Once the bridge has lasted the time a lost camera
// waits for relocalisation (here half a second), a new segment starts at that frame, at the pose
// the depth gave, and tracking goes on from there: nothing lost, one restart, 1.5 mm RMSE.
// Before, the frames were placed by depth alone until the view no longer fixed the pose (frame
// 34), and a segment then started from the last placed pose, as far off as the camera had moved
// since (here a frame, as the first segment is young: 6.7 mm RMSE; otherwise after half a
// second lost).
TEST(FrontendTest, FeaturesBackWhereTheMapIsNotStartASegmentAtTheBridgedPose) {
  constexpr int kFrames = 80, kFirst = 12, kBlank = 20;
  TrackingOptions options = Synchronous();
  options.depth_noise.sigma_2 = 0;
  options.relocalisation_seconds = 0.5;
  RunResult r;
  RunSequence(kFrames, options, &r, /*sensor_noise=*/false,
              std::make_pair(kFirst, kFirst + kBlank - 1),
              /*inverted_from=*/kFirst + kBlank);
  EXPECT_EQ(r.stats.lost_frames, 0);
  EXPECT_EQ(r.stats.restarts, 1);
  EXPECT_GE(r.stats.depth_only_frames, kBlank);
  ASSERT_EQ(r.trajectory.size(), static_cast<std::size_t>(kFrames));
  auto ate = ComputeAte(r.ground_truth, r.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.003);
  EXPECT_LT(ate->error.max, 0.007);
}

// The keyframes' depth alignments tell how closely the depth fits where the surfaces are matched
// rightly, in sigmas of the config's model: a model stricter than the depth (a tenth of a
// millimetre on depth rounded to millimetres) reads several sigma, the Kinect model on the
// room's Kinect-like noise well under two. The bridge allows a frame placed by depth alone as
// much (RealDataFrontendTest.IclNuimBridgesBlankFramesOnItsConfigsModel).
TEST(FrontendTest, KeyframeDepthFitIsMeasuredInTheModelsSigmas) {
  TrackingOptions strict = Synchronous();
  strict.depth_noise.sigma_0 = 0.0001;
  strict.depth_noise.sigma_2 = 0;
  RunResult exact, noisy;
  RunSequence(40, strict, &exact, /*sensor_noise=*/false);
  RunSequence(40, Synchronous(), &noisy, /*sensor_noise=*/true);
  EXPECT_GT(exact.stats.mapping.depth_fit_sigmas, 2.0);
  EXPECT_GT(noisy.stats.mapping.depth_fit_sigmas, 0.0);
  EXPECT_LT(noisy.stats.mapping.depth_fit_sigmas, 2.0);
}

// A blank view of a single wall leaves the pose free along the wall: depth alone does not
// place it, and the frame is lost (then relocalised) rather than put anywhere.
TEST(FrontendTest, DepthAloneDoesNotPlaceAFrameOnAPlanarView) {
  TrackingOptions options = Synchronous();
  options.depth_noise.sigma_2 = 0;
  RunResult r;
  // Frame 60 looks at a wall and a strip of floor (depth alignment conditioning 0.0005).
  RunSequence(90, options, &r, /*sensor_noise=*/false, std::make_pair(60, 69));
  EXPECT_EQ(r.stats.depth_only_frames, 0);
  EXPECT_GE(r.stats.lost_frames, 10);
}

// A room with plain walls (4 texture shapes per square metre instead of 260): where the camera
// faces a wall, the local map gives fewer inliers than ORB-SLAM's 30 for a frame or two. Each
// has a depth, and the frame's depth image, aligned with the newest keyframe's from the pose
// they give, leaves that pose where it is: the frame is tracked. Without that check it was lost
// there, and a new map segment started a second later (30 frames lost, 15 cm RMSE).
TEST(FrontendTest, FewFeaturesConfirmedByTheFramesDepthAreTracked) {
  SyntheticSequenceOptions synth;
  synth.frames = 400;
  synth.seed = 2;
  synth.room.shapes_per_m2 = 4;
  SyntheticSource source(synth);
  auto frontend = Frontend::Create(source.camera(), Synchronous(), nullptr);
  ASSERT_TRUE(frontend.ok()) << frontend.status().ToString();
  RgbdFrame frame;
  while (source.Read(&frame).ok()) (*frontend)->ProcessFrame(frame);
  (*frontend)->Finish();
  EXPECT_EQ((*frontend)->stats().lost_frames, 0);
  EXPECT_EQ((*frontend)->stats().restarts, 0);
  auto ate = ComputeAte(source.GroundTruth(), (*frontend)->FrameTrajectory());
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
}

// The same check refuses what the depth contradicts. Frames 60-69 face a wall with only a
// 110x110 pixel patch of texture left (24-29 inliers), their depth 3 % too far: aligned with
// the keyframe's depth it fits at 12 sigma, and the frames are lost rather than tracked on
// their few features. With their depth as rendered, the same frames are tracked.
TEST(FrontendTest, FewFeaturesTheFramesDepthContradictsAreLost) {
  TrackingOptions options = Synchronous();
  options.depth_noise.sigma_2 = 0;
  const auto run = [&](double depth_scale) {
    RunResult r;
    RunSequence(80, options, &r, /*sensor_noise=*/false, std::nullopt, -1,
                [&](int i, RgbdFrame* f) {
                  if (i < 60 || i > 69) return;
                  const cv::Rect patch(265, 185, 110, 110);
                  const cv::Mat kept = f->bgr(patch).clone();
                  f->bgr.setTo(cv::Scalar(128, 128, 128));
                  kept.copyTo(f->bgr(patch));
                  f->depth_mm.convertTo(f->depth_mm, f->depth_mm.type(), depth_scale);
                });
    return r.stats.lost_frames;
  };
  EXPECT_GE(run(1.03), 10);
  EXPECT_EQ(run(1.0), 0);
}

// Keyframes' depth alignments are found and kept, and they agree with the features: on the
// synthetic room, whose keypoint depths already carry most of what the depth says, the run with
// them stays as accurate as without (a wrong relative pose or information would pull the
// keyframes apart). Where the alignments add what the features lack, on rendered ICL-NUIM
// frames, real_data_test.cc checks that they help.
TEST(FrontendTest, DepthAlignmentsAgreeWithTheFeatures) {
  TrackingOptions without = Synchronous();
  without.depth_alignment_weight = 0;
  RunResult a, b;
  RunSequence(240, without, &a);
  RunSequence(240, Synchronous(), &b);
  EXPECT_EQ(a.stats.mapping.depth_alignments, 0);
  EXPECT_GT(b.stats.mapping.depth_alignments, b.stats.keyframes);  // several neighbours each
  EXPECT_EQ(b.stats.mapping.depth_alignments_failed, 0);
  auto ate_without = ComputeAte(a.ground_truth, a.trajectory);
  auto ate_with = ComputeAte(b.ground_truth, b.trajectory);
  ASSERT_TRUE(ate_without.ok() && ate_with.ok());
  EXPECT_LT(ate_with->error.rmse, 1.25 * ate_without->error.rmse)
      << ate_with->error.rmse << " m with, " << ate_without->error.rmse << " m without";
}

// With exact depth (a renderer's, as ICL-NUIM's), each frame's depth aligned with its keyframe's
// holds the frame's pose closer than its keypoints do: the frames between keyframes come closer
// to the truth, and the keyframes do not move away from it.
TEST(FrontendTest, FrameDepthPriorHoldsFramesOnExactDepth) {
  constexpr int kFrames = 120;
  TrackingOptions with = Synchronous();
  with.depth_noise.sigma_2 = 0;    // the depth's noise model, as configs/icl_nuim.yaml gives it
  with.frame_depth_weight = 0.03;  // configs/icl_nuim.yaml
  TrackingOptions without = with;
  without.frame_depth_weight = 0;
  RunResult a, b;
  RunSequence(kFrames, without, &a, /*sensor_noise=*/false);
  RunSequence(kFrames, with, &b, /*sensor_noise=*/false);
  auto frames_without = ComputeAte(a.ground_truth, a.trajectory);
  auto frames_with = ComputeAte(b.ground_truth, b.trajectory);
  auto keyframes_without = ComputeAte(a.ground_truth, a.keyframe_trajectory);
  auto keyframes_with = ComputeAte(b.ground_truth, b.keyframe_trajectory);
  ASSERT_TRUE(frames_without.ok() && frames_with.ok() && keyframes_without.ok() &&
              keyframes_with.ok());
  EXPECT_EQ(b.stats.lost_frames, 0);
  EXPECT_LT(frames_with->error.rmse, 0.9 * frames_without->error.rmse)
      << frames_with->error.rmse << " m with, " << frames_without->error.rmse << " m without";
  EXPECT_LT(keyframes_with->error.rmse, 1.1 * keyframes_without->error.rmse)
      << keyframes_with->error.rmse << " m with, " << keyframes_without->error.rmse << " m without";
}

// Off unless a config asks (real sensors' depth errors are correlated); a weight that is not a
// finite non-negative number is refused, not run.
TEST(FrontendTest, FrameDepthWeightIsOffByDefaultAndChecked) {
  TrackingOptions options;
  EXPECT_EQ(options.frame_depth_weight, 0.0);
  options.frame_depth_weight = 0.03;
  EXPECT_TRUE(options.Validate().ok());
  for (double bad : {-0.1, std::nan(""), HUGE_VAL}) {
    options.frame_depth_weight = bad;
    EXPECT_FALSE(options.Validate().ok()) << bad;
  }
}

TEST(FrontendTest, SinkGetsEveryKeyframeOnceWithConsistentLinks) {
  RunResult r;
  RunSequence(90, Synchronous(), &r);
  ASSERT_FALSE(r.sink.keyframes.empty());
  std::set<std::uint32_t> ids;
  std::set<std::uint32_t> sent_points;
  int depth_links = 0;
  for (const KeyframeSnapshot& k : r.sink.keyframes) {
    EXPECT_TRUE(ids.insert(k.id.value()).second) << "keyframe sent twice";
    ASSERT_EQ(k.point_ids.size(), k.keypoints.size());
    ASSERT_EQ(k.descriptors.rows, static_cast<int>(k.keypoints.size()));
    for (const auto& p : k.new_points) {
      EXPECT_TRUE(sent_points.insert(p.id.value()).second) << "map point sent twice";
      ASSERT_GE(p.keypoint, 0);
      EXPECT_EQ(k.point_ids[p.keypoint], p.id);
      // A new point's position in the keyframe frame projects close to its keypoint: within
      // the 95% gate of the keypoint's octave (sigma = 1.2^octave pixels), plus a pixel.
      const Eigen::Vector3d& pc = p.position_cam;
      const double u = 525.0 * pc.x() / pc.z() + 319.5;
      const double gate = std::sqrt(5.991) * std::pow(1.2, k.keypoints[p.keypoint].octave) + 1.0;
      EXPECT_NEAR(u, k.keypoints[p.keypoint].pt.x, gate);
    }
    // Every linked point was sent, with this keyframe or before.
    for (const auto& id : k.point_ids) {
      if (id) {
        EXPECT_TRUE(sent_points.count(id->value())) << "link to an unknown point";
      }
    }
    for (const auto& [neighbour, weight] : k.covisibility)
      EXPECT_TRUE(ids.count(neighbour.value()));
    // Depth links go to keyframes sent before, with a usable information matrix.
    for (const auto& link : k.depth_links) {
      EXPECT_TRUE(ids.count(link.other.value()) && link.other != k.id)
          << "depth link to an unsent keyframe";
      EXPECT_TRUE(link.information.allFinite());
      EXPECT_GT(link.information.trace(), 0);
      ++depth_links;
    }
    EXPECT_EQ(k.has_rgbd, !k.bgr.empty());
  }
  EXPECT_GT(depth_links, static_cast<int>(r.sink.keyframes.size()));  // several per keyframe
  EXPECT_TRUE(r.sink.keyframes.front().has_rgbd);  // nothing was sent before the first
  for (const PoseUpdate& u : r.sink.updates) EXPECT_TRUE(ids.count(u.id.value()));
}

// The default: local mapping in its own thread while the tracker goes on (the agents' mode,
// and the one the ThreadSanitizer run checks). The sink hears of each keyframe once, in the
// order the tracker made them, and the path is tracked as well as synchronously.
TEST(FrontendTest, AsynchronousMappingSendsEachKeyframeOnceInOrderAndTracks) {
  TrackingOptions asynchronous;
  ASSERT_FALSE(asynchronous.synchronous_mapping);
  RunResult r;
  RunSequence(120, asynchronous, &r);
  EXPECT_EQ(r.stats.lost_frames, 0);
  ASSERT_EQ(r.trajectory.size(), 120u);
  ASSERT_GE(r.sink.keyframes.size(), 3u);
  std::set<std::uint32_t> ids;
  for (std::size_t i = 0; i < r.sink.keyframes.size(); ++i) {
    const KeyframeSnapshot& k = r.sink.keyframes[i];
    EXPECT_TRUE(ids.insert(k.id.value()).second) << "keyframe sent twice";
    if (i > 0) {
      EXPECT_GT(k.frame_index, r.sink.keyframes[i - 1].frame_index);
    }
  }
  for (const PoseUpdate& u : r.sink.updates) EXPECT_TRUE(ids.count(u.id.value()));
  auto ate = ComputeAte(r.ground_truth, r.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
}

// With a rolling-shutter readout set the map's first keyframe waits for the next frame's
// motion before local mapping gets it. On its own thread, local mapping still sends it first
// and once, the others in order after it; when the input ends at that first frame, finishing
// hands it over all the same.
TEST(FrontendTest, AsynchronousMappingSendsAWaitingFirstKeyframeFirstAndOnce) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 60;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 6;
  synth.rolling_shutter_s = 0.03;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), synth).ok());
  auto sequence = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  const auto run = [&](std::size_t frames, Collector* sink) {
    TrackingOptions options;
    options.rolling_shutter_readout = 0.03;
    ASSERT_FALSE(options.synchronous_mapping);
    auto frontend = Frontend::Create(sequence->camera(), options, sink);
    ASSERT_TRUE(frontend.ok());
    for (std::size_t i = 0; i < frames; ++i) {
      auto frame = sequence->LoadFrame(i);
      ASSERT_TRUE(frame.ok());
      (*frontend)->ProcessFrame(*frame);
    }
    (*frontend)->Finish();
    EXPECT_EQ((*frontend)->stats().lost_frames, 0);
  };
  Collector all;
  run(sequence->size(), &all);
  ASSERT_GE(all.keyframes.size(), 3u);
  EXPECT_EQ(all.keyframes.front().frame_index, 0);
  std::set<std::uint32_t> ids;
  for (std::size_t i = 0; i < all.keyframes.size(); ++i) {
    EXPECT_TRUE(ids.insert(all.keyframes[i].id.value()).second) << "keyframe sent twice";
    if (i > 0) {
      EXPECT_GT(all.keyframes[i].frame_index, all.keyframes[i - 1].frame_index);
    }
  }
  Collector one;
  run(1, &one);
  ASSERT_EQ(one.keyframes.size(), 1u);
  EXPECT_EQ(one.keyframes.front().frame_index, 0);
}

TEST(FrontendTest, BoundedMapStaysBounded) {
  TrackingOptions o = Synchronous();
  o.local_ba_window = 5;
  o.max_keyframes = 12;
  RunResult r;
  RunSequence(240, o, &r);
  EXPECT_EQ(r.stats.lost_frames, 0);
  EXPECT_LE(r.stats.map_keyframes, 12);
  EXPECT_GT(r.stats.keyframes, 12);  // more were created than kept
  auto ate = ComputeAte(r.ground_truth, r.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.02);
}

// The frames of `parts` (ranges of the 600-frame sequence) one after the other, stamped at the
// frame rate as if the camera had been carried from one part to the next in an instant (or,
// with `gap_s`, that much later, as if frames were dropped): a tracking failure that no
// relocalisation can mend where the parts do not see the same place.
void RunParts(const std::vector<FrameRange>& parts, RunResult* out, double gap_s = 0) {
  SyntheticSequenceOptions synth;
  synth.frames = 600;
  synth.seed = 1;
  auto frontend = Frontend::Create(SyntheticSource(synth, FrameRange{0, 0}).camera(), Synchronous(),
                                   &out->sink);
  ASSERT_TRUE(frontend.ok()) << frontend.status().ToString();
  int k = 0;
  for (const FrameRange& part : parts) {
    SyntheticSource source(synth, part);
    const Trajectory truth = source.GroundTruth();
    RgbdFrame frame;
    for (int i = 0; source.Read(&frame).ok(); ++i, ++k) {
      frame.timestamp = k / synth.fps + (k >= parts.front().size() ? gap_s : 0.0);
      out->ground_truth.push_back({frame.timestamp, truth[i].T_world_cam});
      (*frontend)->ProcessFrame(frame);
    }
  }
  (*frontend)->Finish();
  out->trajectory = (*frontend)->FrameTrajectory();
  out->stats = (*frontend)->stats();
}

// The poses of `trajectory` from time `t0` on.
Trajectory From(const Trajectory& trajectory, double t0) {
  Trajectory after;
  for (const StampedPose& p : trajectory) {
    if (p.timestamp >= t0 - 1e-9) after.push_back(p);
  }
  return after;
}

// Ten frames make a map of one keyframe, too young to relocalise in (ORB-SLAM resets such a
// map): the first frame of the other part starts a new segment at once, at the last tracked
// pose, and tracks the rest of that part as well as any. Made at the next frame, the restart
// is a reset (its pose as good as tracking's); after a gap in time it is not.
TEST(FrontendTest, ALostYoungMapRestartsAtOnceFromTheLastPose) {
  RunResult gap;
  RunParts({{0, 9}, {300, 309}}, &gap, 5.0);
  EXPECT_EQ(gap.stats.restarts, 1);
  EXPECT_EQ(gap.stats.lost_frames, 0);
  for (const KeyframeSnapshot& k : gap.sink.keyframes) EXPECT_FALSE(k.reset);

  RunResult r;
  RunParts({{0, 9}, {300, 359}}, &r);
  EXPECT_EQ(r.stats.restarts, 1);
  EXPECT_EQ(r.stats.lost_frames, 0);
  EXPECT_EQ(r.stats.tracked_frames, 70);
  int restarts = 0;
  for (const KeyframeSnapshot& k : r.sink.keyframes) {
    if (!k.restart) continue;
    ++restarts;
    EXPECT_TRUE(k.reset);
    EXPECT_NEAR(k.timestamp, 10 / 30.0, 1e-9);
    EXPECT_FALSE(k.parent.has_value());
    ASSERT_GE(r.trajectory.size(), 10u);
    EXPECT_LT(TranslationDistance(k.T_world_cam, r.trajectory[9].T_world_cam), 0.001);
  }
  EXPECT_EQ(restarts, 1);
  auto ate = ComputeAte(From(r.ground_truth, 10 / 30.0), From(r.trajectory, 10 / 30.0));
  ASSERT_TRUE(ate.ok());
  EXPECT_EQ(ate->matched, 60u);
  EXPECT_LT(ate->error.rmse, 0.01);
}

// A map of several keyframes is given the relocalisation time (one second by default) to find
// the camera again; then a new segment starts.
TEST(FrontendTest, AnEstablishedMapRestartsAfterTheRelocalisationTime) {
  RunResult r;
  RunParts({{0, 89}, {400, 459}}, &r);
  EXPECT_EQ(r.stats.restarts, 1);
  for (std::size_t i = 0; i < r.sink.keyframes.size(); ++i) {
    const KeyframeSnapshot& k = r.sink.keyframes[i];
    EXPECT_FALSE(k.reset);
    // The frames while lost make no keyframe and use up no keyframe id.
    if (k.restart && i > 0) {
      EXPECT_EQ(k.id.value(), r.sink.keyframes[i - 1].id.value() + 1);
    }
  }
  EXPECT_GE(r.stats.lost_frames, 29);
  EXPECT_LE(r.stats.lost_frames, 31);
  auto ate = ComputeAte(From(r.ground_truth, 121 / 30.0), From(r.trajectory, 121 / 30.0));
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
}

// Where the map does see the place again, relocalisation finds the camera and no segment starts.
TEST(FrontendTest, ACameraBackInTheMapRelocalisesInsteadOfRestarting) {
  RunResult r;
  RunParts({{0, 89}, {30, 89}}, &r);
  EXPECT_EQ(r.stats.restarts, 0);
  EXPECT_LE(r.stats.lost_frames, 2);
  auto ate = ComputeAte(r.ground_truth, r.trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
}

// Frame records and the poses of keyframes that left the bounded map are what the
// trajectories are made of: without them (a live agent that writes no trajectory) the frames
// and the dropped keyframes leave nothing behind, and the keyframes are made and sent as before.
TEST(FrontendTest, WithoutTrajectoryRecordsNothingIsLeftBehind) {
  TrackingOptions o = Synchronous();
  o.local_ba_window = 5;
  o.max_keyframes = 10;
  RunResult without, with;
  RunSequence(90, o, &with);
  o.record_trajectory = false;
  RunSequence(90, o, &without);
  ASSERT_GT(with.stats.keyframes, with.stats.map_keyframes);  // some left the map
  EXPECT_EQ(with.trajectory.size(), 90u);
  EXPECT_EQ(with.keyframe_trajectory.size(), static_cast<std::size_t>(with.stats.keyframes));
  EXPECT_EQ(without.stats.tracked_frames, 90);
  EXPECT_TRUE(without.trajectory.empty());
  EXPECT_EQ(without.keyframe_trajectory.size(),
            static_cast<std::size_t>(without.stats.map_keyframes));
  EXPECT_EQ(without.stats.keyframes, with.stats.keyframes);
  EXPECT_EQ(without.sink.keyframes.size(), with.sink.keyframes.size());
}

// A frame's pose is kept in single precision relative to its reference keyframe: a few metres
// and any rotation come back within a micrometre and a microradian, in 40 bytes.
TEST(FrameRecordTest, SinglePrecisionKeepsThePose) {
  static_assert(sizeof(Tracker::FrameRecord) <= 40, "a frame record grows the agent's memory");
  Pose T = Pose::Identity();
  T.linear() =
      Eigen::AngleAxisd(2.7, Eigen::Vector3d(0.3, -1, 0.4).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(3.1, -2.2, 0.7);
  const Tracker::FrameRecord record(12.5, KeyframeId(7), T);
  const Pose back = record.T_ref_cam();
  EXPECT_EQ(record.timestamp, 12.5);
  EXPECT_EQ(record.reference, KeyframeId(7));
  EXPECT_LT((back.translation() - T.translation()).norm(), 1e-6);
  EXPECT_LT(Eigen::AngleAxisd(back.linear().transpose() * T.linear()).angle(), 1e-6);
  EXPECT_LT((back.linear().transpose() * back.linear() - Eigen::Matrix3d::Identity()).norm(),
            1e-12);
}

TEST(FrontendTest, BadOptionsAreRefused) {
  TrackingOptions o;
  o.local_ba_window = 0;
  EXPECT_FALSE(Frontend::Create(SyntheticCamera(), o, nullptr).ok());
  PinholeCamera bad = SyntheticCamera();
  bad.fx = 0;
  EXPECT_FALSE(Frontend::Create(bad, TrackingOptions(), nullptr).ok());
}

}  // namespace
}  // namespace ccmd
