#include "libccmd/util/process_usage.h"

#include <malloc.h>
#include <sys/resource.h>

#include <cstdio>
#include <cstring>

namespace ccmd {

ProcessUsage CurrentProcessUsage() {
  ProcessUsage usage;
  if (std::FILE* f = std::fopen("/proc/self/status", "r")) {
    char line[256];
    while (std::fgets(line, sizeof(line), f)) {
      long kb = 0;
      if (std::sscanf(line, "VmRSS: %ld kB", &kb) == 1) usage.rss_mb = kb / 1024.0;
      if (std::sscanf(line, "VmHWM: %ld kB", &kb) == 1) usage.peak_rss_mb = kb / 1024.0;
    }
    std::fclose(f);
  }
  rusage self{};
  if (getrusage(RUSAGE_SELF, &self) == 0) {
    usage.cpu_seconds = self.ru_utime.tv_sec + self.ru_utime.tv_usec * 1e-6 + self.ru_stime.tv_sec +
                        self.ru_stime.tv_usec * 1e-6;
    if (usage.peak_rss_mb == 0) usage.peak_rss_mb = self.ru_maxrss / 1024.0;
    usage.minor_page_faults = self.ru_minflt;
  }
  return usage;
}

void ReleaseFreeMemory() {
#ifdef __GLIBC__
  malloc_trim(0);
#endif
}

void ConfigureAllocatorForLongRuns(long mmap_threshold_bytes, long trim_threshold_bytes) {
#ifdef __GLIBC__
  // Setting either value also turns off glibc's dynamic adjustment of both.
  mallopt(M_MMAP_THRESHOLD, static_cast<int>(mmap_threshold_bytes));
  mallopt(M_TRIM_THRESHOLD, static_cast<int>(trim_threshold_bytes));
#else
  (void)mmap_threshold_bytes;
  (void)trim_threshold_bytes;
#endif
}

}  // namespace ccmd
