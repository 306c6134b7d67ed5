#pragma once

// 256-bit binary descriptors (ORB) and their Hamming distance.

#include <array>
#include <bit>
#include <cstdint>
#include <cstring>
#include <vector>

#include <opencv2/core.hpp>

// Hamming distances dominate descriptor matching, and the x86-64 baseline has no popcnt
// instruction (std::popcount becomes a dozen instructions). Hot loops are marked with this so
// they are compiled twice and the loader picks the popcnt version where the CPU has it.
// Not under ThreadSanitizer: the loader runs the choosing function (an ifunc resolver) before
// the sanitizer's runtime is up, and its instrumented code crashes the program at start.
#if defined(__x86_64__) && defined(__linux__) && defined(__GNUC__) && !defined(__SANITIZE_THREAD__)
#define CCMD_POPCNT_CLONES __attribute__((target_clones("popcnt", "default")))
#else
#define CCMD_POPCNT_CLONES
#endif

namespace ccmd {

using Descriptor = std::array<std::uint8_t, 32>;

inline int HammingDistance(const std::uint8_t* a, const std::uint8_t* b) {
  int distance = 0;
  for (int i = 0; i < 32; i += 8) {
    std::uint64_t x, y;
    std::memcpy(&x, a + i, 8);
    std::memcpy(&y, b + i, 8);
    distance += std::popcount(x ^ y);
  }
  return distance;
}

inline int HammingDistance(const Descriptor& a, const Descriptor& b) {
  return HammingDistance(a.data(), b.data());
}

inline Descriptor DescriptorRow(const cv::Mat& descriptors, int row) {
  Descriptor d;
  std::memcpy(d.data(), descriptors.ptr<std::uint8_t>(row), 32);
  return d;
}

// The descriptor with the smallest total distance to the others (ORB-SLAM's choice of a map
// point's representative descriptor). Precondition: !descriptors.empty().
Descriptor MedoidDescriptor(const std::vector<Descriptor>& descriptors);

}  // namespace ccmd
