#pragma once

// SensorWorkers: the threads that ray-cast lidar scans and render camera
// frames away from the physics thread. Each sensor has a Slot: at most one
// frame of a sensor is queued or running at a time, so frames come out in
// order and a sensor that cannot keep up loses frames (submit() returns
// false) instead of building a backlog -- or, in lock-step, the physics
// waits for it (`wait`), so that every frame is produced.

#include <condition_variable>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <utility>
#include <vector>

namespace behaviorlib::sim {

class SensorWorkers {
 public:
  /// One sensor's place in the queue; guarded by the workers' mutex.
  struct Slot {
    bool busy = false;
  };

  explicit SensorWorkers(int threads);
  /// Stops the threads; queued jobs are dropped, running ones finish.
  ~SensorWorkers();
  SensorWorkers(const SensorWorkers&) = delete;
  SensorWorkers& operator=(const SensorWorkers&) = delete;

  /// Queues `job` for `slot`. If the slot's previous job is still queued or
  /// running: with `wait`, blocks until it is done; else returns false (the
  /// frame is dropped). `slot` must stay alive until the job has run (the
  /// job should own it). False after stop().
  bool submit(Slot& slot, std::function<void()> job, bool wait);
  /// Blocks until nothing is queued or running.
  void waitIdle();
  /// Blocks until `slot`'s job (if any) is done.
  void waitFor(const Slot& slot);
  /// Stops the threads (idempotent).
  void stop();

 private:
  void run();

  std::mutex mutex_;
  std::condition_variable work_cv_;
  std::condition_variable done_cv_;
  std::deque<std::pair<Slot*, std::function<void()>>> queue_;
  int running_ = 0;
  bool stopping_ = false;
  std::vector<std::thread> threads_;
};

}  // namespace behaviorlib::sim
