#pragma once

// Helpers for checkProcesses(): supervise what a behavior relies on — a child
// process (the paper's wrapper around a reused program) or a worker thread.
//
//   ChildProcess planner({"/usr/bin/my_planner", "--fast"});
//   absl::Status s = planner.start();          // in onActivate
//   Verdict checkProcesses() override { return planner.check(); }
//   planner.stop();                             // in onDeactivate
//
//   SupervisedThread worker([](const std::atomic<bool>& stop, Heartbeat& beat) {
//     while (!stop) { beat.beat(); ... }
//   }, std::chrono::milliseconds(500));          // silence longer than this is a failure
//   Verdict checkProcesses() override { return worker.check(); }

#include <sys/types.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/behavior_execution_manager.h"

namespace behaviorlib {

/// A child process started with fork/exec, reaped without blocking.
class ChildProcess {
 public:
  explicit ChildProcess(std::vector<std::string> argv);
  ~ChildProcess();  // stops it
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  /// Starts the program; FAILED_PRECONDITION if it is already running,
  /// INTERNAL if it cannot be started (exec failure is seen by check()).
  absl::Status start();
  /// keepGoing while it runs; finish("<program> exited with code N" or
  /// "... killed by signal S") once it has stopped on its own.
  Verdict check();
  bool running();
  pid_t pid() const { return pid_; }
  /// SIGTERM, then SIGKILL after `grace`; reaps it.
  void stop(std::chrono::milliseconds grace = std::chrono::milliseconds(500));

 private:
  bool reap(bool block);
  std::vector<std::string> argv_;
  pid_t pid_ = -1;
  std::string exit_description_;
};

/// Proof of life written by a supervised worker.
class Heartbeat {
 public:
  void beat() {
    last_ns_.store(std::chrono::steady_clock::now().time_since_epoch().count(),
                   std::memory_order_relaxed);
  }
  std::chrono::steady_clock::time_point last() const {
    return std::chrono::steady_clock::time_point(
        std::chrono::steady_clock::duration(last_ns_.load(std::memory_order_relaxed)));
  }

 private:
  std::atomic<std::chrono::steady_clock::rep> last_ns_{
      std::chrono::steady_clock::now().time_since_epoch().count()};
};

/// A worker thread whose death (return, exception) or silence (no heartbeat
/// for `max_silence`, wall time) is reported by check().
class SupervisedThread {
 public:
  using Body = std::function<void(const std::atomic<bool>& stop, Heartbeat& heartbeat)>;
  SupervisedThread(Body body, std::chrono::milliseconds max_silence);
  ~SupervisedThread();  // requests stop and joins
  SupervisedThread(const SupervisedThread&) = delete;
  SupervisedThread& operator=(const SupervisedThread&) = delete;

  Verdict check() const;
  void stop();

 private:
  std::atomic<bool> stop_{false};
  std::atomic<bool> exited_{false};
  Heartbeat heartbeat_;
  std::chrono::milliseconds max_silence_;
  mutable absl::Mutex mutex_;
  std::string failure_ ABSL_GUARDED_BY(mutex_);
  std::thread thread_;
};

}  // namespace behaviorlib
