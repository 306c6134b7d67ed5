#include "proto/messages.h"

#include <cmath>
#include <cstdint>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

OrbDescriptor FilledDescriptor(std::uint8_t value) {
  OrbDescriptor d;
  d.fill(value);
  return d;
}

// A keyframe with every kind of content: known links, new map points, unlinked keypoints.
KeyframeMessage RandomKeyframe(std::uint64_t seed, int keypoints) {
  Rng rng(seed);
  KeyframeMessage m;
  m.id = KeyframeId(1000 + static_cast<std::uint32_t>(rng.UniformInt(0, 100)));
  m.timestamp = 1305031453.359684 + rng.Uniform();
  const double qn = std::sqrt(0.1 * 0.1 + 0.2 * 0.2 + 0.3 * 0.3 + 0.9 * 0.9);
  m.T_world_cam.q_xyzw = {0.1 / qn, -0.2 / qn, 0.3 / qn, 0.9 / qn};
  m.T_world_cam.t = {1.25, -3.5, 0.123456789};
  m.parent = KeyframeId(m.id.value() - 1);
  std::uint32_t next_new_point = 50000;
  for (int i = 0; i < keypoints; ++i) {
    WireKeypoint k;
    k.u = static_cast<float>(rng.Uniform(-5.0, 645.0));
    k.v = static_cast<float>(rng.Uniform(-5.0, 485.0));
    k.octave = static_cast<std::uint8_t>(rng.UniformInt(0, 7));
    k.angle_deg = static_cast<float>(rng.Uniform(-10.0, 370.0));
    k.depth_m = rng.Bernoulli(0.1) ? 0.0f : static_cast<float>(rng.Uniform(0.3, 8.0));
    for (auto& b : k.descriptor) b = static_cast<std::uint8_t>(rng.Next());
    const double kind = rng.Uniform();
    if (kind < 0.6) {
      k.map_point = MapPointId(static_cast<std::uint32_t>(rng.UniformInt(0, 49999)));
    } else if (kind < 0.8) {
      NewMapPoint p;
      p.id = MapPointId(next_new_point++);
      p.p_cam = {static_cast<float>(rng.Uniform(-3, 3)), static_cast<float>(rng.Uniform(-3, 3)),
                 static_cast<float>(rng.Uniform(0.3, 30))};
      p.descriptor = k.descriptor;
      m.new_map_points.push_back(p);
      k.map_point = p.id;
    }
    m.keypoints.push_back(k);
  }
  for (int i = 1; i <= 5; ++i) {
    m.covisibility.push_back({KeyframeId(m.id.value() - i), static_cast<std::uint32_t>(200 / i)});
  }
  return m;
}

double AngleDifference(double a, double b) {
  double d = std::fmod(std::fabs(a - b), 360.0);
  return std::min(d, 360.0 - d);
}

// |float(x) - x| <= |x| * 2^-24 (round to nearest, 24-bit significand).
void ExpectFloatRounded(double original, double back) {
  EXPECT_LE(std::fabs(back - original), std::fabs(original) * std::ldexp(1.0, -24));
}

