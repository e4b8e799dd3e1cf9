#pragma once

// Publishes simulated time and ground truth on the data channel without ever
// blocking the physics: the step listener queues samples (bounded; the
// oldest are dropped and counted when the broker is slow) and a thread of its
// own publishes them.
//
// Topics: `clock` (behaviorlib.v1.Clock), `robots/{id}/ground_truth/pose`
// (PoseStamped), `robots/{id}/ground_truth/twist` (TwistStamped, linear in
// the world frame, angular in the body frame), `robots/{id}/flight_state`
// (FlightStatus).

#include <google/protobuf/message.h>

#include <atomic>
#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "channel/channel_client.h"
#include "simulator/core/simulation.h"
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
  ~ChannelPublisher();  // stops the thread
  ChannelPublisher(const ChannelPublisher&) = delete;
  ChannelPublisher& operator=(const ChannelPublisher&) = delete;

  uint64_t publishedCount() const { return published_.load(); }
  uint64_t droppedCount() const { return dropped_.load(); }

 private:
  void onStep(SimTime now, const std::vector<VehicleReport>& vehicles);
  void enqueueLocked(std::string topic, std::unique_ptr<google::protobuf::Message> sample);
  void run();

  channel::ChannelClient& client_;
  const TimeControl& time_;
  PublishRates rates_;
  double next_clock_s_ = 0, next_truth_s_ = 0, next_state_s_ = 0, last_t_ = 0;

  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<std::pair<std::string, std::unique_ptr<google::protobuf::Message>>> queue_;
  bool stopping_ = false;
  std::atomic<uint64_t> published_{0}, dropped_{0};
  std::thread thread_;
};

}  // namespace behaviorlib::sim
