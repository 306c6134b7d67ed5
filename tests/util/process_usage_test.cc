#include "libccmd/util/process_usage.h"

#include <gtest/gtest.h>

#include <cstdlib>

#include "tests/support/test_support.h"  // CCMD_OWN_ALLOCATOR

#ifdef __GLIBC__
#include <malloc.h>
#endif

namespace ccmd {
namespace {

TEST(ProcessUsageTest, ReportsResidentMemoryAndCpu) {
  const ProcessUsage usage = CurrentProcessUsage();
  EXPECT_GT(usage.rss_mb, 1.0);  // a test binary with gtest is never below a megabyte
  EXPECT_GE(usage.peak_rss_mb, usage.rss_mb);
  EXPECT_GE(usage.cpu_seconds, 0.0);
}

#if defined(__GLIBC__) && !defined(CCMD_OWN_ALLOCATOR)
void* Touched(std::size_t bytes) {
  auto* p = static_cast<volatile char*>(std::malloc(bytes));
  for (std::size_t i = 0; i < bytes; i += 4096) p[i] = 1;
  return const_cast<char*>(p);
}

// glibc's default raises its mmap threshold to the largest block freed: after a 4 MB block is
// freed, a 512 kB block would come from a heap and stay resident there once freed. With the
// long-run setting it gets pages of its own, which the free returns.
TEST(ProcessUsageTest, BlocksAboveTheThresholdGetPagesOfTheirOwnAfterALargerOneIsFreed) {
  ConfigureAllocatorForLongRuns(128 * 1024, 1024 * 1024);
  std::free(Touched(4 << 20));
  const struct mallinfo2 before = mallinfo2();
  void* block = Touched(512 << 10);
  const struct mallinfo2 during = mallinfo2();
  EXPECT_EQ(during.hblks, before.hblks + 1);
  EXPECT_GE(during.hblkhd, before.hblkhd + (512 << 10));
  std::free(block);
  EXPECT_EQ(mallinfo2().hblkhd, before.hblkhd);
  // Small blocks still come from the heap.
  void* small = Touched(16 << 10);
  EXPECT_EQ(mallinfo2().hblks, before.hblks);
  std::free(small);
}
#endif

}  // namespace
}  // namespace ccmd
