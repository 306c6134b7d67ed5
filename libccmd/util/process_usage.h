#pragma once

// This process's resource use, for statistics a server writes while it runs.

namespace ccmd {

struct ProcessUsage {
  double rss_mb = 0;           // resident memory now
  double peak_rss_mb = 0;      // the most it has been resident
  double cpu_seconds = 0;      // user + system, all threads
  long minor_page_faults = 0;  // pages first touched (or touched again after being unmapped)
};

// From /proc/self/status and getrusage; zeros where the system does not tell.
ProcessUsage CurrentProcessUsage();

// Gives memory the allocator holds free back to the system (glibc's malloc_trim): after a
// large transient allocation (an optimisation, decoded images) the freed pages would otherwise
// stay resident. Costs about a millisecond; call it after such work, not per item.
void ReleaseFreeMemory();

// For processes that run for hours: every allocation of at least `mmap_threshold_bytes` gets
// pages of its own that go back to the system when it is freed, and freed memory at the top
// of a heap is returned once it exceeds `trim_threshold_bytes`. glibc otherwise raises its
// mmap threshold to the largest block freed so far (up to 32 MB), after which decoded images,
// clouds and solver workspaces are carved from the per-thread heaps, which fragment and keep
// growing while the live data stays bounded. The price is a page fault per page of every such
// block: a process that allocates the same image-sized buffers every frame (the agent) runs at
// half speed with it and does not need it. No-op where the allocator is not glibc's.
void ConfigureAllocatorForLongRuns(long mmap_threshold_bytes = 128 * 1024,
                                   long trim_threshold_bytes = 1024 * 1024);

}  // namespace ccmd
