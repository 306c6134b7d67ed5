#include "libccmd/tracking/cpu_budget.h"

#include <algorithm>
#include <chrono>
#include <opencv2/core/utility.hpp>
#include <thread>

#include "libccmd/util/timer.h"

namespace ccmd {

MappingBudget::MappingBudget(double cores, double sensor_fps)
    : cores_(cores),
      frame_credit_ms_(cores > 0 && sensor_fps > 0 ? 1000.0 * cores / sensor_fps : 0.0),
      max_credit_ms_(1000.0 * std::max(cores, 0.0)),
      max_debt_ms_(500.0 * std::max(cores, 0.0)) {}

void MappingBudget::AddFrame(double tracking_cpu_ms) {
  if (!enabled()) return;
  std::lock_guard<std::mutex> lock(mutex_);
  balance_ms_ = std::min(max_credit_ms_, balance_ms_ + frame_credit_ms_ - tracking_cpu_ms);
  lowest_ms_ = std::min(lowest_ms_, balance_ms_);
}

void MappingBudget::Spend(double mapping_cpu_ms) {
  if (!enabled()) return;
  std::lock_guard<std::mutex> lock(mutex_);
  balance_ms_ -= mapping_cpu_ms;
  lowest_ms_ = std::min(lowest_ms_, balance_ms_);
}

LocalBaLevel MappingBudget::Level() const {
  if (!enabled()) return LocalBaLevel::kFull;
  std::lock_guard<std::mutex> lock(mutex_);
  if (balance_ms_ >= 0) return LocalBaLevel::kFull;
  return balance_ms_ > -max_debt_ms_ ? LocalBaLevel::kReduced : LocalBaLevel::kSkipped;
}

double MappingBudget::balance_ms() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return balance_ms_;
}

double MappingBudget::lowest_balance_ms() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return lowest_ms_;
}

CpuPacer::CpuPacer(double cores)
    : cores_(cores), cpu_start_(ProcessCpuTimeSeconds()), wall_start_(MonotonicSeconds()) {}

double CpuPacer::Pace() {
  if (cores_ <= 0) return 0;
  const double cpu = ProcessCpuTimeSeconds() - cpu_start_;
  const double wall = MonotonicSeconds() - wall_start_;
  const double ahead = cpu / cores_ - wall;  // seconds of wall time the budget still asks for
  if (ahead < 1e-3) return 0;
  std::this_thread::sleep_for(std::chrono::duration<double>(ahead));
  paced_ms_ += 1e3 * ahead;
  return 1e3 * ahead;
}

void UseOpenCvThreadsForBudget(double cores) {
  if (cores > 0) cv::setNumThreads(1);
}

}  // namespace ccmd
