// Algorithm 1 (RGB-D keyframe selection) on hand-made covisibility.

#include "libccmd/tracking/keyframe_selector.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

using Links = std::vector<std::pair<KeyframeId, int>>;

RgbdSelectionOptions Options(int required = 1) {
  RgbdSelectionOptions o;
  o.threshold_ratio = 0.5;  // S = 0.5 * tracked points
  o.threshold_min_points = 60;
  o.decrement_ratio = 0.1;  // S drops by 0.1 * tracked per covering keyframe
  o.min_threshold = 30;
  o.required_covering = required;
  return o;
}

TEST(RgbdSelectorTest, FirstKeyframeAndUnconnectedOnesAreTransmitted) {
  const RgbdSelector selector(Options());
  EXPECT_TRUE(selector.Decide(KeyframeId(0), 500, {}).transmit);
}

TEST(RgbdSelectorTest, OneStrongTransmittedNeighbourSkipsTheRgbd) {
  const RgbdSelector selector(Options());
  // 400 tracked points: S = 200. A neighbour sharing 250 covers it.
  const RgbdDecision d =
      selector.Decide(KeyframeId(5), 400, {{KeyframeId(3), 120}, {KeyframeId(4), 250}});
  EXPECT_FALSE(d.transmit);
  EXPECT_EQ(d.threshold, 200);
  EXPECT_EQ(d.covering, 1);
  ASSERT_EQ(d.considered.size(), 2u);
  EXPECT_EQ(d.considered[0].first, KeyframeId(4));  // sorted by weight
}

TEST(RgbdSelectorTest, WeakOverlapIsTransmitted) {
  const RgbdSelector selector(Options());
  EXPECT_TRUE(
      selector.Decide(KeyframeId(5), 400, {{KeyframeId(3), 150}, {KeyframeId(4), 200}}).transmit);
}

TEST(RgbdSelectorTest, DecrementLowersTheBarForLaterNeighbours) {
  const RgbdSelector selector(Options(/*required=*/2));
  // S = 200; 250 covers and S becomes 160; 170 > 160 covers too: two covering, skip.
  EXPECT_FALSE(
      selector.Decide(KeyframeId(9), 400, {{KeyframeId(1), 170}, {KeyframeId(2), 250}}).transmit);
  // 150 < 160: only one covering, transmit.
  const RgbdDecision d =
      selector.Decide(KeyframeId(9), 400, {{KeyframeId(1), 150}, {KeyframeId(2), 250}});
  EXPECT_TRUE(d.transmit);
  EXPECT_EQ(d.covering, 1);
}

TEST(RgbdSelectorTest, ThresholdHasFloors) {
  RgbdSelectionOptions o = Options(3);
  const RgbdSelector selector(o);
  // 80 tracked: 0.5 * 80 = 40 < 60, so S = 60; decrement 8 per covering: 61 > 60 -> S 52,
  // 53 > 52 -> S 44, 45 > 44 -> three covering.
  EXPECT_FALSE(selector
                   .Decide(KeyframeId(1), 80,
                           {{KeyframeId(2), 61}, {KeyframeId(3), 53}, {KeyframeId(4), 45}})
                   .transmit);
  o.min_threshold = 50;  // S cannot go below 50: the third (45) no longer covers
  EXPECT_TRUE(RgbdSelector(o)
                  .Decide(KeyframeId(1), 80,
                          {{KeyframeId(2), 61}, {KeyframeId(3), 53}, {KeyframeId(4), 45}})
                  .transmit);
}

TEST(RgbdSelectorTest, DisabledSendsEverything) {
  RgbdSelectionOptions o = Options();
  o.enabled = false;
  EXPECT_TRUE(RgbdSelector(o).Decide(KeyframeId(5), 400, {{KeyframeId(4), 390}}).transmit);
}

TEST(RgbdSelectorTest, TheSinksRequestScalesSminOrForcesTheDecision) {
  const RgbdSelector selector(Options());
  const Links links = {{KeyframeId(3), 150}, {KeyframeId(4), 180}};
  // S = 200: 180 does not cover; S x0.8 = 160 it does; S x1.5 = 300 and 250 no longer covers.
  EXPECT_TRUE(selector.Decide(KeyframeId(5), 400, links).transmit);
  RgbdRequest leaner;
  leaner.threshold_scale = 0.8;
  const RgbdDecision d = selector.Decide(KeyframeId(5), 400, links, leaner);
  EXPECT_FALSE(d.transmit);
  EXPECT_EQ(d.threshold, 160);
  EXPECT_DOUBLE_EQ(d.request.threshold_scale, 0.8);
  RgbdRequest richer;
  richer.threshold_scale = 1.5;
  EXPECT_TRUE(selector.Decide(KeyframeId(5), 400, {{KeyframeId(4), 250}}, richer).transmit);
  EXPECT_FALSE(selector.Decide(KeyframeId(5), 400, {{KeyframeId(4), 250}}).transmit);
  // Forced: geometry only, or RGB-D whatever the neighbours.
  RgbdRequest none;
  none.allow = false;
  EXPECT_FALSE(selector.Decide(KeyframeId(0), 500, {}, none).transmit);
  RgbdRequest every;
  every.every_keyframe = true;
  EXPECT_TRUE(selector.Decide(KeyframeId(5), 400, {{KeyframeId(4), 390}}, every).transmit);
}

}  // namespace
}  // namespace ccmd