TEST(MessagesTest, KeyframeRoundTripIsExactOrWithinTheStatedQuantisation) {
  KeyframeMessage m = RandomKeyframe(3, 400);
  m.rgbd = RgbdPayload{2, 3, Bytes{0xFF, 0xD8, 1, 2, 3}, Bytes(100, 7)};
  auto bytes = SerializeKeyframe(m);
  ASSERT_TRUE(bytes.ok()) << bytes.status().ToString();
  auto back = ParseKeyframe(*bytes);
  ASSERT_TRUE(back.ok()) << back.status().ToString();

  EXPECT_EQ(back->id, m.id);
  EXPECT_EQ(back->timestamp, m.timestamp);
  EXPECT_EQ(back->parent, m.parent);
  for (int i = 0; i < 4; ++i)
    ExpectFloatRounded(m.T_world_cam.q_xyzw[i], back->T_world_cam.q_xyzw[i]);
  for (int i = 0; i < 3; ++i) ExpectFloatRounded(m.T_world_cam.t[i], back->T_world_cam.t[i]);

  ASSERT_EQ(back->keypoints.size(), m.keypoints.size());
  for (std::size_t i = 0; i < m.keypoints.size(); ++i) {
    const WireKeypoint& a = m.keypoints[i];
    const WireKeypoint& b = back->keypoints[i];
    EXPECT_LE(std::fabs(a.u - b.u), 1.0 / 16.0 + 1e-4);  // 1/8 px steps
    EXPECT_LE(std::fabs(a.v - b.v), 1.0 / 16.0 + 1e-4);
    EXPECT_EQ(a.octave, b.octave);
    EXPECT_LE(AngleDifference(a.angle_deg, b.angle_deg), 360.0 / 512.0 + 1e-4);
    if (a.depth_m <= 0) {
      EXPECT_EQ(b.depth_m, 0.0f);
    } else {
      EXPECT_LE(std::fabs(a.depth_m - b.depth_m), 0.0005 + 1e-6);
    }
    EXPECT_EQ(a.map_point, b.map_point);
    if (!a.map_point) {
      EXPECT_EQ(a.descriptor, b.descriptor);
    } else {
      EXPECT_EQ(b.descriptor, OrbDescriptor{});  // not sent
    }
  }
  ASSERT_EQ(back->new_map_points.size(), m.new_map_points.size());
  for (std::size_t i = 0; i < m.new_map_points.size(); ++i) {
    EXPECT_EQ(back->new_map_points[i].id, m.new_map_points[i].id);
    EXPECT_EQ(back->new_map_points[i].descriptor, m.new_map_points[i].descriptor);
    for (int c = 0; c < 3; ++c) {
      EXPECT_LE(std::fabs(back->new_map_points[i].p_cam[c] - m.new_map_points[i].p_cam[c]),
                0.0005 + 1e-5);
    }
  }
  ASSERT_EQ(back->covisibility.size(), m.covisibility.size());
  for (std::size_t i = 0; i < m.covisibility.size(); ++i) {
    EXPECT_EQ(back->covisibility[i].keyframe, m.covisibility[i].keyframe);
    EXPECT_EQ(back->covisibility[i].weight, m.covisibility[i].weight);
  }
  ASSERT_TRUE(back->rgbd.has_value());
  EXPECT_EQ(back->rgbd->downsample, 2);
  EXPECT_EQ(back->rgbd->depth_mode, 3);
  EXPECT_EQ(back->rgbd->colour_jpeg, m.rgbd->colour_jpeg);
  EXPECT_EQ(back->rgbd->depth, m.rgbd->depth);

  // A second pass through the wire changes nothing (the quantised values are fixed points).
  auto again = SerializeKeyframe(*back);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(*again, *bytes);
}

// The layout of PROTOCOL.md, byte by byte, for a small hand-built keyframe.
TEST(MessagesTest, KeyframeLayoutByteByByte) {
  KeyframeMessage m;
  m.id = KeyframeId(5);
  m.timestamp = 1.5;  // f64 0x3FF8000000000000
  m.parent = KeyframeId(4);
  WireKeypoint linked;
  linked.u = 10.5f;   // 84 eighths = 0x0054
  linked.v = 20.25f;  // 162 = 0x00A2
  linked.octave = 2;
  linked.angle_deg = 90;    // 64 of 256
  linked.depth_m = 1.234f;  // 1234 mm = 0x04D2
  linked.map_point = MapPointId(300);
  WireKeypoint unlinked;
  unlinked.u = -1.0f;  // -8 = 0xFFF8
  unlinked.v = 0.0f;
  unlinked.descriptor = FilledDescriptor(0xCD);
  m.keypoints = {linked, unlinked};
  m.new_map_points.push_back({MapPointId(300), {0.1f, -0.2f, 1.5f}, FilledDescriptor(0xAB)});
  m.covisibility.push_back({KeyframeId(4), 120});

  Bytes expected = {0x01,                                            // flags: has parent
                    0x05,                                            // id
                    0,    0,    0,    0,    0,    0,    0xF8, 0x3F,  // timestamp
                    0,    0,    0,    0,    0,    0,    0,    0,    0, 0, 0, 0,
                    0,    0,    0x80, 0x3F,                                      // q = (0,0,0,1)
                    0,    0,    0,    0,    0,    0,    0,    0,    0, 0, 0, 0,  // t = 0
                    0x01,                                            // parent: zigzag(-1)
                    0x02,                                            // 2 keypoints
                    0x54, 0x00, 0xA2, 0x00, 0x02, 0x40, 0xD2, 0x04,  // keypoint 0
                    0xF8, 0xFF, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,  // keypoint 1
                    0xD9, 0x04,               // link 1 + zigzag(300) = 601 = varint D9 04
                    0x00};                    // no link
  expected.insert(expected.end(), 32, 0xCD);  // descriptor of the unlinked keypoint
  const Bytes tail = {0x01,                   // 1 new map point
                      0xD8, 0x04,             // zigzag(300 - 0) = 600
                      0x64, 0x00,             // x = 100 mm
                      0x38, 0xFF,             // y = -200 mm
                      0xDC, 0x05};            // z = 1500 mm
  expected.insert(expected.end(), tail.begin(), tail.end());
  expected.insert(expected.end(), 32, 0xAB);
  const Bytes covis = {0x01, 0x01, 0x78};  // 1 link: zigzag(4 - 5) = 1, weight 120
  expected.insert(expected.end(), covis.begin(), covis.end());

  KeyframeSizeBreakdown b;
  auto bytes = SerializeKeyframe(m, &b);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(*bytes, expected);
  EXPECT_EQ(b.total(), expected.size());
  EXPECT_EQ(b.pose, 28u);
  EXPECT_EQ(b.keypoints, 16u);
  EXPECT_EQ(b.descriptors, 64u);
  EXPECT_EQ(b.map_points, 3u + 8u);  // links + (id, position)
  EXPECT_EQ(b.colour + b.depth, 0u);
  EXPECT_EQ(b.other, 1u + 1u + 8u + 1u + 1u + 1u + 3u);
}

