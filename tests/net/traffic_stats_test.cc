#include "libccmd/net/traffic_stats.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

// One agent over two seconds with hand-computed expectations.
TEST(TrafficStatsTest, AveragesRatesAndBucketsByHand) {
  TrafficStats stats({.bucket_seconds = 1.0, .max_buckets = 10}, /*start_time=*/100.0);
  const AgentId a(4);
  stats.AgentConnected(a, "robot", 100.0);
  KeyframeSizeBreakdown parts;
  parts.pose = 28;
  parts.keypoints = 40;
  parts.other = 32;  // 100 bytes in all
  stats.AddDataMessage(a, 16, 100, &parts, 100.5);
  stats.AddDataMessage(a, 17, 40, nullptr, 101.2);
  stats.AddDataMessage(a, 16, 100, &parts, 101.5);
  stats.AddDuplicate(a, 128);
  stats.AgentDisconnected(a, 102.0);

  const Json json = stats.ToJson(105.0);
  ASSERT_EQ(json.Get("agents")->size(), 1u);
  const Json& j = json.Get("agents")->at(0);
  EXPECT_EQ(j.Get("name")->string(), "robot");
  EXPECT_EQ(j.Get("connected_seconds")->number(), 2.0);
  EXPECT_EQ(j.Get("messages")->Get("keyframe")->Get("count")->number(), 2);
  EXPECT_EQ(j.Get("messages")->Get("keyframe")->Get("bytes")->number(), 200);
  EXPECT_EQ(j.Get("messages")->Get("pose_update")->Get("bytes")->number(), 40);
  EXPECT_DOUBLE_EQ(j.Get("average_traffic_bytes_per_s")->number(), 240.0 / 2.0);
  EXPECT_DOUBLE_EQ(j.Get("average_keyframe_bytes")->number(), 100.0);
  EXPECT_DOUBLE_EQ(j.Get("keyframe_rate_hz")->number(), 1.0);
  EXPECT_EQ(j.Get("keyframe_parts_bytes")->Get("pose")->number(), 56);
  EXPECT_EQ(j.Get("keyframe_parts_bytes")->Get("keypoints")->number(), 80);
  EXPECT_EQ(j.Get("duplicates")->Get("count")->number(), 1);
  EXPECT_EQ(j.Get("wire_overhead_bytes")->number(), 3 * 28);
  EXPECT_DOUBLE_EQ(j.Get("first_message_s")->number(), 0.5);
  EXPECT_DOUBLE_EQ(j.Get("last_message_s")->number(), 1.5);
  const Json& buckets = *j.Get("per_bucket");
  ASSERT_EQ(buckets.size(), 2u);
  EXPECT_EQ(buckets.at(0).Get("t")->number(), 0);
  EXPECT_EQ(buckets.at(0).Get("bytes")->number(), 100);
  EXPECT_EQ(buckets.at(0).Get("keyframes")->number(), 1);
  EXPECT_EQ(buckets.at(1).Get("t")->number(), 1);
  EXPECT_EQ(buckets.at(1).Get("bytes")->number(), 140);
  EXPECT_EQ(buckets.at(1).Get("keyframes")->number(), 1);
  EXPECT_EQ(buckets.at(1).Get("pose_updates")->number(), 1);
}

TEST(TrafficStatsTest, OpenSessionCountsUpToNowAndOldBucketsAreDropped) {
  TrafficStats stats({.bucket_seconds = 0.5, .max_buckets = 2}, 0.0);
  const AgentId a(1);
  stats.AgentConnected(a, "r", 1.0);
  for (double t : {1.1, 1.6, 2.1}) stats.AddDataMessage(a, 16, 10, nullptr, t);
  const Json json = stats.ToJson(5.0);
  const Json& j = json.Get("agents")->at(0);
  EXPECT_TRUE(j.Get("connected")->boolean());
  EXPECT_EQ(j.Get("connected_seconds")->number(), 4.0);
  EXPECT_EQ(j.Get("messages")->Get("keyframe")->Get("count")->number(), 3);  // totals keep all
  const Json& buckets = *j.Get("per_bucket");
  ASSERT_EQ(buckets.size(), 2u);
  EXPECT_EQ(buckets.at(0).Get("t")->number(), 1.5);
  EXPECT_EQ(buckets.at(1).Get("t")->number(), 2.0);
  // No keyframes yet: rates are null, not a division by zero.
  TrafficStats empty({}, 0.0);
  empty.AgentConnected(AgentId(2), "idle", 0.0);
  EXPECT_TRUE(empty.ToJson(0.0).Get("agents")->at(0).Get("average_keyframe_bytes")->is_null());
}

}  // namespace
}  // namespace ccmd
