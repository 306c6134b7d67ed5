#include "libccmd/sensors/retrying_source.h"

#include <gtest/gtest.h>

#include <deque>
#include <thread>

namespace ccmd {
namespace {

// An inner source that plays a script: each Read returns the next status; OK steps deliver
// a frame with the scripted timestamp.
struct Step {
  Status status;
  double timestamp = 0;
};

class ScriptedSource : public RgbdSource {
 public:
  ScriptedSource(std::deque<Step> steps, int width = 64) : steps_(std::move(steps)) {
    camera_.width = width;
    camera_.height = 48;
  }
  Status Read(RgbdFrame* frame) override {
    if (steps_.empty()) return Unavailable("script ended");
    const Step step = steps_.front();
    steps_.pop_front();
    if (!step.status.ok()) return step.status;
    frame->index = 1000;  // the wrapper renumbers
    frame->timestamp = step.timestamp;
    return Status::Ok();
  }
  const PinholeCamera& camera() const override { return camera_; }
  std::string Describe() const override { return "scripted"; }
  bool IsLive() const override { return true; }
  Pose T_color_trajectory() const override {
    Pose T = Pose::Identity();
    T.translation().x() = -0.025;  // a rig whose trajectories give its depth camera
    return T;
  }

 private:
  std::deque<Step> steps_;
  PinholeCamera camera_;
};

Step Frame(double t) { return {Status::Ok(), t}; }
Step Lost() { return {Unavailable("camera unplugged"), 0}; }

// Opens scripted sources in order; an entry without a script is a failed open.
struct ScriptedOpener {
  struct Entry {
    Status open_error;
    std::deque<Step> steps;
    int width = 64;
  };
  std::deque<Entry> entries;
  int calls = 0;

  RetryingSource::Opener Get() {
    return [this]() -> StatusOr<std::unique_ptr<RgbdSource>> {
      ++calls;
      if (entries.empty()) return NotFound("no camera");
      Entry entry = std::move(entries.front());
      entries.pop_front();
      if (!entry.open_error.ok()) return entry.open_error;
      return std::unique_ptr<RgbdSource>(new ScriptedSource(std::move(entry.steps), entry.width));
    };
  }
};

struct Recorder {
  std::vector<double> waits;
  std::vector<RetryEvent> events;
  double now = 0;
  RetryHooks Hooks() {
    RetryHooks hooks;
    hooks.wait = [this](double s) {
      waits.push_back(s);
      now += s;
      return true;
    };
    hooks.now = [this] { return now; };
    hooks.report = [this](const RetryEvent& e) { events.push_back(e); };
    return hooks;
  }
};

TEST(RetryingSourceTest, BackoffDoublesUpToTheCap) {
  const RetryOptions defaults;
  const double expected[] = {0.5, 1, 2, 4, 8, 8, 8};
  for (int i = 0; i < 7; ++i) EXPECT_DOUBLE_EQ(BackoffDelay(defaults, i), expected[i]) << i;
  RetryOptions custom;
  custom.initial_delay_s = 1;
  custom.multiplier = 3;
  custom.max_delay_s = 20;
  EXPECT_DOUBLE_EQ(BackoffDelay(custom, 2), 9);
  EXPECT_DOUBLE_EQ(BackoffDelay(custom, 3), 20);
  EXPECT_DOUBLE_EQ(BackoffDelay(custom, 1000000), 20);  // no overflow for long outages
}

TEST(RetryingSourceTest, ReportsEveryRetryAndReopensOnTheSchedule) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Frame(1.0), Lost()}});
  for (int i = 0; i < 3; ++i)
    opener.entries.push_back({NotFound("/dev/video2: no such device"), {}});
  opener.entries.push_back({Status::Ok(), {Frame(30.0), Lost()}});
  opener.entries.push_back({Status::Ok(), {Frame(60.0)}});
  Recorder recorder;
  auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
  ASSERT_TRUE(source.ok()) << source.status().ToString();

  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.index, 0);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);  // lost
  for (int i = 0; i < 3; ++i) {
    const Status status = (*source)->Read(&frame);  // each Read: one wait, one attempt
    EXPECT_EQ(status.code(), StatusCode::kUnavailable) << i;
    EXPECT_NE(status.message().find("no such device"), std::string::npos) << status.message();
  }
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ(frame.index, 1);
  EXPECT_DOUBLE_EQ(frame.timestamp, 30.0);
  EXPECT_EQ(recorder.waits, (std::vector<double>{0.5, 1, 2, 4}));

  ASSERT_EQ(recorder.events.size(), 5u);
  EXPECT_EQ(recorder.events[0].kind, RetryEvent::Kind::kLost);
  EXPECT_DOUBLE_EQ(recorder.events[0].next_delay_s, 0.5);
  for (int i = 1; i <= 3; ++i) {
    EXPECT_EQ(recorder.events[i].kind, RetryEvent::Kind::kRetryFailed);
    EXPECT_EQ(recorder.events[i].attempt, i);
    EXPECT_EQ(recorder.events[i].status.code(), StatusCode::kNotFound);
  }
  EXPECT_DOUBLE_EQ(recorder.events[3].next_delay_s, 4);
  EXPECT_EQ(recorder.events[4].kind, RetryEvent::Kind::kReconnected);
  EXPECT_EQ(recorder.events[4].attempt, 4);
  EXPECT_DOUBLE_EQ(recorder.events[4].away_s, 0.5 + 1 + 2 + 4);
  EXPECT_NE(recorder.events[4].ToString().find("camera back after 7.5 s"), std::string::npos)
      << recorder.events[4].ToString();

  // A second outage starts the schedule again from the first delay.
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_DOUBLE_EQ(recorder.waits.back(), 0.5);
  EXPECT_EQ((*source)->reconnects(), 2);
  EXPECT_EQ((*source)->failed_attempts(), 3);
}