TEST(MessagesTest, LinkedKeypointsSendNoDescriptor) {
  KeyframeMessage m = RandomKeyframe(5, 100);
  for (auto& k : m.keypoints) k.map_point.reset();
  m.new_map_points.clear();
  KeyframeSizeBreakdown all_unlinked;
  ASSERT_TRUE(SerializeKeyframe(m, &all_unlinked).ok());
  EXPECT_EQ(all_unlinked.descriptors, 100u * 32u);
  // Link every keypoint to consecutive known map points: one-byte links, no descriptors.
  for (std::size_t i = 0; i < m.keypoints.size(); ++i) {
    m.keypoints[i].map_point = MapPointId(7000 + static_cast<std::uint32_t>(i));
  }
  KeyframeSizeBreakdown all_linked;
  auto bytes = SerializeKeyframe(m, &all_linked);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(all_linked.descriptors, 0u);
  // The first link is 1 + zigzag(7000) = 14001 < 2^14: 2 bytes; then deltas of 1: 1 byte.
  EXPECT_EQ(all_linked.map_points, 2u + 99u);
  EXPECT_EQ(all_unlinked.total() - all_linked.total(), 100u * 32u + 100u - (2u + 99u));
}

// The case issue 8 budgets for: 1000 keypoints, 700 of them on map points the server has,
// 150 on new map points, 150 unlinked.
TEST(MessagesTest, TypicalKeyframeSizeMatchesTheFormula) {
  KeyframeMessage m;
  m.id = KeyframeId(40);
  m.parent = KeyframeId(39);
  for (int i = 0; i < 1000; ++i) {
    WireKeypoint k;
    k.u = 320;
    k.v = 240;
    k.depth_m = 2;
    if (i < 700) {
      k.map_point = MapPointId(10 * i);  // deltas of 10: one-byte links
    } else if (i < 850) {
      NewMapPoint p{MapPointId(20000 + i), {0.5f, 0.5f, 2.0f}, {}};
      m.new_map_points.push_back(p);
      k.map_point = p.id;
    }
    m.keypoints.push_back(k);
  }
  KeyframeSizeBreakdown b;
  auto bytes = SerializeKeyframe(m, &b);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(b.keypoints, 8000u);
  EXPECT_EQ(b.descriptors, 300u * 32u);  // 150 unlinked + 150 new map points
  // Links: 1 byte each except the jump from id 6990 to 20700 (zigzag(13710)+1 = 27421: 3
  // bytes); new map points: 1-byte id delta except the first (zigzag(20700): 3 bytes) + 6.
  EXPECT_EQ(b.map_points, (1000u + 2u) + (150u * 7u + 2u));
  EXPECT_EQ(b.pose, 28u);
  // flags 1, id 1, timestamp 8, parent 1, N = 1000 (2), M = 150 (2), C = 0 (1).
  EXPECT_EQ(b.other, 16u);
  EXPECT_EQ(bytes->size(), 8000u + 9600u + 2054u + 28u + 16u);
}

