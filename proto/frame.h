#pragma once

// Wire framing: every message travels as one frame, a fixed 20-byte header followed by the
// payload and, in an authenticated session, a 16-byte tag. All fields little-endian (see
// proto/PROTOCOL.md for the byte-by-byte layout):
//
//   offset size field
//    0      4   magic "CCMD" (0x43 0x43 0x4D 0x44)
//    4      1   protocol version (kProtocolVersion)
//    5      1   message type (MessageType; 1..15 session control, 16.. data)
//    6      2   flags: bit 15 (kFrameTagged) = a tag follows the payload; bits 0..14 are
//               defined per message type (every type defined so far sends 0)
//    8      4   payload length in bytes
//   12      4   CRC32C of the payload
//   16      4   CRC32C of header bytes 0..15
//   20      n   payload
//   20+n   16   tag, only if flags bit 15: opaque here; libccmd/net/frame_auth.h makes and
//               checks it (a MAC over the header and payload)
//
// The header has its own CRC so that a corrupted length is caught at once, before the
// receiver waits for a payload of that size. A payload length above the receiver's limit is
// rejected from the header alone; below it, the payload buffer grows with the bytes that
// actually arrive, never with the length the header claims.
//
// Sending:   std::vector<std::uint8_t> bytes = EncodeFrame(type, 0, payload);
// Receiving from a stream (socket):
//   FrameDecoder decoder({.max_payload_bytes = 8 << 20});
//   std::vector<Frame> frames;
//   Status s = decoder.Feed(received_bytes, &frames);   // any split of the stream works
//   for (Frame& f : frames) ...;                        // complete, CRC-checked frames
//   if (!s.ok()) close the connection;                  // the decoder stays failed

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

constexpr std::uint8_t kFrameMagic[4] = {'C', 'C', 'M', 'D'};
// Version 2 added the tag (flags bit 15) and authenticated sessions. Journals written by
// version 1 stay readable (FrameLimits::oldest_version).
constexpr std::uint8_t kProtocolVersion = 2;
constexpr std::size_t kFrameHeaderSize = 20;
constexpr std::uint16_t kFrameTagged = 0x8000;
constexpr std::size_t kFrameTagSize = 16;
using FrameTag = std::array<std::uint8_t, kFrameTagSize>;
constexpr std::uint32_t kDefaultMaxPayloadBytes = 16u << 20;

// Message type numbers. 1..15 are reserved for session control (defined by the transport in
// libccmd/net and PROTOCOL.md); 16 and up carry data. 0 is never valid.
enum class MessageType : std::uint8_t {
  kKeyframe = 16,
  kPoseUpdate = 17,
};
constexpr std::uint8_t kFirstSessionMessageType = 1;
constexpr std::uint8_t kLastSessionMessageType = 15;
constexpr std::uint8_t kFirstDataMessageType = 16;

struct FrameHeader {
  std::uint8_t version = kProtocolVersion;
  std::uint8_t type = 0;
  std::uint16_t flags = 0;
  std::uint32_t payload_size = 0;
  std::uint32_t payload_crc = 0;
  bool tagged() const { return (flags & kFrameTagged) != 0; }
  // Bytes after the header: the payload and the tag, if any.
  std::size_t body_size() const { return payload_size + (tagged() ? kFrameTagSize : 0); }
};

struct Frame {
  std::uint8_t type = 0;
  std::uint16_t flags = 0;
  std::vector<std::uint8_t> payload;
  std::array<std::uint8_t, kFrameHeaderSize> header{};  // as received: the tag covers it
  std::optional<FrameTag> tag;                          // present iff flags bit 15
};

struct FrameLimits {
  // Frames announcing a larger payload are rejected (kOutOfRange) from the header alone.
  std::uint32_t max_payload_bytes = kDefaultMaxPayloadBytes;
  // Versions oldest_version..kProtocolVersion are accepted (journals: 1; the wire: current).
  std::uint8_t oldest_version = kProtocolVersion;
};

// Appends one complete frame to *out. Precondition: type != 0, payload.size() < 2^32.
void AppendFrame(std::uint8_t type, std::uint16_t flags, ByteSpan payload,
                 std::vector<std::uint8_t>* out);
std::vector<std::uint8_t> EncodeFrame(std::uint8_t type, std::uint16_t flags, ByteSpan payload);
inline std::vector<std::uint8_t> EncodeFrame(MessageType type, ByteSpan payload) {
  return EncodeFrame(static_cast<std::uint8_t>(type), 0, payload);
}

// Checks a 20-byte header, in this order: magic (kCorrupt), version (kUnsupported), header
// CRC (kCorrupt), type 0 (kCorrupt), payload length against the limit (kOutOfRange).
// Version 1 had no tag: a version-1 header with flags bit 15 set is kCorrupt.
StatusOr<FrameHeader> ParseFrameHeader(ByteSpan header, const FrameLimits& limits = {});

// Decodes exactly one whole frame, tag included (no bytes missing, none left over); for files
// and tests.
StatusOr<Frame> DecodeFrame(ByteSpan bytes, const FrameLimits& limits = {});

// Incremental decoder for a byte stream: feed bytes as they arrive, in pieces of any size.
// Memory held is at most one header plus one payload of at most the limit; the payload
// buffer is started only after its header has passed every check and grows with the bytes
// received (a header claiming 16 MiB followed by one byte holds a small buffer). A stream
// cannot be resynchronised safely after a bad frame, so the first error is sticky: every
// later Feed returns it and the connection should be closed.
class FrameDecoder {
 public:
  explicit FrameDecoder(FrameLimits limits = {}) : limits_(limits) {}

  // Consumes all of `data` and appends every frame it completes to *frames (frames decoded
  // before an error in the same call are still appended).
  Status Feed(ByteSpan data, std::vector<Frame>* frames);

  // How many more bytes complete the current header or payload (a read-size hint).
  std::size_t BytesWanted() const;
  // True when no partial frame is buffered: the stream may end here cleanly.
  bool Idle() const { return ok() && header_fill_ == 0 && !in_body_; }
  // True once a header has passed its checks and its payload (or tag) is still incomplete.
  bool InFrame() const { return in_body_; }
  bool ok() const { return error_.ok(); }
  const Status& error() const { return error_; }
  std::uint64_t frames_decoded() const { return frames_decoded_; }
  // Headers accepted so far (frames_decoded, plus one while InFrame()).
  std::uint64_t headers_accepted() const { return frames_decoded_ + (in_body_ ? 1 : 0); }
  std::uint64_t bytes_consumed() const { return bytes_consumed_; }
  // Bytes reserved for the payload in progress (grows with what arrived, not the claim).
  std::size_t buffer_capacity() const { return current_.payload.capacity(); }

 private:
  void StartBody(const FrameHeader& header);
  // Moves payload, then tag bytes from the front of `data`; returns how many it took.
  std::size_t TakeBody(ByteSpan data);
  bool BodyComplete() const;

  FrameLimits limits_;
  Status error_;
  std::uint8_t header_bytes_[kFrameHeaderSize] = {};
  std::size_t header_fill_ = 0;
  bool in_body_ = false;
  FrameHeader header_;
  Frame current_;
  std::size_t tag_fill_ = 0;
  std::uint64_t frames_decoded_ = 0;
  std::uint64_t bytes_consumed_ = 0;
};

}  // namespace ccmd
