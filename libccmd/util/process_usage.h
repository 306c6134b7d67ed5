#pragma once

// This process's resource use, for statistics a server writes while it runs.

namespace ccmd {

struct ProcessUsage {
  double rss_mb = 0;       // resident memory now
  double peak_rss_mb = 0;  // the most it has been resident
  double cpu_seconds = 0;  // user + system, all threads
};

// From /proc/self/status and getrusage; zeros where the system does not tell.
ProcessUsage CurrentProcessUsage();

// Gives memory the allocator holds free back to the system (glibc's malloc_trim): after a
// large transient allocation (an optimisation, decoded images) the freed pages would otherwise
// stay resident. Costs about a millisecond; call it after such work, not per item.
void ReleaseFreeMemory();

}  // namespace ccmd