TEST(MessagesTest, FarMapPointsUseTheFloatEscape) {
  KeyframeMessage m;
  m.new_map_points.push_back({MapPointId(1), {0.0f, 0.0f, 32.767f}, {}});  // fits int16 mm
  m.new_map_points.push_back({MapPointId(2), {0.0f, 0.0f, 32.768f}, {}});  // 32768 mm: no
  m.new_map_points.push_back({MapPointId(3), {-45.25f, 1.0f, 100.5f}, {}});
  KeyframeSizeBreakdown b;
  auto bytes = SerializeKeyframe(m, &b);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(b.map_points, 3u * 1u + 6u + 14u + 14u);
  auto back = ParseKeyframe(*bytes);
  ASSERT_TRUE(back.ok());
  EXPECT_NEAR(back->new_map_points[0].p_cam[2], 32.767f, 1e-6);
  EXPECT_EQ(back->new_map_points[1].p_cam[2], 32.768f);  // exact float
  EXPECT_EQ(back->new_map_points[2].p_cam[0], -45.25f);
  EXPECT_EQ(back->new_map_points[2].p_cam[2], 100.5f);
}

TEST(MessagesTest, SerializeRejectsValuesTheFormatCannotCarry) {
  KeyframeMessage m;
  WireKeypoint k;
  k.u = 4096.0f;
  m.keypoints = {k};
  EXPECT_EQ(SerializeKeyframe(m).status().code(), StatusCode::kInvalidArgument);
  m.keypoints[0].u = -4096.0f;
  EXPECT_TRUE(SerializeKeyframe(m).ok());
  m.keypoints[0].v = NAN;
  EXPECT_EQ(SerializeKeyframe(m).status().code(), StatusCode::kInvalidArgument);
  m.keypoints.clear();
  m.rgbd = RgbdPayload{3, 0, {}, {}};
  EXPECT_EQ(SerializeKeyframe(m).status().code(), StatusCode::kInvalidArgument);
  m.rgbd.reset();
  m.T_world_cam.t[1] = INFINITY;
  EXPECT_EQ(SerializeKeyframe(m).status().code(), StatusCode::kInvalidArgument);
}

TEST(MessagesTest, EveryTruncationIsAnErrorAndTrailingBytesToo) {
  KeyframeMessage m = RandomKeyframe(11, 30);
  m.rgbd = RgbdPayload{4, 1, Bytes(20, 1), Bytes(30, 2)};
  const Bytes bytes = *SerializeKeyframe(m);
  for (std::size_t n = 0; n < bytes.size(); ++n) {
    auto r = ParseKeyframe(ByteSpan(bytes.data(), n));
    ASSERT_FALSE(r.ok()) << n;
    EXPECT_EQ(r.status().code(), StatusCode::kCorrupt) << n << " " << r.status().ToString();
  }
  Bytes longer = bytes;
  longer.push_back(0);
  EXPECT_EQ(ParseKeyframe(longer).status().code(), StatusCode::kCorrupt);
}

TEST(MessagesTest, HugeCountsAreRejectedBeforeAllocating) {
  // flags, id, timestamp, identity pose, then a keypoint count of 2^32 - 1.
  Bytes bytes = {0x00, 0x01, 0, 0, 0, 0, 0, 0, 0, 0};
  for (int i = 0; i < 28; ++i) bytes.push_back(0);
  const Bytes huge = {0xFF, 0xFF, 0xFF, 0xFF, 0x0F};
  Bytes over_limit = bytes;
  over_limit.insert(over_limit.end(), huge.begin(), huge.end());
  EXPECT_EQ(ParseKeyframe(over_limit).status().code(), StatusCode::kOutOfRange);
  // Within the limit but more than the bytes present.
  Bytes too_many = bytes;
  too_many.push_back(0x64);  // 100 keypoints, no bytes follow
  EXPECT_EQ(ParseKeyframe(too_many).status().code(), StatusCode::kCorrupt);
  MessageLimits tight;
  tight.max_keypoints = 50;
  EXPECT_EQ(ParseKeyframe(too_many, tight).status().code(), StatusCode::kOutOfRange);

  Bytes pose_updates = {0xFF, 0xFF, 0xFF, 0xFF, 0x0F};
  EXPECT_EQ(ParsePoseUpdate(pose_updates).status().code(), StatusCode::kOutOfRange);
}

