#pragma once

// Shared by the fuzz targets. Each target file defines LLVMFuzzerTestOneInput (the libFuzzer
// entry point) and FuzzSeeds() (valid inputs that fuzz_driver.cc mutates in the normal
// build, and that scripts/fuzz.sh writes out as libFuzzer's starting corpus).
// A target must never crash, hang or allocate without bound on any input; a failed
// invariant check calls FuzzFail, which aborts (and so shows up in both builds).

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds();

// Inputs that once made the target fail (optional; fuzz_driver.cc has an empty default).
// The driver runs them before its mutations, and --write-seeds writes them into the corpus
// too, so that scripts/fuzz.sh replays them under AddressSanitizer and UBSan: undefined
// behaviour that a release build happens to survive is caught there.
std::vector<std::vector<std::uint8_t>> FuzzRegressions();

[[noreturn]] inline void FuzzFail(const char* what) {
  std::fprintf(stderr, "fuzz invariant failed: %s\n", what);
  std::abort();
}

}  // namespace ccmd::fuzz
