#include "proto/frame.h"

#include <cstdint>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

// Bit-at-a-time CRC32C, the textbook definition, independent of the library's tables.
std::uint32_t ReferenceCrc32c(const std::uint8_t* p, std::size_t n) {
  std::uint32_t c = 0xFFFFFFFFu;
  for (std::size_t i = 0; i < n; ++i) {
    c ^= p[i];
    for (int k = 0; k < 8; ++k) c = (c >> 1) ^ ((c & 1) ? 0x82F63B78u : 0);
  }
  return ~c;
}

std::uint32_t Le32(const Bytes& b, std::size_t at) {
  return b[at] | (b[at + 1] << 8) | (b[at + 2] << 16) |
         (static_cast<std::uint32_t>(b[at + 3]) << 24);
}

void PutLe32(Bytes* b, std::size_t at, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) (*b)[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
}

// Rewrites the header CRC after a deliberate header edit, so that a later check is reached.
void ResealHeader(Bytes* frame) { PutLe32(frame, 16, ReferenceCrc32c(frame->data(), 16)); }

Bytes Payload(const std::string& s) { return Bytes(s.begin(), s.end()); }

TEST(FrameTest, HeaderLayoutByteByByte) {
  const Bytes payload = Payload("abc");
  const Bytes frame = EncodeFrame(16, 0x0102, payload);
  ASSERT_EQ(frame.size(), 20u + 3u);
  EXPECT_EQ(Bytes(frame.begin(), frame.begin() + 4), Payload("CCMD"));
  EXPECT_EQ(frame[4], 2);     // version
  EXPECT_EQ(frame[5], 16);    // type
  EXPECT_EQ(frame[6], 0x02);  // flags, little-endian
  EXPECT_EQ(frame[7], 0x01);
  EXPECT_EQ(Le32(frame, 8), 3u);  // payload length
  EXPECT_EQ(Le32(frame, 12), ReferenceCrc32c(payload.data(), 3));
  EXPECT_EQ(Le32(frame, 12), 0x364B3FB7u);  // CRC32C("abc")
  EXPECT_EQ(Le32(frame, 16), ReferenceCrc32c(frame.data(), 16));
  EXPECT_EQ(Bytes(frame.begin() + 20, frame.end()), payload);
}

TEST(FrameTest, DecodeRoundTrip) {
  const Bytes payload = Payload("keyframe bytes");
  auto frame = DecodeFrame(EncodeFrame(MessageType::kPoseUpdate, payload));
  ASSERT_TRUE(frame.ok()) << frame.status().ToString();
  EXPECT_EQ(frame->type, 17);
  EXPECT_EQ(frame->flags, 0);
  EXPECT_EQ(frame->payload, payload);
  auto empty = DecodeFrame(EncodeFrame(3, 7, {}));
  ASSERT_TRUE(empty.ok());
  EXPECT_EQ(empty->type, 3);
  EXPECT_EQ(empty->flags, 7);
  EXPECT_TRUE(empty->payload.empty());
}

TEST(FrameTest, WrongMagicVersionAndTypeAreClearErrors) {
  Bytes frame = EncodeFrame(16, 0, Payload("x"));
  Bytes bad_magic = frame;
  bad_magic[0] = 'X';
  auto s1 = DecodeFrame(bad_magic);
  EXPECT_EQ(s1.status().code(), StatusCode::kCorrupt);
  EXPECT_NE(s1.status().message().find("magic"), std::string::npos);

  Bytes bad_version = frame;
  bad_version[4] = 1;
  auto s2 = DecodeFrame(bad_version);
  EXPECT_EQ(s2.status().code(), StatusCode::kUnsupported);
  EXPECT_NE(s2.status().message().find("version 1"), std::string::npos);
  // Readers of old journals accept version 1 explicitly.
  ResealHeader(&bad_version);
  EXPECT_TRUE(DecodeFrame(bad_version, {.oldest_version = 1}).ok());
  bad_version[4] = 3;
  ResealHeader(&bad_version);
  EXPECT_EQ(DecodeFrame(bad_version, {.oldest_version = 1}).status().code(),
            StatusCode::kUnsupported);

  Bytes type_zero = frame;
  type_zero[5] = 0;
  ResealHeader(&type_zero);
  EXPECT_EQ(DecodeFrame(type_zero).status().code(), StatusCode::kCorrupt);
}

