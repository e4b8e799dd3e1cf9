#include "simulator/service/channel_publisher.h"

#include <google/protobuf/util/time_util.h>

#include "behaviorlib/v1/types.pb.h"
#include "simulator/service/messages.h"

namespace behaviorlib::sim {

ChannelPublisher::ChannelPublisher(channel::ChannelClient& client, Simulation& simulation,
                                   const TimeControl& time, PublishRates rates)
    : time_(time), rates_(rates), queue_(client, PublishQueueLimits{}) {
  simulation.addStepListener(
      [this](SimTime now, const std::vector<VehicleReport>& vehicles) { onStep(now, vehicles); });
}

ChannelPublisher::~ChannelPublisher() = default;

void ChannelPublisher::onStep(SimTime now, const std::vector<VehicleReport>& vehicles) {
  const double t = std::chrono::duration<double>(now).count();
  const auto stamp = google::protobuf::util::TimeUtil::NanosecondsToTimestamp(now.count());
  if (t < last_t_) next_clock_s_ = next_truth_s_ = next_state_s_ = 0.0;  // Reset restarted time
  last_t_ = t;
  if (t + 1e-9 >= next_clock_s_) {
    next_clock_s_ = t + 1.0 / rates_.clock_hz;
    auto clock = std::make_unique<v1::Clock>();
    *clock->mutable_header()->mutable_stamp() = stamp;
    *clock->mutable_time() = stamp;
    clock->set_time_scale(time_.lock_step.load() ? 0.0 : time_.time_scale.load());
    queue_.push("clock", std::move(clock));
  }
  const bool truth = t + 1e-9 >= next_truth_s_;
  const bool state = t + 1e-9 >= next_state_s_;
  if (truth) next_truth_s_ = t + 1.0 / rates_.ground_truth_hz;
  if (state) next_state_s_ = t + 1.0 / rates_.flight_state_hz;
  for (const auto& report : vehicles) {
    if (!truth && !state) break;
    const std::string prefix = "robots/" + *report.robot_id + "/";
    const v1::VehicleState full = vehicleStateMessage(*report.robot_id, now, report);
    if (truth) {
      auto pose = std::make_unique<v1::PoseStamped>();
      *pose->mutable_header() = full.header();
      *pose->mutable_pose() = full.pose();
      queue_.push(prefix + "ground_truth/pose", std::move(pose));
      auto twist = std::make_unique<v1::TwistStamped>();
      *twist->mutable_header() = full.header();
      *twist->mutable_twist() = full.twist();
      queue_.push(prefix + "ground_truth/twist", std::move(twist));
    }
    if (state) {
      queue_.push(prefix + "flight_state",
                  std::make_unique<v1::FlightStatus>(flightStatusMessage(
                      *report.robot_id, now, *report.platform, report.snapshot.battery_ratio)));
    }
  }
}

}  // namespace behaviorlib::sim
