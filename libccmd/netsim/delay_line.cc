#include "libccmd/netsim/delay_line.h"

#include <algorithm>

namespace ccmd {

bool DelayLine::Push(double now, std::vector<std::uint8_t> packet) {
  ++stats_.arrived;
  stats_.arrived_bytes += packet.size();
  // Both draws happen for every packet, so one packet's fate does not shift the others'.
  const bool lost = rng_.Bernoulli(options_.loss);
  const double delay = options_.delay_s + options_.jitter_s * (2 * rng_.Uniform() - 1);
  if (lost) {
    ++stats_.lost;
    return false;
  }
  if (queue_.size() >= options_.max_packets || bytes_ + packet.size() > options_.max_bytes) {
    ++stats_.overflow;
    return false;
  }
  const double due = std::max(now + std::max(0.0, delay), last_due_);
  last_due_ = due;
  bytes_ += packet.size();
  queue_.push_back({due, std::move(packet)});
  return true;
}

bool DelayLine::PopDue(double now, std::vector<std::uint8_t>* packet) {
  if (queue_.empty() || queue_.front().due > now) return false;
  *packet = std::move(queue_.front().packet);
  queue_.pop_front();
  bytes_ -= packet->size();
  ++stats_.left;
  stats_.left_bytes += packet->size();
  return true;
}

}  // namespace ccmd
