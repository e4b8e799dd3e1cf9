#include "simulator/service/channel_publisher.h"

#include <google/protobuf/util/time_util.h>

#include <random>

#include "behaviorlib/v1/types.pb.h"
#include "simulator/service/messages.h"

namespace behaviorlib::sim {

namespace {

uint64_t randomEpochBase() {
  std::random_device random;
  return (static_cast<uint64_t>(random()) << 32) ^ (static_cast<uint64_t>(random()) << 8);
}

google::protobuf::Timestamp timestampOf(SimTime t) {
  return google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
      std::chrono::duration_cast<std::chrono::nanoseconds>(t).count());
}

}  // namespace

ChannelPublisher::ChannelPublisher(ChannelRoutes& client, Simulation& simulation,
                                   const TimeControl& time, PublishRates rates)
    : simulation_(simulation),
      time_(time),
      rates_(rates),
      epoch_base_(randomEpochBase()),
      queue_(client, PublishQueueLimits{}, time.deterministic.load()) {
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
    publishClock(now);
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

v1::Clock ChannelPublisher::lockStepClock(SimTime t) const {
  v1::Clock clock;
  clock.set_epoch(epoch_base_ + simulation_.pace().epoch);
  *clock.mutable_time() = timestampOf(t);
  *clock.mutable_header()->mutable_stamp() = clock.time();
  clock.set_time_scale(0.0);
  return clock;
}

void ChannelPublisher::publishClock(SimTime now) {
  const Pace pace = simulation_.pace();
  const bool free_running = !time_.lock_step.load() && pace.scale > 0.0;
  const auto wall_now = std::chrono::steady_clock::now();
  auto clock = std::make_unique<v1::Clock>();
  clock->set_epoch(epoch_base_ + pace.epoch);
  if (free_running && rates_.clock_every_tick) {
    *clock->mutable_time() = timestampOf(now);
    clock->set_time_scale(pace.scale);
  } else if (free_running) {
    // The line, placed at this instant; only when it changed or as the
    // heartbeat: readers extrapolate it.
    if (published_free_running_ && pace.generation == published_generation_ &&
        wall_now - last_clock_wall_ < rates_.clock_heartbeat) {
      return;
    }
    const auto line_now =
        pace.sim + std::chrono::duration_cast<SimDuration>((wall_now - pace.wall) * pace.scale);
    const auto system_now = std::chrono::system_clock::now();
    *clock->mutable_time() = timestampOf(line_now);
    *clock->mutable_wall_time() = google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
        std::chrono::duration_cast<std::chrono::nanoseconds>(system_now.time_since_epoch())
            .count());
    clock->set_time_scale(pace.scale);
  } else {
    // Lock-step: time stands between samples, which come every period.
    *clock->mutable_time() = timestampOf(now);
    clock->set_time_scale(0.0);
  }
  *clock->mutable_header()->mutable_stamp() = clock->time();
  published_free_running_ = free_running;
  published_generation_ = pace.generation;
  last_clock_wall_ = wall_now;
  queue_.push("clock", std::move(clock));
}

}  // namespace behaviorlib::sim
