#pragma once

// SensorPublisher: the simulated sensors of every vehicle (SensorSystem) on
// the data channel. Samples are turned into messages and queued for a
// publishing thread of their own (topics in channel_publisher.h). Camera
// frames are rendered only while someone wants a vehicle's
// `robots/{id}/camera/image`: with an interest watch (setInterest), as soon
// as the broker says so; without one (or while it is down), a thread asks
// the broker (ListTopics, subscriber_count) every `poll_period` of wall
// time.
//
//   SensorPublisher sensors(client, simulation, time, config);
//   worlds.on_reset = [&](auto world, uint64_t seed) { sensors.reset(world, seed); };

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <thread>

#include "simulator/core/simulation.h"
#include "simulator/sensors/sensor_system.h"
#include "simulator/service/channel_routes.h"
#include "simulator/service/publish_queue.h"
#include "simulator/service/simulator_service.h"  // TimeControl

namespace behaviorlib::sim {

class SensorPublisher {
 public:
  /// Registers a step listener on `simulation`; in lock-step (`time`) the
  /// physics waits for lidar and camera frames instead of dropping them.
  /// `frame_timer` (optional) is told how long each frame took to make.
  /// Precondition: config.validate() is OK.
  SensorPublisher(ChannelRoutes& client, Simulation& simulation, const TimeControl& time,
                  SensorConfig config, SensorSystem::FrameTimer frame_timer = {},
                  std::chrono::milliseconds poll_period = std::chrono::milliseconds(500));
  /// Stops the poller, the workers and the publishing thread. The step
  /// listener must not run any more.
  ~SensorPublisher();
  SensorPublisher(const SensorPublisher&) = delete;
  SensorPublisher& operator=(const SensorPublisher&) = delete;

  /// Restarts every sensor for a new world and seed (Reset); call it from
  /// Simulation::resetVehicles' `then`.
  void reset(std::shared_ptr<const world::World> world, uint64_t seed) {
    sensors_.reset(world, seed);
  }

  const SensorSystem& sensors() const { return sensors_; }
  /// For fault injection (SensorSystem::setFault is thread-safe).
  SensorSystem& sensors() { return sensors_; }
  uint64_t publishedCount() const { return queue_.publishedCount(); }
  /// Publishes the vehicles' topics only while wanted (PublishQueue).
  void setInterest(const ChannelRoutes* interest);
  void interestChanged();
  uint64_t gatedCount() const { return queue_.gatedCount(); }
  /// Deterministic mode: publishes what is queued on this thread, and with
  /// `sync` waits until the broker took it (PublishQueue::flush).
  absl::Status flush(bool sync) { return queue_.flush(sync); }
  uint64_t droppedCount() const { return queue_.droppedCount(); }

 private:
  void pollSubscribers();
  // The wanted cameras from the interest watch; false while it is not known.
  bool camerasFromInterest();

  ChannelRoutes& client_;
  const std::chrono::milliseconds poll_period_;
  PublishQueue queue_;  // before sensors_: the workers push into it
  SensorSystem sensors_;

  std::mutex poll_mutex_;
  std::condition_variable poll_cv_;
  bool stopping_ = false;
  const ChannelRoutes* interest_ = nullptr;  // guarded by poll_mutex_
  std::thread poller_;
};

}  // namespace behaviorlib::sim
