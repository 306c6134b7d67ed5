#pragma once

// The agent's CPU budget, in cores. At the sensor rate a frame may cost `cores / fps` seconds
// of CPU in all; tracking takes its share first, since it must never fall behind the camera,
// and local mapping gets the rest. MappingBudget keeps that account, frame by frame and
// keyframe by keyframe, and tells the mapper how much of a local BA it can afford: all of it,
// a smaller one (smaller window, fewer iterations), or none. Measured CPU time, not wall
// time, so other programs on the machine do not count against the agent.

#include <mutex>

namespace ccmd {

enum class LocalBaLevel { kFull, kReduced, kSkipped };

class MappingBudget {
 public:
  // `cores` <= 0: no budget, every local BA is full.
  MappingBudget(double cores, double sensor_fps);

  bool enabled() const { return cores_ > 0; }
  // After each frame: the tracking thread's CPU time for it (milliseconds).
  void AddFrame(double tracking_cpu_ms);
  // After each keyframe: the mapping thread's CPU time for it (milliseconds).
  void Spend(double mapping_cpu_ms);
  // What the next local BA may be: full while the account is in credit, reduced while it is
  // in debt, skipped once the debt exceeds half a second of the budget.
  LocalBaLevel Level() const;
  double balance_ms() const;
  double lowest_balance_ms() const;

 private:
  const double cores_;
  const double frame_credit_ms_;  // budget per frame at the sensor rate
  const double max_credit_ms_;    // savings beyond one second of budget do not accumulate
  const double max_debt_ms_;
  mutable std::mutex mutex_;
  double balance_ms_ = 0;
  double lowest_ms_ = 0;
};

// Paces a replay (frames read as fast as the agent takes them) so that the process uses at
// most `cores` on average since construction: before each frame it sleeps while the
// process's CPU time is ahead of cores x wall time. Sleeping is the point here (the budget is
// a rate), not a way to wait for another thread. `cores` <= 0: never sleeps.
class CpuPacer {
 public:
  explicit CpuPacer(double cores);
  // Returns the milliseconds slept.
  double Pace();
  double paced_ms() const { return paced_ms_; }

 private:
  const double cores_;
  const double cpu_start_, wall_start_;
  double paced_ms_ = 0;
};

// OpenCV runs some functions on its own thread pool, whose workers spin between tasks: on a
// budget the agent's own threads (tracking, mapping) are all the parallelism it can use, so
// with a budget (cores > 0) OpenCV runs in the calling thread. Process-wide; for programs.
void UseOpenCvThreadsForBudget(double cores);

}  // namespace ccmd
