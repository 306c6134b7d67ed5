// A deterministic stand-in for libFuzzer, so that the normal (gcc) build exercises every
// fuzz target as a ctest: seeded mutations of valid inputs (truncations, bit flips, byte
// overwrites with boundary values, huge varints, duplicated and deleted ranges, splices).
//
//   fuzz_<target>_driver [--iterations N] [--seed S] [--write-seeds DIR]

#include <cstring>
#include <fstream>
#include <string>

#include "libccmd/util/random.h"
#include "tests/fuzz/fuzz_target.h"

namespace {

using Bytes = std::vector<std::uint8_t>;

Bytes Mutate(const Bytes& seed, const std::vector<Bytes>& seeds, ccmd::Rng& rng) {
  Bytes b = seed;
  const int steps = rng.UniformInt(1, 4);
  for (int s = 0; s < steps; ++s) {
    const int kind = rng.UniformInt(0, 7);
    const std::size_t n = b.size();
    const std::size_t at =
        n ? static_cast<std::size_t>(rng.UniformInt(0, static_cast<int>(n) - 1)) : 0;
    switch (kind) {
      case 0:  // truncate
        b.resize(n ? static_cast<std::size_t>(rng.UniformInt(0, static_cast<int>(n) - 1)) : 0);
        break;
      case 1:  // flip one bit
        if (n) b[at] ^= static_cast<std::uint8_t>(1u << rng.UniformInt(0, 7));
        break;
      case 2: {  // boundary value
        static const std::uint8_t values[] = {0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF};
        if (n) b[at] = values[rng.UniformInt(0, 5)];
        break;
      }
      case 3: {  // a huge varint or 32-bit length in place
        static const Bytes huge = {0xFF, 0xFF, 0xFF, 0xFF, 0x0F};
        for (std::size_t k = 0; k < huge.size() && at + k < n; ++k) b[at + k] = huge[k];
        break;
      }
      case 4: {  // delete a range
        const std::size_t len = std::min<std::size_t>(n - at, rng.UniformInt(1, 16));
        if (n) b.erase(b.begin() + at, b.begin() + at + len);
        break;
      }
      case 5: {  // duplicate a range
        const std::size_t len = std::min<std::size_t>(n - at, rng.UniformInt(1, 16));
        if (n) b.insert(b.begin() + at, b.begin() + at, b.begin() + at + len);
        break;
      }
      case 6: {  // splice with another seed
        const Bytes& other = seeds[rng.UniformInt(0, static_cast<int>(seeds.size()) - 1)];
        if (!other.empty()) {
          const std::size_t from = rng.UniformInt(0, static_cast<int>(other.size()) - 1);
          b.resize(at);
          b.insert(b.end(), other.begin() + from, other.end());
        }
        break;
      }
      default:  // random byte
        if (n) b[at] = static_cast<std::uint8_t>(rng.Next());
        break;
    }
  }
  return b;
}

}  // namespace

// The default for targets without regression inputs (fuzz_target.h).
__attribute__((weak)) std::vector<Bytes> ccmd::fuzz::FuzzRegressions() { return {}; }

int main(int argc, char** argv) {
  long iterations = 20000;
  std::uint64_t seed = 1;
  std::string write_seeds;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--iterations" && i + 1 < argc) {
      iterations = std::atol(argv[++i]);
    } else if (arg == "--seed" && i + 1 < argc) {
      seed = std::strtoull(argv[++i], nullptr, 10);
    } else if (arg == "--write-seeds" && i + 1 < argc) {
      write_seeds = argv[++i];
    } else {
      std::fprintf(stderr, "usage: %s [--iterations N] [--seed S] [--write-seeds DIR]\n", argv[0]);
      return 2;
    }
  }
  const std::vector<Bytes> seeds = ccmd::fuzz::FuzzSeeds();
  const std::vector<Bytes> regressions = ccmd::fuzz::FuzzRegressions();
  if (!write_seeds.empty()) {
    auto write = [&](const std::string& name, const Bytes& bytes) {
      std::ofstream out(write_seeds + "/" + name, std::ios::binary);
      out.write(reinterpret_cast<const char*>(bytes.data()),
                static_cast<std::streamsize>(bytes.size()));
    };
    for (std::size_t k = 0; k < seeds.size(); ++k) write("seed_" + std::to_string(k), seeds[k]);
    for (std::size_t k = 0; k < regressions.size(); ++k) {
      write("regression_" + std::to_string(k), regressions[k]);
    }
    return 0;
  }
  for (const Bytes& r : regressions) LLVMFuzzerTestOneInput(r.data(), r.size());
  for (const Bytes& s : seeds) LLVMFuzzerTestOneInput(s.data(), s.size());
  ccmd::Rng rng(seed);
  for (long i = 0; i < iterations; ++i) {
    const Bytes input = Mutate(seeds[i % seeds.size()], seeds, rng);
    LLVMFuzzerTestOneInput(input.data(), input.size());
  }
  // Pure noise too.
  for (int i = 0; i < 200; ++i) {
    Bytes noise(rng.UniformInt(0, 512));
    for (auto& b : noise) b = static_cast<std::uint8_t>(rng.Next());
    LLVMFuzzerTestOneInput(noise.data(), noise.size());
  }
  std::printf("%s: %zu regression inputs, %ld mutated inputs and 200 random ones, no failure\n",
              argv[0], regressions.size(), iterations);
  return 0;
}
