// Fuzz target: the stream frame decoder and the whole-frame decoder.

#include <algorithm>

#include "proto/frame.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  std::vector<std::uint8_t> two;
  AppendFrame(16, 0, std::vector<std::uint8_t>(40, 7), &two);
  AppendFrame(3, 2, {}, &two);
  return {EncodeFrame(17, 0, std::vector<std::uint8_t>{1, 2, 3}), two,
          EncodeFrame(16, 0, std::vector<std::uint8_t>(300, 0xAB))};
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const FrameLimits limits{.max_payload_bytes = 1u << 16};
  (void)DecodeFrame(ByteSpan(data, size), limits);
  // The stream decoder, fed in chunks whose sizes come from the input itself.
  FrameDecoder decoder(limits);
  std::vector<Frame> frames;
  std::size_t pos = 0, chunk = 1;
  while (pos < size) {
    const std::size_t n = std::min(size - pos, chunk);
    const Status s = decoder.Feed(ByteSpan(data + pos, n), &frames);
    pos += n;
    chunk = 1 + data[pos - 1] % 97;
    if (!s.ok()) {
      // Sticky: a failed decoder refuses everything afterwards.
      if (decoder.Feed(ByteSpan(data, size), &frames).ok()) fuzz::FuzzFail("decoder not sticky");
      break;
    }
  }
  for (const Frame& f : frames) {
    if (f.payload.size() > limits.max_payload_bytes) fuzz::FuzzFail("payload over the limit");
  }
  return 0;
}
