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
    }
    cv_.Signal();
    return true;
  }

  /// Refuses new tasks, runs the queued ones, joins the threads.
  void stop() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
    }
    cv_.SignalAll();
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
        while (!stopping_ && tasks_.empty()) cv_.Wait(&mutex_);
        if (tasks_.empty()) return;
        task = std::move(tasks_.front());
        tasks_.pop_front();
      }
      task();
    }
  }

  absl::Mutex mutex_;
  absl::CondVar cv_;
  std::deque<std::function<void()>> tasks_ ABSL_GUARDED_BY(mutex_);
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::vector<std::thread> threads_;
};

}  // namespace behaviorlib::coordinator
