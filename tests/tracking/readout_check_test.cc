// A rolling shutter's readout chosen from a recording's own depth (readout_check.h).

#include "libccmd/tracking/readout_check.h"

#include <gtest/gtest.h>

#include "libccmd/geometry/pose.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/synth/sequence.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

ReadoutTrial Trial(double readout, double translation_mm, double rotation_deg, int pairs = 50) {
  ReadoutTrial t;
  t.readout = readout;
  t.consistency.pairs = pairs;
  t.consistency.translation_median_m = translation_mm * 1e-3;
  t.consistency.rotation_median_rad = rotation_deg * M_PI / 180;
  return t;
}

// The figures of the 30 ms rendering, the global shutter and 7-Scenes every other frame
// (docs/benchmarks/frontend.md, "Choosing the readout without ground truth"): the rotation
// median decides.
TEST(ReadoutCheckTest, ChoosesTheSmallestRotationMedianWhenItBeatsAGlobalShutter) {
  // Between the candidates: the parabola through 15, 30 and 45 ms has its vertex at 28.5 ms.
  const auto rendered_30ms = ChooseReadout({Trial(0.045, 1.49, 0.054), Trial(0, 1.77, 0.069),
                                            Trial(0.015, 1.60, 0.050), Trial(0.03, 1.33, 0.042)},
                                           0.1);
  ASSERT_TRUE(rendered_30ms.has_value());
  EXPECT_NEAR(*rendered_30ms, 0.0285, 1e-6);
  EXPECT_EQ(ChooseReadout(
                {Trial(0, 1.36, 0.046), Trial(0.015, 1.55, 0.057), Trial(0.03, 1.83, 0.062)}, 0.1),
            std::optional<double>(0.0));
  // The translation median is smallest at 30 ms, the rotation's at 0.
  EXPECT_EQ(ChooseReadout(
                {Trial(0, 8.54, 0.375), Trial(0.015, 8.68, 0.404), Trial(0.03, 8.17, 0.429)}, 0.1),
            std::optional<double>(0.0));
  // 30 ms is smallest, but by 5 % only: no readout is shown either way.
  EXPECT_FALSE(ChooseReadout({Trial(0, 1.40, 0.044), Trial(0.03, 1.33, 0.042)}, 0.1).has_value());
  // A trial with no aligned pair counts for nothing; the largest candidate is taken as it is;
  // without readout 0 nothing is chosen.
  EXPECT_EQ(
      ChooseReadout({Trial(0, 1.77, 0.069), Trial(0.03, 0, 0, 0), Trial(0.045, 1.49, 0.054)}, 0.1),
      std::optional<double>(0.045));
  EXPECT_FALSE(ChooseReadout({Trial(0.03, 1.33, 0.042), Trial(0.045, 1.49, 0.054)}, 0.1));
}

// The fast path (a loop every 6 s) rendered with a 30 ms readout and with a global shutter:
// tracked with each candidate, the depth picks the readout each was rendered with (rotation
// medians when written: 0.117 / 0.144 / 0.242 degrees for the global shutter, 0.223 / 0.136 /
// 0.285 for the 30 ms readout, at 0 / 30 / 60 ms).
TEST(ReadoutCheckTest, TheDepthPicksTheReadoutASequenceWasRenderedWith) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 90;
  synth.width = 320;
  synth.height = 240;
  synth.seed = 1;
  synth.path.loop_period_s = 6;
  for (double readout : {0.0, 0.03}) {
    synth.rolling_shutter_s = readout;
    ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
    auto sequence = TumSequence::Open(dir.File("seq"), std::nullopt);
    ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
    std::vector<RgbdFrame> frames;
    for (std::size_t i = 0; i < sequence->size(); ++i) {
      auto frame = sequence->LoadFrame(i);
      ASSERT_TRUE(frame.ok()) << frame.status().ToString();
      frames.push_back(*frame);
    }
    ReadoutCheckOptions options;
    options.candidates = {0.03, 0.06};
    std::vector<double> tried;
    const auto check = CheckReadout(frames, sequence->camera(), TrackingOptions(), options,
                                    [&](const ReadoutTrial& t) { tried.push_back(t.readout); });
    ASSERT_TRUE(check.ok()) << check.status().ToString();
    EXPECT_EQ(tried, (std::vector<double>{0, 0.03, 0.06}));
    // 63 degrees a second: 8 degrees take 4 frames.
    EXPECT_EQ(check->gap, 4);
    for (const ReadoutTrial& t : check->trials) {
      EXPECT_EQ(t.lost_frames, 0);
      EXPECT_GT(t.consistency.pairs, 30);
    }
    ASSERT_TRUE(check->readout.has_value());
    EXPECT_NEAR(*check->readout, readout, 0.01);
  }
}

TEST(ReadoutCheckTest, PairsFramesAsFarApartAsTheCameraTakesToTurnSoMuch) {
  Trajectory turning, still;
  for (int k = 0; k < 100; ++k) {
    StampedPose p;
    p.timestamp = k / 30.0;
    p.T_world_cam.linear() = RotationFromAngleAxis(Eigen::Vector3d(0, k * M_PI / 180, 0));
    turning.push_back(p);
    p.T_world_cam.linear().setIdentity();
    p.T_world_cam.translation() = Eigen::Vector3d(0.01 * k, 0, 0);
    still.push_back(p);
  }
  EXPECT_EQ(GapForRotation(turning, 7.5 * M_PI / 180), 8);
  EXPECT_EQ(GapForRotation(turning, 1 * M_PI / 180), 2);  // never under 2
  EXPECT_EQ(GapForRotation(turning, 90 * M_PI / 180), 30);
  EXPECT_EQ(GapForRotation(still, 8 * M_PI / 180), 30);  // moves without turning
  EXPECT_EQ(GapForRotation(Trajectory(turning.begin(), turning.begin() + 5), 8 * M_PI / 180), 30);
}

TEST(ReadoutCheckTest, RefusesTooFewFramesAndAnImpossibleReadout) {
  ReadoutCheckOptions options;
  EXPECT_EQ(CheckReadout(std::vector<RgbdFrame>(5), PinholeCamera(), TrackingOptions(), options)
                .status()
                .code(),
            StatusCode::kInvalidArgument);
  options.candidates = {-0.01};
  EXPECT_EQ(CheckReadout(std::vector<RgbdFrame>(40), PinholeCamera(), TrackingOptions(), options)
                .status()
                .code(),
            StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace ccmd
