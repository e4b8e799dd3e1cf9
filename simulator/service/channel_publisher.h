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
//   clock                              Clock         simulated time, 200 Hz
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

#include <memory>

#include "channel/channel_client.h"
#include "simulator/core/simulation.h"
#include "simulator/service/publish_queue.h"
#include "simulator/service/simulator_service.h"  // TimeControl

namespace behaviorlib::sim {

struct PublishRates {
  double clock_hz = 200.0;
  double ground_truth_hz = 100.0;
  double flight_state_hz = 10.0;
};

class ChannelPublisher {
 public:
  ChannelPublisher(channel::ChannelClient& client, Simulation& simulation, const TimeControl& time,
                   PublishRates rates);
  ~ChannelPublisher();  // stops publishing (the listener must not run any more)
  ChannelPublisher(const ChannelPublisher&) = delete;
  ChannelPublisher& operator=(const ChannelPublisher&) = delete;

  uint64_t publishedCount() const { return queue_.publishedCount(); }
  uint64_t droppedCount() const { return queue_.droppedCount(); }

 private:
  void onStep(SimTime now, const std::vector<VehicleReport>& vehicles);

  const TimeControl& time_;
  PublishRates rates_;
  // Physics thread only.
  double next_clock_s_ = 0, next_truth_s_ = 0, next_state_s_ = 0, last_t_ = 0;
  PublishQueue queue_;
};

}  // namespace behaviorlib::sim
