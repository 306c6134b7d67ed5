#include "libccmd/util/stage.h"

#include <gtest/gtest.h>

#include <atomic>
#include <future>
#include <mutex>
#include <thread>
#include <vector>

namespace ccmd {
namespace {

// Opens once; every wait returns after that.
class Gate {
 public:
  void Open() {
    std::lock_guard<std::mutex> lock(mutex_);
    open_ = true;
    cv_.notify_all();
  }
  void Wait() {
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait(lock, [&] { return open_; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  bool open_ = false;
};

TEST(StageTest, HandlesItemsInOrderAndIsIdleOnlyWhenTheLastIsDone) {
  std::vector<int> handled;  // written by the stage thread; read after WaitIdle
  Stage<int> stage(4);
  stage.Start([&](int x) { handled.push_back(x); });
  for (int i = 0; i < 100; ++i) ASSERT_TRUE(stage.Push(i));
  stage.WaitIdle();
  ASSERT_EQ(handled.size(), 100u);
  for (int i = 0; i < 100; ++i) EXPECT_EQ(handled[i], i);
  EXPECT_EQ(stage.backlog(), 0u);
  EXPECT_FALSE(stage.busy());
}

TEST(StageTest, WaitIdleWaitsForTheItemBeingHandled) {
  Gate gate;
  std::atomic<bool> waiter_returned{false};
  std::atomic<bool> returned_while_handling{false};
  std::promise<void> handling;
  Stage<int> stage(4);
  stage.Start([&](int) {
    handling.set_value();
    gate.Wait();
    returned_while_handling = waiter_returned.load();
  });
  ASSERT_TRUE(stage.Push(1));
  handling.get_future().wait();  // the item has left the queue and is being handled
  EXPECT_EQ(stage.backlog(), 0u);
  EXPECT_TRUE(stage.busy());
  std::thread waiter([&] {
    stage.WaitIdle();
    waiter_returned = true;
  });
  gate.Open();
  waiter.join();
  EXPECT_FALSE(returned_while_handling);
  EXPECT_TRUE(waiter_returned);
}

TEST(StageTest, WorkPassedToTheNextStageIsCountedThereBeforeItIsDoneHere) {
  std::atomic<int> second_done{0};
  Stage<int> second(2);
  second.Start([&](int) { second_done++; });
  Stage<int> first(2);
  first.Start([&](int x) {
    second.Push(x);
    second.Push(x);
  });
  for (int i = 0; i < 50; ++i) first.Push(i);
  first.WaitIdle();
  second.WaitIdle();
  EXPECT_EQ(second_done.load(), 100);
}

TEST(StageTest, LatestPolicyReplacesTheWaitingRequest) {
  Gate gate;
  std::promise<void> handling;
  std::vector<int> handled;
  Stage<int> stage(1, Stage<int>::Policy::kLatest);
  stage.Start([&](int x) {
    if (x == 1) {
      handling.set_value();
      gate.Wait();
    }
    handled.push_back(x);
  });
  stage.Push(1);
  handling.get_future().wait();
  stage.Push(2);  // waits behind 1
  stage.Push(3);  // replaces 2
  EXPECT_EQ(stage.backlog(), 1u);
  gate.Open();
  stage.WaitIdle();
  EXPECT_EQ(handled, (std::vector<int>{1, 3}));
}

TEST(StageTest, PushIfIdleQueuesOnlyWhenNothingIsQueuedOrBeingHandled) {
  Gate gate;
  std::promise<void> handling;
  std::vector<int> handled;
  Stage<int> stage(4, Stage<int>::Policy::kLatest);
  stage.Start([&](int x) {
    if (x == 1) {
      handling.set_value();
      gate.Wait();
    }
    handled.push_back(x);
  });
  ASSERT_TRUE(stage.PushIfIdle(1));
  handling.get_future().wait();
  EXPECT_FALSE(stage.PushIfIdle(2));  // 1 is being handled
  stage.Push(3);
  EXPECT_FALSE(stage.PushIfIdle(4));  // 3 waits: not replaced
  gate.Open();
  stage.WaitIdle();
  EXPECT_TRUE(stage.PushIfIdle(5));
  stage.Stop();
  EXPECT_FALSE(stage.PushIfIdle(6));
  EXPECT_EQ(handled, (std::vector<int>{1, 3, 5}));
}

TEST(StageTest, StopHandlesWhatIsQueuedThenRefusesMore) {
  Gate gate;
  std::vector<int> handled;
  Stage<int> stage(8);
  stage.Start([&](int x) {
    gate.Wait();
    handled.push_back(x);
  });
  for (int i = 0; i < 5; ++i) stage.Push(i);
  gate.Open();
  stage.Stop();
  EXPECT_EQ(handled, (std::vector<int>{0, 1, 2, 3, 4}));
  EXPECT_FALSE(stage.Push(9));
  stage.WaitIdle();  // returns at once
  stage.Stop();      // idempotent
}

}  // namespace
}  // namespace ccmd
