#include "libccmd/netsim/delay_line.h"

#include <algorithm>

namespace ccmd {

Status DelayLineOptions::Validate() const {
  if (!(delay_s >= 0) || !(jitter_s >= 0) || !std::isfinite(delay_s) || !std::isfinite(jitter_s)) {
    return InvalidArgument("delay and jitter must be >= 0");
  }
  if (!(loss >= 0 && loss < 1)) return InvalidArgument("loss must be in [0, 1)");
  if (max_packets == 0 || max_bytes == 0) return InvalidArgument("the delay line needs room");
  return Status::Ok();
}

void DelayLineOptions::Describe(OptionsWriter* out) const {
  out->Add("delay_s", delay_s);
  out->Add("jitter_s", jitter_s);
  out->Add("loss", loss);
  out->Add("seed", seed);
  out->Add("max_packets", max_packets);
  out->Add("max_bytes", max_bytes);
}

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
