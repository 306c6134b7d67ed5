// Fuzz target: the stream frame decoder and the whole-frame decoder, tagged frames
// (protocol version 2) included.

#include <algorithm>

#include "proto/frame.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

namespace {

std::vector<std::uint8_t> Tagged(std::uint8_t type, std::vector<std::uint8_t> payload) {
  std::vector<std::uint8_t> frame = EncodeFrame(type, kFrameTagged, payload);
  for (std::size_t i = 0; i < kFrameTagSize; ++i) frame.push_back(static_cast<std::uint8_t>(i));
  return frame;
}

}  // namespace

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  std::vector<std::uint8_t> two;
  AppendFrame(16, 0, std::vector<std::uint8_t>(40, 7), &two);
  AppendFrame(3, 2, {}, &two);
  std::vector<std::uint8_t> tagged = Tagged(16, std::vector<std::uint8_t>(60, 9));
  const std::vector<std::uint8_t> empty = Tagged(7, {});
  tagged.insert(tagged.end(), empty.begin(), empty.end());
  return {EncodeFrame(17, 0, std::vector<std::uint8_t>{1, 2, 3}), two,
          EncodeFrame(16, 0, std::vector<std::uint8_t>(300, 0xAB)), tagged,
          Tagged(5, std::vector<std::uint8_t>(8, 1))};
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const FrameLimits limits{.max_payload_bytes = 1u << 16};
  if (StatusOr<Frame> f = DecodeFrame(ByteSpan(data, size), limits); f.ok()) {
    if (f->tag.has_value() != ((f->flags & kFrameTagged) != 0)) fuzz::FuzzFail("tag flag");
    const std::size_t expected =
        kFrameHeaderSize + f->payload.size() + (f->tag ? kFrameTagSize : 0);
    if (expected != size) fuzz::FuzzFail("whole frame size");
  }
  // The stream decoder, fed in chunks whose sizes come from the input itself.
  FrameDecoder decoder(limits);
  std::vector<Frame> frames;
  std::size_t pos = 0, chunk = 1;
  while (pos < size) {
    const std::size_t n = std::min(size - pos, chunk);
    const Status s = decoder.Feed(ByteSpan(data + pos, n), &frames);
    pos += n;
    chunk = 1 + data[pos - 1] % 97;
    // Memory follows the bytes that arrived, never the length a header claims.
    if (decoder.buffer_capacity() > std::max<std::size_t>(64 << 10, 2 * pos)) {
      fuzz::FuzzFail("payload buffer beyond what arrived");
    }
    if (!s.ok()) {
      // Sticky: a failed decoder refuses everything afterwards.
      if (decoder.Feed(ByteSpan(data, size), &frames).ok()) fuzz::FuzzFail("decoder not sticky");
      break;
    }
  }
  std::size_t consumed = 0;
  for (const Frame& f : frames) {
    if (f.payload.size() > limits.max_payload_bytes) fuzz::FuzzFail("payload over the limit");
    if (f.tag.has_value() != ((f.flags & kFrameTagged) != 0)) fuzz::FuzzFail("stream tag flag");
    consumed += kFrameHeaderSize + f.payload.size() + (f.tag ? kFrameTagSize : 0);
  }
  if (consumed > decoder.bytes_consumed()) fuzz::FuzzFail("frames larger than the input");
  return 0;
}
