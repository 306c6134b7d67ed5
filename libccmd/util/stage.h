#pragma once

// A pipeline stage: a bounded queue and the one owned thread that handles its items in order.
// The stage itself counts what it was given and has not finished (queued or being handled),
// so WaitIdle() needs no counters kept by producers or handlers. Items pushed by a handler
// into a later stage are counted there before this stage's item counts as finished, so
// waiting for the stages in pipeline order sees everything submitted before the wait.
//
//   Stage<Job> stage(64);
//   stage.Start([&](Job job) { Handle(job); });
//   stage.Push(job);   // blocks while 64 items wait
//   stage.WaitIdle();  // nothing queued, nothing being handled
//   stage.Stop();      // handles what is queued, then joins the thread
//
// With Policy::kLatest a pushed item replaces the one still waiting, if any: for requests
// where only the newest matters (a global optimisation of a map).

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <utility>

#include "libccmd/util/logging.h"

namespace ccmd {

template <typename T>
class Stage {
 public:
  enum class Policy { kQueue, kLatest };
  using Handler = std::function<void(T)>;

  explicit Stage(std::size_t capacity, Policy policy = Policy::kQueue)
      : capacity_(capacity), policy_(policy) {
    CCMD_CHECK_GT(capacity, 0u);
  }
  ~Stage() { Stop(); }
  Stage(const Stage&) = delete;
  Stage& operator=(const Stage&) = delete;

  // Starts the thread. Call once, before the first Push.
  void Start(Handler handler) {
    CCMD_CHECK(!thread_.joinable()) << "stage started twice";
    handler_ = std::move(handler);
    thread_ = std::thread([this] { Run(); });
  }

  // Queues an item (blocks while full, unless the policy replaces a waiting item). Returns
  // false once the stage is stopping: the item is dropped.
  bool Push(T item) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (policy_ == Policy::kLatest && !items_.empty() && !closed_) {
      items_.back() = std::move(item);
      return true;
    }
    not_full_.wait(lock, [&] { return closed_ || items_.size() < capacity_; });
    if (closed_) return false;
    items_.push_back(std::move(item));
    not_empty_.notify_one();
    return true;
  }

  // Queues an item only when nothing is queued or being handled (work that must not replace or
  // delay another's). Returns whether it was queued.
  bool PushIfIdle(T item) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (closed_ || busy_ || !items_.empty()) return false;
    items_.push_back(std::move(item));
    not_empty_.notify_one();
    return true;
  }

  // Refuses new items, lets the thread handle what is queued and joins it. Idempotent.
  void Stop() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      closed_ = true;
    }
    not_empty_.notify_all();
    not_full_.notify_all();
    if (thread_.joinable()) thread_.join();
  }

  // Returns once nothing is queued and no item is being handled.
  void WaitIdle() const {
    std::unique_lock<std::mutex> lock(mutex_);
    idle_.wait(lock, [&] { return items_.empty() && !busy_; });
  }

  // Items waiting (not counting one being handled).
  std::size_t backlog() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return items_.size();
  }
  bool busy() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return busy_;
  }

 private:
  void Run() {
    std::unique_lock<std::mutex> lock(mutex_);
    while (true) {
      not_empty_.wait(lock, [&] { return closed_ || !items_.empty(); });
      if (items_.empty()) break;  // closed and drained
      T item = std::move(items_.front());
      items_.pop_front();
      busy_ = true;
      not_full_.notify_one();
      lock.unlock();
      handler_(std::move(item));
      lock.lock();
      busy_ = false;
      if (items_.empty()) idle_.notify_all();
    }
    idle_.notify_all();
  }

  const std::size_t capacity_;
  const Policy policy_;
  Handler handler_;
  mutable std::mutex mutex_;
  std::condition_variable not_empty_, not_full_;
  mutable std::condition_variable idle_;
  std::deque<T> items_;
  bool busy_ = false;
  bool closed_ = false;
  std::thread thread_;
};

}  // namespace ccmd
