// Fuzz target: frame authentication (libccmd/net/frame_auth.h) on a stream of frames. The
// seeds are an honest agent's tagged stream; whatever the fuzzer makes of it, a frame that
// passes the server's check must be exactly the honest frame due at that point (no byte of
// header, payload or tag left unchecked, no replay or reordering accepted), and checking
// stops at the first failure, as the server closes the connection there.

#include <cstring>

#include "libccmd/net/frame_auth.h"
#include "libccmd/net/session_messages.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {
namespace {

SessionKeys Keys() {
  Nonce agent{}, server{};
  agent.fill(0x11);
  server.fill(0x22);
  static constexpr std::uint8_t kHello[] = {'a', ' ', 'h', 'e', 'l', 'l', 'o'};
  return DeriveSessionKeys("the fuzzing deployment key", agent, server,
                           ByteSpan(kHello, sizeof(kHello)));
}

// The honest stream, and where each of its frames starts.
struct Honest {
  std::vector<std::uint8_t> stream;
  std::vector<std::size_t> starts;
};

const Honest& HonestStream() {
  static const Honest honest = [] {
    Honest h;
    SessionAuth agent(FrameRole::kAgent, Keys(), true);
    auto mark = [&] { h.starts.push_back(h.stream.size()); };
    mark();
    agent.AppendDataFrame(16, 1, std::vector<std::uint8_t>(120, 0x31), &h.stream);
    mark();
    agent.AppendFrame(static_cast<std::uint8_t>(SessionType::kHeartbeat), {}, &h.stream);
    mark();
    agent.AppendDataFrame(17, 2, std::vector<std::uint8_t>(29, 0x32), &h.stream);
    mark();
    agent.AppendDataFrame(16, 3, std::vector<std::uint8_t>(7, 0x33), &h.stream);
    mark();
    agent.AppendFrame(static_cast<std::uint8_t>(SessionType::kBye),
                      SerializeBye({ByeReason::kNormal, "done"}), &h.stream);
    h.starts.push_back(h.stream.size());
    return h;
  }();
  return honest;
}

}  // namespace

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  const Honest& h = HonestStream();
  std::vector<std::vector<std::uint8_t>> seeds = {h.stream};
  // Each frame alone, and the stream with its frames swapped pairwise.
  for (std::size_t k = 0; k + 1 < h.starts.size(); ++k) {
    seeds.emplace_back(h.stream.begin() + static_cast<std::ptrdiff_t>(h.starts[k]),
                       h.stream.begin() + static_cast<std::ptrdiff_t>(h.starts[k + 1]));
  }
  std::vector<std::uint8_t> swapped(h.stream.begin() + static_cast<std::ptrdiff_t>(h.starts[1]),
                                    h.stream.begin() + static_cast<std::ptrdiff_t>(h.starts[2]));
  swapped.insert(swapped.end(), h.stream.begin(),
                 h.stream.begin() + static_cast<std::ptrdiff_t>(h.starts[1]));
  seeds.push_back(swapped);
  return seeds;
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const fuzz::Honest& honest = fuzz::HonestStream();
  FrameDecoder decoder(FrameLimits{.max_payload_bytes = 1u << 16});
  std::vector<Frame> frames;
  (void)decoder.Feed(ByteSpan(data, size), &frames);
  SessionAuth server(FrameRole::kServer, fuzz::Keys(), true);
  for (const Frame& f : frames) {
    if (!server.Verify(f).ok()) break;
    const std::size_t k = server.frames_verified() - 1;
    if (k + 1 >= honest.starts.size()) fuzz::FuzzFail("a frame beyond the honest stream verified");
    const std::size_t begin = honest.starts[k], end = honest.starts[k + 1];
    const std::uint8_t* expected = honest.stream.data() + begin;
    const bool same = f.tag && end - begin == kFrameHeaderSize + f.payload.size() + kFrameTagSize &&
                      std::memcmp(expected, f.header.data(), kFrameHeaderSize) == 0 &&
                      (f.payload.empty() || std::memcmp(expected + kFrameHeaderSize,
                                                        f.payload.data(), f.payload.size()) == 0) &&
                      std::memcmp(expected + kFrameHeaderSize + f.payload.size(), f.tag->data(),
                                  kFrameTagSize) == 0;
    if (!same) fuzz::FuzzFail("a frame other than the honest one verified");
  }
  return 0;
}