TEST(FrameTest, OversizedLengthIsRejectedFromTheHeaderAlone) {
  Bytes frame = EncodeFrame(16, 0, Payload("x"));
  PutLe32(&frame, 8, 0xFFFFFFF0u);  // claims ~4 GiB
  ResealHeader(&frame);
  const Bytes header(frame.begin(), frame.begin() + 20);
  auto h = ParseFrameHeader(header, {.max_payload_bytes = 1 << 20});
  EXPECT_EQ(h.status().code(), StatusCode::kOutOfRange);
  // The stream decoder fails after the 20 header bytes, without waiting for the payload.
  FrameDecoder decoder({.max_payload_bytes = 1 << 20});
  std::vector<Frame> frames;
  EXPECT_EQ(decoder.Feed(header, &frames).code(), StatusCode::kOutOfRange);
  EXPECT_TRUE(frames.empty());
  // At exactly the limit it is accepted.
  const Bytes at_limit = EncodeFrame(16, 0, Bytes(64, 1));
  EXPECT_TRUE(DecodeFrame(at_limit, {.max_payload_bytes = 64}).ok());
  EXPECT_EQ(DecodeFrame(at_limit, {.max_payload_bytes = 63}).status().code(),
            StatusCode::kOutOfRange);
}

TEST(FrameTest, TruncatedAndTrailingBytesAreErrors) {
  const Bytes frame = EncodeFrame(16, 0, Payload("payload"));
  for (std::size_t n = 0; n < frame.size(); ++n) {
    auto r = DecodeFrame(Bytes(frame.begin(), frame.begin() + n));
    EXPECT_EQ(r.status().code(), StatusCode::kCorrupt) << n;
  }
  Bytes longer = frame;
  longer.push_back(0);
  EXPECT_EQ(DecodeFrame(longer).status().code(), StatusCode::kCorrupt);
}

TEST(FrameTest, EverySingleBitFlipIsDetected) {
  const Bytes frame = EncodeFrame(16, 0, Payload("0123456789abcdef"));
  for (std::size_t bit = 0; bit < frame.size() * 8; ++bit) {
    Bytes flipped = frame;
    flipped[bit / 8] ^= static_cast<std::uint8_t>(1u << (bit % 8));
    EXPECT_FALSE(DecodeFrame(flipped).ok()) << "bit " << bit;
  }
  Bytes payload_flip = frame;
  payload_flip[25] ^= 0x10;
  auto r = DecodeFrame(payload_flip);
  EXPECT_EQ(r.status().code(), StatusCode::kCorrupt);
  EXPECT_NE(r.status().message().find("payload CRC"), std::string::npos);
  Bytes header_flip = frame;
  header_flip[9] ^= 0x01;  // length
  r = DecodeFrame(header_flip);
  EXPECT_EQ(r.status().code(), StatusCode::kCorrupt);
  EXPECT_NE(r.status().message().find("header CRC"), std::string::npos);
}

TEST(FrameTest, StreamDecoderHandlesAnySplit) {
  Bytes stream;
  std::vector<Bytes> payloads = {Payload("first"), {}, Bytes(1000, 0x5A), Payload("last")};
  for (std::size_t i = 0; i < payloads.size(); ++i) {
    AppendFrame(static_cast<std::uint8_t>(16 + i), static_cast<std::uint16_t>(i), payloads[i],
                &stream);
  }
  Rng rng(7);
  for (int trial = 0; trial < 50; ++trial) {
    FrameDecoder decoder;
    std::vector<Frame> frames;
    std::size_t pos = 0;
    while (pos < stream.size()) {
      // Byte by byte in the first trial, random chunk sizes afterwards.
      const std::size_t n =
          trial == 0 ? 1 : std::min<std::size_t>(stream.size() - pos, rng.UniformInt(1, 64));
      ASSERT_TRUE(decoder.Feed(ByteSpan(stream.data() + pos, n), &frames).ok());
      pos += n;
    }
    EXPECT_TRUE(decoder.Idle());
    ASSERT_EQ(frames.size(), payloads.size());
    for (std::size_t i = 0; i < payloads.size(); ++i) {
      EXPECT_EQ(frames[i].type, 16 + i);
      EXPECT_EQ(frames[i].flags, i);
      EXPECT_EQ(frames[i].payload, payloads[i]);
    }
    EXPECT_EQ(decoder.frames_decoded(), payloads.size());
    EXPECT_EQ(decoder.bytes_consumed(), stream.size());
  }
}