TEST(MessagesTest, UnknownFlagsAndBadFieldsAreCorrupt) {
  const Bytes bytes = *SerializeKeyframe(RandomKeyframe(2, 10));
  Bytes flags = bytes;
  flags[0] |= 0x80;
  EXPECT_EQ(ParseKeyframe(flags).status().code(), StatusCode::kCorrupt);

  KeyframeMessage m;
  m.rgbd = RgbdPayload{2, 0, {}, {}};
  Bytes rgbd = *SerializeKeyframe(m);
  // flags(1) id(1) timestamp(8) pose(28) keypoints(1) new points(1) covisibility(1): then
  // the downsample byte.
  ASSERT_EQ(rgbd[41], 2);
  rgbd[41] = 3;
  EXPECT_EQ(ParseKeyframe(rgbd).status().code(), StatusCode::kCorrupt);
}

// The restart mark is flag bit 3, a reset bit 4 with it: they cost no byte, come back as sent,
// a reset without a restart is corrupt, and bits 5-7 stay unknown.
TEST(MessagesTest, TheRestartMarkIsFlagBitThree) {
  KeyframeMessage m = RandomKeyframe(6, 20);
  const Bytes plain = *SerializeKeyframe(m);
  EXPECT_EQ(plain[0] & 0x08, 0);
  EXPECT_FALSE(ParseKeyframe(plain)->restart);
  m.restart = true;
  const Bytes marked = *SerializeKeyframe(m);
  EXPECT_EQ(marked[0], plain[0] | 0x08);
  EXPECT_TRUE(std::equal(plain.begin() + 1, plain.end(), marked.begin() + 1, marked.end()));
  auto back = ParseKeyframe(marked);
  ASSERT_TRUE(back.ok()) << back.status().ToString();
  EXPECT_TRUE(back->restart);
  EXPECT_FALSE(back->reset);
  EXPECT_EQ(back->parent, m.parent);
  m.reset = true;
  const Bytes reset = *SerializeKeyframe(m);
  EXPECT_EQ(reset[0], plain[0] | 0x18);
  EXPECT_TRUE(ParseKeyframe(reset)->reset);
  Bytes reset_alone = reset;
  reset_alone[0] &= ~0x08;
  EXPECT_EQ(ParseKeyframe(reset_alone).status().code(), StatusCode::kCorrupt);
  Bytes unknown = marked;
  unknown[0] |= 0x20;
  EXPECT_EQ(ParseKeyframe(unknown).status().code(), StatusCode::kCorrupt);
}

// Depth links: flag bit 2, then a count and per link the keyframe delta, pose and 21 float32s;
// the values come back as float32, and a keyframe without links has no section at all.
TEST(MessagesTest, DepthLinksRoundTripAndCostTheirBytes) {
  KeyframeMessage m = RandomKeyframe(5, 20);
  const Bytes without = *SerializeKeyframe(m);
  EXPECT_EQ(without[0] & 0x04, 0);
  DepthLink link;
  link.keyframe = KeyframeId(m.id.value() - 3);
  link.T_this_other.q_xyzw = {0, 0, std::sin(0.05), std::cos(0.05)};
  link.T_this_other.t = {0.1, -0.02, 0.3};
  for (int i = 0; i < 21; ++i) link.information[i] = 1000.0f * (i + 1) + 0.125f;
  m.depth_links = {link, link};
  m.depth_links[1].keyframe = KeyframeId(m.id.value() - 1);
  const Bytes with = *SerializeKeyframe(m);
  EXPECT_EQ(with[0] & 0x04, 0x04);
  EXPECT_EQ(with.size(), without.size() + 1 + 2 * (1 + 28 + 21 * 4));
  auto back = ParseKeyframe(with);
  ASSERT_TRUE(back.ok()) << back.status().ToString();
  ASSERT_EQ(back->depth_links.size(), 2u);
  EXPECT_EQ(back->depth_links[0].keyframe, link.keyframe);
  EXPECT_EQ(back->depth_links[1].keyframe, KeyframeId(m.id.value() - 1));
  for (int i = 0; i < 21; ++i) EXPECT_EQ(back->depth_links[0].information[i], link.information[i]);
  for (int i = 0; i < 3; ++i)
    ExpectFloatRounded(link.T_this_other.t[i], back->depth_links[0].T_this_other.t[i]);
  EXPECT_EQ(back->keypoints.size(), m.keypoints.size());
  // Every truncation of the section is an error; a non-finite value cannot be sent.
  for (std::size_t n = without.size() - 1; n < with.size(); ++n) {
    EXPECT_EQ(ParseKeyframe(ByteSpan(with.data(), n)).status().code(), StatusCode::kCorrupt) << n;
  }
  m.depth_links[0].information[7] = std::nanf("");
  EXPECT_EQ(SerializeKeyframe(m).status().code(), StatusCode::kInvalidArgument);
}

