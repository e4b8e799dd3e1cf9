#pragma once

// Publishes simulated time and ground truth on the data channel without ever
// blocking the physics: the step listener queues samples (PublishQueue:
// bounded; the oldest are dropped and counted when the broker is slow) and a
// thread of its own publishes them. The sensors have a publisher of their
// own (SensorPublisher), so that camera images never delay the clock.
//
// Every topic the simulator publishes. Headers are stamped in simulated time
// and carry the robot id; the sensors' (from imu on) also a `seq` per vehicle
// and sensor, from 0 again after each Reset.
//
//   clock                              Clock         simulated time: free-running,
//                                                    its line (time, wall_time,
//                                                    time scale) when it changes
//                                                    and once a wall second; in
//                                                    lock-step 200 Hz of
//                                                    simulated time
//   robots/{id}/ground_truth/pose      PoseStamped   frame world, 100 Hz
//   robots/{id}/ground_truth/twist     TwistStamped  linear in world, angular
//                                                    in the body frame, 100 Hz
//   robots/{id}/flight_state           FlightStatus  10 Hz
//   robots/{id}/imu                    Imu           frame base_link, 200 Hz
//   robots/{id}/gps                    PositionFix   frame world, 10 Hz
//   robots/{id}/baro                   Altitude      frame world, 25 Hz
//   robots/{id}/linear_speed           TwistStamped  frame base_link (linear
//                                                    only), 30 Hz
//   robots/{id}/battery                BatteryState  frame base_link, 2 Hz
//   robots/{id}/lidar/scan             LaserScan     frame lidar, 10 Hz (2-D)
//   robots/{id}/lidar/points           PointCloud    frame lidar, 10 Hz (3-D)
//   robots/{id}/camera/image           Image         frame camera (optical),
//                                                    jpeg/png, 15 Hz, only
//                                                    while subscribed
//   robots/{id}/camera/info            CameraInfo    frame camera, 1 Hz
//
// The sensor rates are defaults: --sensor-config changes them (0 disables a
// sensor); see simulator/sensors/README.md.

#include <chrono>
#include <memory>

#include "behaviorlib/v1/types.pb.h"
#include "simulator/core/simulation.h"
#include "simulator/service/channel_routes.h"
#include "simulator/service/publish_queue.h"
#include "simulator/service/simulator_service.h"  // TimeControl

namespace behaviorlib::sim {

struct PublishRates {
  /// In lock-step, the rate of clock samples (simulated time); free-running,
  /// how often the pace is looked at for a new line.
  double clock_hz = 200.0;
  /// Free-running, the pace line is published again after this much wall
  /// time without a change (a heartbeat for late readers and liveness).
  std::chrono::nanoseconds clock_heartbeat = std::chrono::seconds(1);
  /// Publish a clock sample every 1/clock_hz of simulated time also when
  /// free-running (no wall_time: readers anchor at arrival), as before the
  /// pace line; for comparison and for readers that want every tick.
  bool clock_every_tick = false;
  double ground_truth_hz = 100.0;
  double flight_state_hz = 10.0;
};

class ChannelPublisher {
 public:
  ChannelPublisher(ChannelRoutes& client, Simulation& simulation, const TimeControl& time,
                   PublishRates rates);
  ~ChannelPublisher();  // stops publishing (the listener must not run any more)
  ChannelPublisher(const ChannelPublisher&) = delete;
  ChannelPublisher& operator=(const ChannelPublisher&) = delete;

  uint64_t publishedCount() const { return queue_.publishedCount(); }
  /// Publishes the vehicles' topics only while wanted (PublishQueue).
  void setInterest(const ChannelRoutes* interest) { queue_.setInterest(interest); }
  void interestChanged() { queue_.interestChanged(); }
  uint64_t gatedCount() const { return queue_.gatedCount(); }
  /// Deterministic mode: publishes what is queued on this thread, and with
  /// `sync` waits until the broker took it (PublishQueue::flush).
  absl::Status flush(bool sync) { return queue_.flush(sync); }
  /// A lock-step clock sample of time `t` (time scale 0, this simulator's
  /// epoch), as the clock topic carries in lock-step; also the time grants'.
  v1::Clock lockStepClock(SimTime t) const;
  uint64_t droppedCount() const { return queue_.droppedCount(); }

 private:
  void onStep(SimTime now, const std::vector<VehicleReport>& vehicles);
  void publishClock(SimTime now);

  const Simulation& simulation_;
  const TimeControl& time_;
  PublishRates rates_;
  // Added to the simulation's epoch: a restarted simulator's time is told
  // apart from the time of the one before.
  const uint64_t epoch_base_;
  // Physics thread only: the pace generation last published, and when.
  uint64_t published_generation_ = 0;
  bool published_free_running_ = false;
  std::chrono::steady_clock::time_point last_clock_wall_{};
  // Physics thread only.
  double next_clock_s_ = 0, next_truth_s_ = 0, next_state_s_ = 0, last_t_ = 0;
  PublishQueue queue_;
};

}  // namespace behaviorlib::sim
