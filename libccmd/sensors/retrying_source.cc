#include "libccmd/sensors/retrying_source.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status RetryOptions::Validate() const {
  if (!(initial_delay_s >= 0)) return InvalidArgument("initial_delay_s must be >= 0");
  if (!(max_delay_s >= initial_delay_s)) {
    return InvalidArgument("max_delay_s must be >= initial_delay_s");
  }
  if (!(multiplier >= 1)) return InvalidArgument("multiplier must be >= 1");
  if (max_attempts < 0) return InvalidArgument("max_attempts must be >= 0");
  return Status::Ok();
}

void RetryOptions::Describe(OptionsWriter* out) const {
  out->Add("initial_delay_s", initial_delay_s);
  out->Add("max_delay_s", max_delay_s);
  out->Add("multiplier", multiplier);
  out->Add("max_attempts", max_attempts);
  out->Add("wait_for_first_open", wait_for_first_open);
}

double BackoffDelay(const RetryOptions& options, int attempt) {
  // Computed by repeated multiplication so a large attempt count cannot overflow.
  double delay = options.initial_delay_s;
  for (int i = 0; i < attempt && delay < options.max_delay_s; ++i) delay *= options.multiplier;
  return std::min(delay, options.max_delay_s);
}

std::string RetryEvent::ToString() const {
  std::ostringstream out;
  out.precision(3);
  switch (kind) {
    case Kind::kLost:
      out << "camera lost (" << status.ToString() << "); reopening in " << next_delay_s << " s";
      break;
    case Kind::kRetryFailed:
      out << "camera reopen attempt " << attempt << " failed (" << status.ToString()
          << "); next attempt in " << next_delay_s << " s";
      break;
    case Kind::kReconnected:
      out << "camera back after " << away_s << " s (attempt " << attempt << ")";
      break;
    case Kind::kGaveUp:
      out << "camera gave up after " << attempt << " attempts over " << away_s << " s ("
          << status.ToString() << ")";
      break;
  }
  return out.str();
}

RetryingSource::RetryingSource(Opener opener, const RetryOptions& options, RetryHooks hooks)
    : opener_(std::move(opener)), options_(options), hooks_(std::move(hooks)) {
  if (!hooks_.now) hooks_.now = MonotonicSeconds;
  if (!hooks_.report) {
    hooks_.report = [](const RetryEvent& event) {
      if (event.kind == RetryEvent::Kind::kReconnected) {
        CCMD_LOG(INFO) << event.ToString();
      } else {
        CCMD_LOG(WARNING) << event.ToString();
      }
    };
  }
}

StatusOr<std::unique_ptr<RetryingSource>> RetryingSource::Open(Opener opener,
                                                               const RetryOptions& options,
                                                               RetryHooks hooks) {
  CCMD_RETURN_IF_ERROR(options.Validate().WithContext("retry options"));
  if (!opener) return InvalidArgument("retry: no opener");
  std::unique_ptr<RetryingSource> source(
      new RetryingSource(std::move(opener), options, std::move(hooks)));
  StatusOr<std::unique_ptr<RgbdSource>> first = source->opener_();
  if (!first.ok()) {
    if (!options.wait_for_first_open) return first.status();
    // Waiting for the camera to be plugged in: the same schedule as after a loss.
    source->lost_at_ = source->hooks_.now();
    RetryEvent event{RetryEvent::Kind::kLost, 0, BackoffDelay(options, 0), 0, first.status()};
    source->hooks_.report(event);
    while (source->inner_ == nullptr) {
      const Status status = source->Reopen();
      if (status.ok()) break;
      if (status.code() != StatusCode::kUnavailable) return status;
    }
    source->reconnects_ = 0;  // that was the first connection, not a reconnection
  } else {
    source->inner_ = std::move(first).value();
  }
  source->camera_ = source->inner_->camera();
  source->T_color_trajectory_ = source->inner_->T_color_trajectory();
  source->have_camera_ = true;
  source->description_ = source->inner_->Describe();
  source->frame_count_ = source->inner_->FrameCount();
  source->live_ = source->inner_->IsLive();
  return source;
}

