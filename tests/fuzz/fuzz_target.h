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

[[noreturn]] inline void FuzzFail(const char* what) {
  std::fprintf(stderr, "fuzz invariant failed: %s\n", what);
  std::abort();
}

}  // namespace ccmd::fuzz
