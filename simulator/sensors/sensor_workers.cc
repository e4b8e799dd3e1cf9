#include "simulator/sensors/sensor_workers.h"

namespace behaviorlib::sim {

SensorWorkers::SensorWorkers(int threads) {
  for (int i = 0; i < threads; ++i) threads_.emplace_back([this] { run(); });
}

SensorWorkers::~SensorWorkers() { stop(); }

void SensorWorkers::stop() {
  std::deque<std::pair<Slot*, std::function<void()>>> dropped;
  {
    std::lock_guard lock(mutex_);
    if (stopping_ && threads_.empty()) return;
    stopping_ = true;
    dropped.swap(queue_);
  }
  work_cv_.notify_all();
  done_cv_.notify_all();
  for (std::thread& thread : threads_) {
    if (thread.joinable()) thread.join();
  }
  threads_.clear();
  // `dropped` (and the sensors its jobs own) goes here, outside the lock.
}

bool SensorWorkers::submit(Slot& slot, std::function<void()> job, bool wait) {
  std::unique_lock lock(mutex_);
  if (slot.busy) {
    if (!wait) return false;
    done_cv_.wait(lock, [&] { return !slot.busy || stopping_; });
  }
  if (stopping_) return false;
  slot.busy = true;
  queue_.emplace_back(&slot, std::move(job));
  lock.unlock();
  work_cv_.notify_one();
  return true;
}

void SensorWorkers::waitIdle() {
  std::unique_lock lock(mutex_);
  done_cv_.wait(lock, [&] { return stopping_ || (queue_.empty() && running_ == 0); });
}

void SensorWorkers::waitFor(const Slot& slot) {
  std::unique_lock lock(mutex_);
  done_cv_.wait(lock, [&] { return stopping_ || !slot.busy; });
}

void SensorWorkers::run() {
  std::unique_lock lock(mutex_);
  while (true) {
    work_cv_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
    if (stopping_) return;
    auto [slot, job] = std::move(queue_.front());
    queue_.pop_front();
    ++running_;
    lock.unlock();
    job();
    lock.lock();
    slot->busy = false;
    --running_;
    // The job (and the sensor owning `slot`) may go now, outside the lock.
    lock.unlock();
    job = nullptr;
    done_cv_.notify_all();
    lock.lock();
  }
}

}  // namespace behaviorlib::sim
