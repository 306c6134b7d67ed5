#include "libccmd/netsim/delay_line.h"

#include <gtest/gtest.h>

#include <cmath>

namespace ccmd {
namespace {

std::vector<std::uint8_t> Packet(int tag, std::size_t size = 100) {
  return std::vector<std::uint8_t>(size, tag & 0xFF);
}

TEST(DelayLineTest, FixedDelayReleasesEachPacketExactlyOnTime) {
  DelayLineOptions o;
  o.delay_s = 0.05;
  DelayLine line(o);
  ASSERT_TRUE(line.Push(1.0, Packet(1)));
  ASSERT_TRUE(line.Push(1.01, Packet(2)));
  std::vector<std::uint8_t> out;
  EXPECT_DOUBLE_EQ(line.NextDue(), 1.05);
  EXPECT_FALSE(line.PopDue(1.0499, &out));
  ASSERT_TRUE(line.PopDue(1.05, &out));
  EXPECT_EQ(out[0], 1);
  EXPECT_FALSE(line.PopDue(1.055, &out));
  ASSERT_TRUE(line.PopDue(1.06, &out));
  EXPECT_EQ(out[0], 2);
  EXPECT_TRUE(std::isinf(line.NextDue()));
  EXPECT_EQ(line.stats().left, 2u);
}

TEST(DelayLineTest, JitterStaysInItsRange) {
  DelayLineOptions o;
  o.delay_s = 0.05;
  o.jitter_s = 0.02;
  o.seed = 9;
  DelayLine line(o);
  double min_delay = 1, max_delay = 0;
  std::vector<std::uint8_t> out;
  for (int i = 0; i < 2000; ++i) {
    const double now = i * 1.0;  // far apart: the order rule never holds a packet back
    ASSERT_TRUE(line.Push(now, Packet(i)));
    min_delay = std::min(min_delay, line.NextDue() - now);
    max_delay = std::max(max_delay, line.NextDue() - now);
    ASSERT_TRUE(line.PopDue(now + 1, &out));
  }
  EXPECT_GE(min_delay, 0.03 - 1e-9);
  EXPECT_LE(max_delay, 0.07 + 1e-9);
  EXPECT_LT(min_delay, 0.031);  // the whole range is used, not just its middle
  EXPECT_GT(max_delay, 0.069);
}

TEST(DelayLineTest, PacketsLeaveInTheOrderTheyCame) {
  DelayLineOptions o;
  o.delay_s = 0.05;
  o.jitter_s = 0.04;
  DelayLine line(o);
  for (int i = 0; i < 500; ++i) ASSERT_TRUE(line.Push(i * 0.001, Packet(i)));
  std::vector<std::uint8_t> out;
  int expected = 0;
  double last_due = 0;
  while (line.waiting() > 0) {
    const double due = line.NextDue();
    EXPECT_GE(due, last_due);
    last_due = due;
    ASSERT_TRUE(line.PopDue(due, &out));
    EXPECT_EQ(out[0], expected & 0xFF);
    ++expected;
  }
  EXPECT_EQ(expected, 500);
}

TEST(DelayLineTest, LossRateMatchesTheSpecAndIsReproducible) {
  auto run = [](std::uint64_t seed) {
    DelayLineOptions o;
    o.loss = 0.02;
    o.seed = seed;
    DelayLine line(o);
    std::vector<bool> fate;
    for (int i = 0; i < 50000; ++i) fate.push_back(line.Push(0, Packet(i, 1)));
    return std::make_pair(fate, line.stats().lost);
  };
  const auto [fate_a, lost_a] = run(4);
  const auto [fate_b, lost_b] = run(4);
  EXPECT_EQ(fate_a, fate_b);
  // 50000 draws at p = 0.02: sigma = 31 packets; 5 sigma either side.
  EXPECT_NEAR(static_cast<double>(lost_a), 1000, 160);
  const auto [fate_c, lost_c] = run(5);
  EXPECT_NE(fate_a, fate_c);
}

TEST(DelayLineTest, FullLineDropsAndCounts) {
  DelayLineOptions o;
  o.delay_s = 1;
  o.max_packets = 3;
  o.max_bytes = 250;
  DelayLine line(o);
  EXPECT_TRUE(line.Push(0, Packet(1)));
  EXPECT_TRUE(line.Push(0, Packet(2)));
  EXPECT_FALSE(line.Push(0, Packet(3)));  // 300 bytes > 250
  EXPECT_TRUE(line.Push(0, Packet(4, 50)));
  EXPECT_FALSE(line.Push(0, Packet(5, 1)));  // 3 packets
  EXPECT_EQ(line.stats().overflow, 2u);
  EXPECT_EQ(line.waiting(), 3u);
}

}  // namespace
}  // namespace ccmd
