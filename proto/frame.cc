#include "proto/frame.h"

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <string>

#include "proto/crc32c.h"

namespace ccmd {
namespace {

// What a payload buffer starts with, whatever the header claims.
constexpr std::size_t kInitialPayloadReserve = 64 << 10;

std::string Hex32(std::uint32_t v) {
  char text[16];
  std::snprintf(text, sizeof(text), "0x%08X", v);
  return text;
}

}  // namespace

void AppendFrame(std::uint8_t type, std::uint16_t flags, ByteSpan payload,
                 std::vector<std::uint8_t>* out) {
  ByteWriter w(kFrameHeaderSize);
  w.PutBytes(kFrameMagic, sizeof(kFrameMagic));
  w.PutU8(kProtocolVersion);
  w.PutU8(type);
  w.PutU16(flags);
  w.PutU32(static_cast<std::uint32_t>(payload.size()));
  w.PutU32(Crc32c(payload));
  w.PutU32(Crc32c(w.data(), 16));
  out->reserve(out->size() + kFrameHeaderSize + payload.size());
  out->insert(out->end(), w.data(), w.data() + w.size());
  out->insert(out->end(), payload.begin(), payload.end());
}

std::vector<std::uint8_t> EncodeFrame(std::uint8_t type, std::uint16_t flags, ByteSpan payload) {
  std::vector<std::uint8_t> out;
  AppendFrame(type, flags, payload, &out);
  return out;
}

StatusOr<FrameHeader> ParseFrameHeader(ByteSpan header, const FrameLimits& limits) {
  if (header.size() < kFrameHeaderSize) {
    return Corrupt("truncated frame header: " + std::to_string(header.size()) + " of " +
                   std::to_string(kFrameHeaderSize) + " bytes");
  }
  if (std::memcmp(header.data(), kFrameMagic, sizeof(kFrameMagic)) != 0) {
    std::uint32_t got = 0;
    for (int i = 0; i < 4; ++i) got = (got << 8) | header[i];
    return Corrupt("bad frame magic " + Hex32(got) + " (expected \"CCMD\")");
  }
  ByteReader r(header.subspan(4, kFrameHeaderSize - 4));
  FrameHeader h;
  std::uint32_t header_crc = 0;
  // The header is exactly 20 bytes here, so none of these reads can fail.
  r.ReadU8(&h.version).IgnoreError();
  r.ReadU8(&h.type).IgnoreError();
  r.ReadU16(&h.flags).IgnoreError();
  r.ReadU32(&h.payload_size).IgnoreError();
  r.ReadU32(&h.payload_crc).IgnoreError();
  r.ReadU32(&header_crc).IgnoreError();
  if (h.version < limits.oldest_version || h.version > kProtocolVersion) {
    return Unsupported("protocol version " + std::to_string(h.version) +
                       " is not supported (this build speaks version " +
                       std::to_string(kProtocolVersion) + ")");
  }
  const std::uint32_t computed = Crc32c(header.data(), 16);
  if (computed != header_crc) {
    return Corrupt("frame header CRC mismatch (stored " + Hex32(header_crc) + ", computed " +
                   Hex32(computed) + ")");
  }
  if (h.type == 0) return Corrupt("frame has message type 0");
  if (h.version == 1 && h.tagged()) return Corrupt("version 1 frame with the tag flag");
  if (h.payload_size > limits.max_payload_bytes) {
    return OutOfRange("frame payload of " + std::to_string(h.payload_size) +
                      " bytes exceeds the limit of " + std::to_string(limits.max_payload_bytes));
  }
  return h;
}

namespace {

Status CheckPayloadCrc(const FrameHeader& h, ByteSpan payload) {
  const std::uint32_t computed = Crc32c(payload);
  if (computed != h.payload_crc) {
    return Corrupt("frame payload CRC mismatch (type " + std::to_string(h.type) + ", " +
                   std::to_string(h.payload_size) + " bytes, stored " + Hex32(h.payload_crc) +
                   ", computed " + Hex32(computed) + ")");
  }
  return Status::Ok();
}

}  // namespace

StatusOr<Frame> DecodeFrame(ByteSpan bytes, const FrameLimits& limits) {
  CCMD_ASSIGN_OR_RETURN(const FrameHeader h, ParseFrameHeader(bytes, limits));
  const std::size_t total = kFrameHeaderSize + h.body_size();
  if (bytes.size() < total) {
    return Corrupt("truncated frame: " + std::to_string(bytes.size()) + " of " +
                   std::to_string(total) + " bytes");
  }
  if (bytes.size() > total) {
    return Corrupt(std::to_string(bytes.size() - total) + " bytes after the end of the frame");
  }
  const ByteSpan payload = bytes.subspan(kFrameHeaderSize, h.payload_size);
  CCMD_RETURN_IF_ERROR(CheckPayloadCrc(h, payload));
  Frame frame;
  frame.type = h.type;
  frame.flags = h.flags;
  frame.payload.assign(payload.begin(), payload.end());
  std::copy_n(bytes.begin(), kFrameHeaderSize, frame.header.begin());
  if (h.tagged()) {
    frame.tag.emplace();
    std::copy_n(bytes.begin() + kFrameHeaderSize + h.payload_size, kFrameTagSize,
                frame.tag->begin());
  }
  return frame;
}

Status FrameDecoder::Feed(ByteSpan data, std::vector<Frame>* frames) {
  if (!error_.ok()) return error_;
  std::size_t pos = 0;
  while (pos < data.size()) {
    if (!in_body_) {
      const std::size_t take = std::min(kFrameHeaderSize - header_fill_, data.size() - pos);
      std::memcpy(header_bytes_ + header_fill_, data.data() + pos, take);
      header_fill_ += take;
      pos += take;
      bytes_consumed_ += take;
      // Check the magic as soon as its bytes are in, so garbage fails fast.
      const std::size_t magic_have = std::min(header_fill_, sizeof(kFrameMagic));
      if (std::memcmp(header_bytes_, kFrameMagic, magic_have) != 0) {
        error_ = Corrupt("bad frame magic at stream offset " +
                         std::to_string(bytes_consumed_ - header_fill_) +
                         " (not a CCMD stream, or out of step)");
        return error_;
      }
      if (header_fill_ < kFrameHeaderSize) break;
      StatusOr<FrameHeader> h =
          ParseFrameHeader(ByteSpan(header_bytes_, kFrameHeaderSize), limits_);
      if (!h.ok()) {
        error_ = h.status();
        return error_;
      }
      StartBody(*h);
    }
    const std::size_t took = TakeBody(data.subspan(pos));
    pos += took;
    bytes_consumed_ += took;
    if (!BodyComplete()) break;
    Status crc = CheckPayloadCrc(header_, current_.payload);
    if (!crc.ok()) {
      error_ = crc;
      return error_;
    }
    frames->push_back(std::move(current_));
    current_ = Frame{};
    ++frames_decoded_;
    in_body_ = false;
    header_fill_ = 0;
  }
  return Status::Ok();
}

void FrameDecoder::StartBody(const FrameHeader& header) {
  header_ = header;
  current_ = Frame{};
  current_.type = header_.type;
  current_.flags = header_.flags;
  std::memcpy(current_.header.data(), header_bytes_, kFrameHeaderSize);
  if (header_.tagged()) current_.tag.emplace();
  // Start small whatever the header claims: the buffer grows with what arrives.
  current_.payload.reserve(std::min<std::size_t>(header_.payload_size, kInitialPayloadReserve));
  tag_fill_ = 0;
  in_body_ = true;
}

std::size_t FrameDecoder::TakeBody(ByteSpan data) {
  std::vector<std::uint8_t>& payload = current_.payload;
  const std::size_t want = header_.payload_size - payload.size();
  const std::size_t take = std::min(want, data.size());
  if (take > 0) {
    if (payload.capacity() < payload.size() + take) {
      // Double, but never beyond the claimed size: memory stays within twice what arrived.
      payload.reserve(std::min<std::size_t>(
          header_.payload_size, std::max(payload.size() + take, 2 * payload.capacity())));
    }
    payload.insert(payload.end(), data.begin(), data.begin() + take);
  }
  std::size_t took = take;
  if (current_.tag && payload.size() == header_.payload_size) {
    const std::size_t tag_take = std::min(kFrameTagSize - tag_fill_, data.size() - took);
    std::memcpy(current_.tag->data() + tag_fill_, data.data() + took, tag_take);
    tag_fill_ += tag_take;
    took += tag_take;
  }
  return took;
}

bool FrameDecoder::BodyComplete() const {
  return current_.payload.size() == header_.payload_size &&
         (!current_.tag || tag_fill_ == kFrameTagSize);
}

std::size_t FrameDecoder::BytesWanted() const {
  if (!in_body_) return kFrameHeaderSize - header_fill_;
  return header_.body_size() - current_.payload.size() - tag_fill_;
}

}  // namespace ccmd