TEST(MessagesTest, RandomBitFlipsNeverCrash) {
  const Bytes bytes = *SerializeKeyframe(RandomKeyframe(9, 50));
  Rng rng(99);
  int rejected = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    Bytes flipped = bytes;
    const int flips = rng.UniformInt(1, 4);
    for (int f = 0; f < flips; ++f) {
      const std::size_t bit =
          static_cast<std::size_t>(rng.UniformInt(0, static_cast<int>(bytes.size()) * 8 - 1));
      flipped[bit / 8] ^= static_cast<std::uint8_t>(1u << (bit % 8));
    }
    if (!ParseKeyframe(flipped).ok()) ++rejected;
  }
  // Flips in descriptors or coordinates give another valid message (the frame CRC catches
  // those); flips in counts, links and varints must be caught here.
  EXPECT_GT(rejected, 100);
}

TEST(MessagesTest, PoseUpdateRoundTripAndLayout) {
  PoseUpdateMessage m;
  m.entries.push_back({KeyframeId(3), WirePose{{0, 0, 0, 1}, {1, 2, 3}}});
  m.entries.push_back({KeyframeId(1), WirePose{{0.6, 0, 0, 0.8}, {-0.1, 0.2, 5e6}}});
  auto bytes = SerializePoseUpdate(m);
  ASSERT_TRUE(bytes.ok());
  ASSERT_EQ(bytes->size(), 1u + 2u * (1u + 28u));
  EXPECT_EQ((*bytes)[0], 2);   // count
  EXPECT_EQ((*bytes)[1], 6);   // zigzag(3)
  EXPECT_EQ((*bytes)[30], 3);  // zigzag(1 - 3) = zigzag(-2)
  auto back = ParsePoseUpdate(*bytes);
  ASSERT_TRUE(back.ok());
  ASSERT_EQ(back->entries.size(), 2u);
  EXPECT_EQ(back->entries[0].keyframe, KeyframeId(3));
  EXPECT_EQ(back->entries[1].keyframe, KeyframeId(1));
  for (std::size_t e = 0; e < 2; ++e) {
    for (int i = 0; i < 4; ++i) {
      ExpectFloatRounded(m.entries[e].T_world_cam.q_xyzw[i],
                         back->entries[e].T_world_cam.q_xyzw[i]);
    }
    for (int i = 0; i < 3; ++i) {
      ExpectFloatRounded(m.entries[e].T_world_cam.t[i], back->entries[e].T_world_cam.t[i]);
    }
  }
  for (std::size_t n = 0; n < bytes->size(); ++n) {
    EXPECT_FALSE(ParsePoseUpdate(ByteSpan(bytes->data(), n)).ok());
  }
  // An id below zero is corrupt.
  Bytes negative = *bytes;
  negative[1] = 1;  // zigzag(-1) as the first id
  EXPECT_EQ(ParsePoseUpdate(negative).status().code(), StatusCode::kCorrupt);
}

TEST(MessagesTest, SingleValueQuantisers) {
  EXPECT_EQ(QuantizePixel(10.5f), 84);
  EXPECT_EQ(QuantizePixel(-0.0624f), 0);
  EXPECT_EQ(QuantizePixel(0.0625f), 1);  // half a step rounds away from zero
  EXPECT_EQ(QuantizeAngle(0.0f), 0);
  EXPECT_EQ(QuantizeAngle(359.5f), 0);  // 255.64 rounds to 256 = 0 (wraps)
  EXPECT_EQ(QuantizeAngle(-90.0f), 192);
  EXPECT_EQ(QuantizeAngle(45.0f), 32);
  EXPECT_FLOAT_EQ(DequantizeAngle(32), 45.0f);
  EXPECT_EQ(QuantizeDepthMm(1.2344f), 1234);
  EXPECT_EQ(QuantizeDepthMm(0.0f), 0);
  EXPECT_EQ(QuantizeDepthMm(-1.0f), 0);
  EXPECT_EQ(QuantizeDepthMm(65.535f), 65535);
  EXPECT_EQ(QuantizeDepthMm(65.6f), 0);  // beyond 16 bits: no depth
}

}  // namespace
}  // namespace ccmd
