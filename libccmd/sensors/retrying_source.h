#pragma once

// Keeps a live camera going through unplugs and hiccups. Wraps a source opener: when the
// source's Read returns Unavailable (unplugged, busy, silent), the source is closed and
// reopened with bounded exponential backoff (0.5 s, 1 s, 2 s, ... up to 8 s by default),
// each attempt reported. Read never blocks longer than one backoff delay plus one open, and
// returns Unavailable while the camera is away, so the caller (the agent) keeps its map,
// keeps sending what it has and simply calls Read again.
//
// Frames keep counting across reconnects (index), and timestamps stay increasing even if
// the device clock restarts on reopen (OpenNI2 devices count from zero).

#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <string>

#include "libccmd/sensors/rgbd_source.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct RetryOptions {
  double initial_delay_s = 0.5;
  double max_delay_s = 8.0;
  double multiplier = 2.0;
  // Consecutive failed reopen attempts before giving up (Read then returns Timeout); 0 = never.
  int max_attempts = 0;
  // If the first open fails, keep trying (waiting for the camera to be plugged in) instead of
  // returning the error.
  bool wait_for_first_open = false;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Delay before reopen attempt `attempt` (0-based): min(initial * multiplier^attempt, max).
double BackoffDelay(const RetryOptions& options, int attempt);

struct RetryEvent {
  enum class Kind {
    kLost,         // the source failed with Unavailable and was closed
    kRetryFailed,  // a reopen attempt failed
    kReconnected,  // a reopen attempt succeeded
    kGaveUp,       // max_attempts reached
  };
  Kind kind = Kind::kLost;
  int attempt = 0;          // reopen attempts so far in this outage (1 = the first)
  double next_delay_s = 0;  // wait before the next attempt (kLost, kRetryFailed)
  double away_s = 0;        // time since the camera was lost (kReconnected, kGaveUp)
  Status status;            // what failed

  // "camera lost: unavailable: ...; reopening in 0.5 s"
  std::string ToString() const;
};

// Replaceable for tests; defaults are a cancellable timed wait, the monotonic clock and a
// warning in the log.
struct RetryHooks {
  std::function<bool(double seconds)> wait;  // false = cancelled
  std::function<double()> now;
  std::function<void(const RetryEvent&)> report;
};

class RetryingSource : public RgbdSource {
 public:
  using Opener = std::function<StatusOr<std::unique_ptr<RgbdSource>>()>;

  static StatusOr<std::unique_ptr<RetryingSource>> Open(Opener opener,
                                                        const RetryOptions& options = {},
                                                        RetryHooks hooks = {});

  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return camera_; }
  std::string Describe() const override;
  int FrameCount() const override { return frame_count_; }
  bool IsLive() const override { return live_; }
  Trajectory GroundTruth() const override;
  Pose T_color_trajectory() const override { return T_color_trajectory_; }  // the first open's
  long DroppedFrames() const override {
    return dropped_before_ + (inner_ ? inner_->DroppedFrames() : 0);
  }

  // Ends a wait in progress (from another thread, e.g. on shutdown): that Read and every
  // later one returns Cancelled.
  void Cancel();

  bool connected() const { return inner_ != nullptr; }
  int reconnects() const { return reconnects_; }
  int failed_attempts() const { return failed_attempts_; }

 private:
  RetryingSource(Opener opener, const RetryOptions& options, RetryHooks hooks);
  Status Reopen();
  bool Wait(double seconds);
  bool cancelled() const;

  Opener opener_;
  RetryOptions options_;
  RetryHooks hooks_;
  std::unique_ptr<RgbdSource> inner_;
  PinholeCamera camera_;
  Pose T_color_trajectory_ = Pose::Identity();
  bool have_camera_ = false;
  std::string description_;
  int frame_count_ = -1;
  bool live_ = true;
  int attempt_ = 0;  // reopen attempts in the current outage
  int failed_attempts_ = 0;
  int reconnects_ = 0;
  double lost_at_ = 0;
  long dropped_before_ = 0;  // by the devices opened before the current one
  Status gave_up_;

  int next_index_ = 0;
  bool have_last_ = false;
  double last_timestamp_ = 0;  // last timestamp handed out
  double last_frame_at_ = 0;   // clock time when it was handed out
  double time_offset_ = 0;     // added to the device time after a clock restart
  bool check_clock_ = false;   // first frame after a reconnect

  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool cancelled_ = false;
};

}  // namespace ccmd
