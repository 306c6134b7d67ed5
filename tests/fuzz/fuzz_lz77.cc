// Fuzz target: LZ77 decoding. Whatever decodes must code back to the same bytes.

#include "libccmd/codec/lz77.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  std::vector<std::vector<std::uint8_t>> seeds;
  std::vector<std::uint8_t> text;
  for (int i = 0; i < 2000; ++i)
    text.push_back(static_cast<std::uint8_t>("abcabcabd"[i % 9] + i / 500));
  for (const auto& raw :
       {text, std::vector<std::uint8_t>(3000, 0), std::vector<std::uint8_t>{1, 2, 3}}) {
    std::vector<std::uint8_t> coded;
    Lz77Compress(raw, &coded);
    seeds.push_back(coded);
  }
  return seeds;
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  std::vector<std::uint8_t> out;
  if (!Lz77Decompress(std::span(data, size), 1u << 20, &out).ok()) return 0;
  std::vector<std::uint8_t> coded, back;
  Lz77Compress(out, &coded);
  if (!Lz77Decompress(coded, out.size(), &back).ok() || back != out) {
    fuzz::FuzzFail("LZ77 round trip of decoded data");
  }
  return 0;
}
