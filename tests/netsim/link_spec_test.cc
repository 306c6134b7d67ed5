#include "libccmd/netsim/link_spec.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

TEST(LinkSpecTest, ParsesTheIssueExample) {
  auto spec = ParseLinkSpec("rate=2.4mbit,delay=50ms,jitter=10ms,loss=0.02");
  ASSERT_TRUE(spec.ok()) << spec.status().ToString();
  EXPECT_DOUBLE_EQ(spec->rate_bytes_per_s, 300000);  // 2.4e6 bits / 8
  EXPECT_DOUBLE_EQ(spec->delay_s, 0.05);
  EXPECT_DOUBLE_EQ(spec->jitter_s, 0.01);
  EXPECT_DOUBLE_EQ(spec->loss, 0.02);
  EXPECT_DOUBLE_EQ(spec->queue_s, 0.1);  // default
  EXPECT_EQ(spec->seed, 1u);
}

TEST(LinkSpecTest, UnitsFollowTc) {
  EXPECT_DOUBLE_EQ(*ParseRateBytesPerSecond("800kbit"), 100000);
  EXPECT_DOUBLE_EQ(*ParseRateBytesPerSecond("100kbps"), 100000);  // tc: bps is bytes per second
  EXPECT_DOUBLE_EQ(*ParseRateBytesPerSecond("1gbit"), 125e6);
  EXPECT_DOUBLE_EQ(*ParseDurationSeconds("250us"), 250e-6);
  EXPECT_DOUBLE_EQ(*ParseDurationSeconds("2s"), 2);
  EXPECT_DOUBLE_EQ(*ParseDurationSeconds("0.5"), 0.5);
  EXPECT_DOUBLE_EQ(ParseLinkSpec("loss=2%")->loss, 0.02);
  EXPECT_EQ(ParseLinkSpec("delay=1ms,seed=7")->seed, 7u);
}

TEST(LinkSpecTest, CanonicalTextParsesBackToTheSameSpec) {
  auto spec = ParseLinkSpec("rate=3mbit,delay=20ms,jitter=5ms,loss=1%,queue=50ms,seed=3");
  ASSERT_TRUE(spec.ok());
  auto again = ParseLinkSpec(spec->ToString());
  ASSERT_TRUE(again.ok()) << spec->ToString() << ": " << again.status().ToString();
  EXPECT_DOUBLE_EQ(again->rate_bytes_per_s, spec->rate_bytes_per_s);
  EXPECT_DOUBLE_EQ(again->delay_s, spec->delay_s);
  EXPECT_DOUBLE_EQ(again->jitter_s, spec->jitter_s);
  EXPECT_DOUBLE_EQ(again->loss, spec->loss);
  EXPECT_DOUBLE_EQ(again->queue_s, spec->queue_s);
  EXPECT_EQ(again->seed, spec->seed);
}

TEST(LinkSpecTest, RejectsWhatCannotBeALink) {
  for (const char* bad : {"", "rate", "rate=fast", "rate=2.4", "rate=2.4mbits", "rate=-1mbit",
                          "rate=10bps", "delay=50", "delay=50xs", "delay=-5ms", "jitter=10ms",
                          "delay=5ms,jitter=10ms", "loss=1", "loss=-0.1", "loss=abc",
                          "bandwidth=1mbit", "rate=1mbit,rate=2mbit", "seed=-3", "queue=0ms"}) {
    EXPECT_FALSE(ParseLinkSpec(bad).ok()) << "'" << bad << "' accepted";
  }
  // Errors name what is wrong.
  EXPECT_NE(ParseLinkSpec("bandwidth=1mbit").status().message().find("bandwidth"),
            std::string::npos);
}

}  // namespace
}  // namespace ccmd