bool RetryingSource::cancelled() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return cancelled_;
}

void RetryingSource::Cancel() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    cancelled_ = true;
  }
  wake_.notify_all();
}

bool RetryingSource::Wait(double seconds) {
  if (hooks_.wait) return hooks_.wait(seconds) && !cancelled();
  // A timed wait for the device, cut short only by Cancel().
  std::unique_lock<std::mutex> lock(mutex_);
  wake_.wait_for(lock, std::chrono::duration<double>(seconds), [&] { return cancelled_; });
  return !cancelled_;
}

// One reopen attempt, after its backoff delay. Ok when the source is back.
Status RetryingSource::Reopen() {
  if (!gave_up_.ok()) return gave_up_;
  const double delay = BackoffDelay(options_, attempt_);
  if (!Wait(delay)) return Cancelled("camera reopen cancelled");
  ++attempt_;
  StatusOr<std::unique_ptr<RgbdSource>> opened = opener_();
  if (opened.ok() && have_camera_ &&
      ((*opened)->camera().width != camera_.width ||
       (*opened)->camera().height != camera_.height)) {
    // The map was built at the first size; a different one after reconnecting cannot be used.
    return gave_up_ =
               Unsupported("camera came back at " + std::to_string((*opened)->camera().width) +
                           "x" + std::to_string((*opened)->camera().height) + ", was " +
                           std::to_string(camera_.width) + "x" + std::to_string(camera_.height));
  }
  if (opened.ok()) {
    inner_ = std::move(opened).value();
    RetryEvent event{RetryEvent::Kind::kReconnected, attempt_, 0, hooks_.now() - lost_at_, {}};
    hooks_.report(event);
    attempt_ = 0;
    ++reconnects_;
    check_clock_ = true;
    return Status::Ok();
  }
  ++failed_attempts_;
  if (options_.max_attempts > 0 && attempt_ >= options_.max_attempts) {
    RetryEvent event{RetryEvent::Kind::kGaveUp, attempt_, 0, hooks_.now() - lost_at_,
                     opened.status()};
    hooks_.report(event);
    return gave_up_ = Timeout("camera did not come back after " + std::to_string(attempt_) +
                              " attempts: " + opened.status().ToString());
  }
  RetryEvent event{RetryEvent::Kind::kRetryFailed, attempt_, BackoffDelay(options_, attempt_), 0,
                   opened.status()};
  hooks_.report(event);
  return Unavailable("camera away (reopen attempt " + std::to_string(attempt_) +
                     "): " + opened.status().ToString());
}

Status RetryingSource::Read(RgbdFrame* frame) {
  if (cancelled()) return Cancelled("camera source cancelled");
  if (inner_ == nullptr) CCMD_RETURN_IF_ERROR(Reopen());

  const Status status = inner_->Read(frame);
  if (status.code() == StatusCode::kUnavailable) {
    dropped_before_ += inner_->DroppedFrames();
    inner_.reset();  // closes the device now, so it can be reopened (or replugged)
    lost_at_ = hooks_.now();
    RetryEvent event{RetryEvent::Kind::kLost, 0, BackoffDelay(options_, 0), 0, status};
    hooks_.report(event);
    return status;
  }
  if (!status.ok()) return status;

  const double now = hooks_.now();
  if (check_clock_ && have_last_ && frame->timestamp + time_offset_ <= last_timestamp_) {
    // The device clock restarted with the device: continue from the last time handed out
    // plus the time that really passed.
    time_offset_ = last_timestamp_ + std::max(now - last_frame_at_, 1e-3) - frame->timestamp;
  }
  check_clock_ = false;
  frame->timestamp += time_offset_;
  frame->index = next_index_++;
  have_last_ = true;
  last_timestamp_ = frame->timestamp;
  last_frame_at_ = now;
  return Status::Ok();
}

std::string RetryingSource::Describe() const { return description_ + " (reopened on failure)"; }

Trajectory RetryingSource::GroundTruth() const {
  return inner_ != nullptr ? inner_->GroundTruth() : Trajectory{};
}

}  // namespace ccmd