TEST(RetryingSourceTest, PermanentErrorsAndTheEndPassThroughWithoutReopening) {
  ScriptedOpener opener;
  opener.entries.push_back(
      {Status::Ok(), {Frame(1.0), {Corrupt("bad frame"), 0}, {EndOfStream(), 0}}});
  Recorder recorder;
  auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kCorrupt);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kEndOfStream);
  EXPECT_EQ(opener.calls, 1);
  EXPECT_TRUE(recorder.events.empty());
}

// The camera whose poses the trajectories give (the config's Trajectory.camera) is the
// wrapped camera's, through outages too: the agent writes and announces it.
TEST(RetryingSourceTest, KeepsTheTrajectoryCameraOfTheWrappedSource) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Frame(1.0), Lost()}});
  opener.entries.push_back({Status::Ok(), {Frame(2.0)}});
  Recorder recorder;
  auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);  // lost
  ASSERT_TRUE((*source)->Read(&frame).ok());                            // reopened
  EXPECT_EQ(opener.calls, 2);
  EXPECT_DOUBLE_EQ((*source)->T_color_trajectory().translation().x(), -0.025);
}

TEST(RetryingSourceTest, GivesUpAfterMaxAttempts) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Lost()}});
  RetryOptions options;
  options.max_attempts = 2;
  Recorder recorder;
  auto source = RetryingSource::Open(opener.Get(), options, recorder.Hooks());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kTimeout);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kTimeout);  // no more attempts
  EXPECT_EQ(opener.calls, 3);
  EXPECT_EQ(recorder.events.back().kind, RetryEvent::Kind::kGaveUp);
  EXPECT_EQ(recorder.waits, (std::vector<double>{0.5, 1}));
}

TEST(RetryingSourceTest, TimestampsStayIncreasingWhenTheDeviceClockRestarts) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Frame(100.0), Frame(100.5), Lost()}});
  opener.entries.push_back({Status::Ok(), {Frame(0.0), Frame(0.25)}});
  Recorder recorder;
  recorder.now = 50;
  auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  ASSERT_TRUE((*source)->Read(&frame).ok());
  ASSERT_TRUE((*source)->Read(&frame).ok());  // handed out at clock 50
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  ASSERT_TRUE((*source)->Read(&frame).ok());  // after a 0.5 s wait: clock 50.5
  // The new device time 0.0 continues from 100.5 plus the 0.5 s that really passed.
  EXPECT_DOUBLE_EQ(frame.timestamp, 101.0);
  ASSERT_TRUE((*source)->Read(&frame).ok());
  EXPECT_DOUBLE_EQ(frame.timestamp, 101.25);
  EXPECT_EQ(frame.index, 3);
}

TEST(RetryingSourceTest, ACameraBackAtAnotherSizeIsAPermanentError) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Lost()}});
  opener.entries.push_back({Status::Ok(), {Frame(1.0)}, 320});
  Recorder recorder;
  auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnsupported);
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnsupported);
}

TEST(RetryingSourceTest, FirstOpenFailsOrWaitsForTheCamera) {
  {
    ScriptedOpener opener;
    opener.entries.push_back({NotFound("openni2: no device found"), {}});
    Recorder recorder;
    auto source = RetryingSource::Open(opener.Get(), {}, recorder.Hooks());
    EXPECT_EQ(source.status().code(), StatusCode::kNotFound);
    EXPECT_TRUE(recorder.waits.empty());
  }
  {
    ScriptedOpener opener;
    opener.entries.push_back({NotFound("no device"), {}});
    opener.entries.push_back({NotFound("no device"), {}});
    opener.entries.push_back({Status::Ok(), {Frame(5.0)}});
    RetryOptions options;
    options.wait_for_first_open = true;
    Recorder recorder;
    auto source = RetryingSource::Open(opener.Get(), options, recorder.Hooks());
    ASSERT_TRUE(source.ok()) << source.status().ToString();
    EXPECT_EQ(recorder.waits, (std::vector<double>{0.5, 1}));
    EXPECT_EQ((*source)->reconnects(), 0);
    EXPECT_EQ((*source)->camera().width, 64);
    RgbdFrame frame;
    ASSERT_TRUE((*source)->Read(&frame).ok());
    EXPECT_EQ(frame.index, 0);
  }
}

TEST(RetryingSourceTest, CancelEndsAWaitFromAnotherThread) {
  ScriptedOpener opener;
  opener.entries.push_back({Status::Ok(), {Lost()}});
  RetryOptions options;
  options.initial_delay_s = 3600;  // only Cancel can end this wait
  options.max_delay_s = 3600;
  RetryHooks hooks;
  hooks.report = [](const RetryEvent&) {};
  auto source = RetryingSource::Open(opener.Get(), options, hooks);  // real timed wait
  ASSERT_TRUE(source.ok());
  RgbdFrame frame;
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kUnavailable);
  std::thread canceller([&] { (*source)->Cancel(); });
  // Whether Cancel lands before or during the wait, Read returns Cancelled.
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kCancelled);
  canceller.join();
  EXPECT_EQ((*source)->Read(&frame).code(), StatusCode::kCancelled);
  EXPECT_EQ(opener.calls, 1);
}

TEST(RetryingSourceTest, RejectsBadOptions) {
  RetryOptions options;
  options.max_delay_s = 0.1;  // below the initial delay
  ScriptedOpener opener;
  EXPECT_EQ(RetryingSource::Open(opener.Get(), options).status().code(),
            StatusCode::kInvalidArgument);
  options = {};
  options.multiplier = 0.5;
  EXPECT_EQ(RetryingSource::Open(opener.Get(), options).status().code(),
            StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace ccmd
