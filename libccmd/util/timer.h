#pragma once

#include <chrono>
#include <ctime>

namespace ccmd {

// Seconds on a monotonic clock; only differences are meaningful.
inline double MonotonicSeconds() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// Seconds since the Unix epoch (wall clock), for timestamps written to files.
inline double WallSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

// CPU time in seconds: of the calling thread, and of the whole process (all threads). They
// measure work rather than waiting, so they stay meaningful on a machine shared with other
// work, where wall times are not.
inline double ThreadCpuTimeSeconds() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}
inline double ProcessCpuTimeSeconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

// CPU time of the calling thread since construction (or Restart).
class ThreadCpuStopwatch {
 public:
  ThreadCpuStopwatch() : start_(ThreadCpuTimeSeconds()) {}
  void Restart() { start_ = ThreadCpuTimeSeconds(); }
  double ElapsedMillis() const { return (ThreadCpuTimeSeconds() - start_) * 1e3; }

 private:
  double start_;
};

class Stopwatch {
 public:
  Stopwatch() : start_(std::chrono::steady_clock::now()) {}
  void Restart() { start_ = std::chrono::steady_clock::now(); }
  double ElapsedSeconds() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  }
  double ElapsedMillis() const { return ElapsedSeconds() * 1e3; }

 private:
  std::chrono::steady_clock::time_point start_;
};

}  // namespace ccmd