TEST(FrameTest, StreamDecoderReportsWhatItWantsAndStaysFailed) {
  const Bytes frame = EncodeFrame(16, 0, Payload("0123456789"));
  FrameDecoder decoder;
  std::vector<Frame> frames;
  EXPECT_EQ(decoder.BytesWanted(), 20u);
  ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data(), 5), &frames).ok());
  EXPECT_EQ(decoder.BytesWanted(), 15u);
  EXPECT_FALSE(decoder.Idle());
  ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data() + 5, 17), &frames).ok());
  EXPECT_EQ(decoder.BytesWanted(), 8u);  // 10-byte payload, 2 received
  EXPECT_TRUE(frames.empty());

  // Garbage instead of the next frame: the magic check fails on the first wrong byte.
  Bytes rest(frame.begin() + 22, frame.end());
  rest.push_back('X');
  EXPECT_EQ(decoder.Feed(rest, &frames).code(), StatusCode::kCorrupt);
  EXPECT_EQ(frames.size(), 1u);  // the frame completed before the garbage is delivered
  EXPECT_FALSE(decoder.ok());
  EXPECT_EQ(decoder.Feed(frame, &frames).code(), StatusCode::kCorrupt);  // sticky
  EXPECT_EQ(frames.size(), 1u);
}

TEST(FrameTest, StreamDecoderRejectsACorruptPayload) {
  Bytes frame = EncodeFrame(16, 0, Payload("0123456789"));
  frame.back() ^= 0x80;
  FrameDecoder decoder;
  std::vector<Frame> frames;
  const Status s = decoder.Feed(frame, &frames);
  EXPECT_EQ(s.code(), StatusCode::kCorrupt);
  EXPECT_NE(s.message().find("payload CRC"), std::string::npos);
  EXPECT_TRUE(frames.empty());
}

TEST(FrameTest, StreamDecoderBufferGrowsWithTheBytesNotTheClaim) {
  const Bytes payload(6 << 20, 0x33);
  const Bytes frame = EncodeFrame(16, 0, payload);
  FrameDecoder decoder({.max_payload_bytes = 16 << 20});
  std::vector<Frame> frames;
  // The header claims 6 MiB; 100 bytes arrive.
  ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data(), kFrameHeaderSize + 100), &frames).ok());
  EXPECT_TRUE(decoder.InFrame());
  EXPECT_LE(decoder.buffer_capacity(), 64u << 10);
  // 1 MiB more: at most twice what arrived.
  std::size_t fed = kFrameHeaderSize + 100;
  ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data() + fed, 1 << 20), &frames).ok());
  fed += 1 << 20;
  EXPECT_LE(decoder.buffer_capacity(), 2 * (fed - kFrameHeaderSize));
  ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data() + fed, frame.size() - fed), &frames).ok());
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].payload, payload);
  EXPECT_EQ(frames[0].payload.capacity(), payload.size());  // never beyond the claim
  EXPECT_FALSE(decoder.InFrame());
}

TEST(FrameTest, ATaggedFrameCarriesSixteenBytesAfterItsPayload) {
  Bytes frame = EncodeFrame(16, kFrameTagged, Payload("abc"));
  for (int i = 0; i < 16; ++i) frame.push_back(static_cast<std::uint8_t>(i));
  EXPECT_EQ(frame[7], 0x80);  // flags bit 15
  auto decoded = DecodeFrame(frame);
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  ASSERT_TRUE(decoded->tag.has_value());
  EXPECT_EQ((*decoded->tag)[15], 15);
  EXPECT_EQ(decoded->payload, Payload("abc"));
  EXPECT_EQ(Bytes(decoded->header.begin(), decoded->header.end()),
            Bytes(frame.begin(), frame.begin() + 20));
  // Byte by byte through the stream decoder, which waits for the tag too.
  FrameDecoder decoder;
  std::vector<Frame> frames;
  for (std::size_t i = 0; i + 1 < frame.size(); ++i) {
    ASSERT_TRUE(decoder.Feed(ByteSpan(frame.data() + i, 1), &frames).ok());
  }
  EXPECT_TRUE(frames.empty());
  EXPECT_EQ(decoder.BytesWanted(), 1u);
  ASSERT_TRUE(decoder.Feed(ByteSpan(&frame.back(), 1), &frames).ok());
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].tag, decoded->tag);
  // Without the tag the frame is truncated; version 1 had no tags at all.
  EXPECT_EQ(DecodeFrame(ByteSpan(frame.data(), frame.size() - 16)).status().code(),
            StatusCode::kCorrupt);
  frame[4] = 1;
  ResealHeader(&frame);
  EXPECT_EQ(DecodeFrame(frame, {.oldest_version = 1}).status().code(), StatusCode::kCorrupt);
}

}  // namespace
}  // namespace ccmd
