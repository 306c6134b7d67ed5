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

}  // namespace ccmd
