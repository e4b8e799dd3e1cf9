#pragma once

// BlockingPool: a few threads for the coordinator's calls that block (plans,
// missions' control, safety actions), so that gRPC's callback threads never
// wait on another server.
//
//   BlockingPool pool(4);
//   pool.post([reactor] { ...; reactor->Finish(status); });
//   pool.stop();   // runs what is queued, then joins

#include <deque>
#include <functional>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"

namespace behaviorlib::coordinator {

class BlockingPool {
 public:
  explicit BlockingPool(int threads) {
    for (int i = 0; i < threads; ++i) threads_.emplace_back([this] { run(); });
  }
  ~BlockingPool() { stop(); }
  BlockingPool(const BlockingPool&) = delete;
  BlockingPool& operator=(const BlockingPool&) = delete;

  /// Queues `task`; false after stop() (the task is not run).
  bool post(std::function<void()> task) {
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return false;
      tasks_.push_back(std::move(task));
    }  // a waiting thread's Await sees the task at this unlock
    return true;
  }

  /// Refuses new tasks, runs the queued ones, joins the threads.
  void stop() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
    }
    for (auto& t : threads_) {
      if (t.joinable()) t.join();
    }
  }

 private:
  void run() {
    for (;;) {
      std::function<void()> task;
      {
        absl::MutexLock lock(&mutex_);
        mutex_.Await(absl::Condition(this, &BlockingPool::hasWorkLocked));
        if (tasks_.empty()) return;
        task = std::move(tasks_.front());
        tasks_.pop_front();
      }
      task();
    }
  }

  bool hasWorkLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || !tasks_.empty();
  }

  // The threads wait on mutex_ (Mutex::Await) for a task or the stop.
  absl::Mutex mutex_;
  std::deque<std::function<void()>> tasks_ ABSL_GUARDED_BY(mutex_);
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::vector<std::thread> threads_;
};

}  // namespace behaviorlib::coordinator
