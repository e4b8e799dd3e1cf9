#include "simulator/service/channel_publisher.h"

#include <google/protobuf/util/time_util.h>

#include "behaviorlib/v1/types.pb.h"
#include "simulator/service/messages.h"

namespace behaviorlib::sim {
namespace {

constexpr size_t kQueueLimit = 10000;

}  // namespace

ChannelPublisher::ChannelPublisher(channel::ChannelClient& client, Simulation& simulation,
                                   const TimeControl& time, PublishRates rates)
    : client_(client), time_(time), rates_(rates) {
  thread_ = std::thread([this] { run(); });
  simulation.addStepListener(
      [this](SimTime now, const std::vector<VehicleReport>& vehicles) { onStep(now, vehicles); });
}

ChannelPublisher::~ChannelPublisher() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void ChannelPublisher::enqueueLocked(std::string topic,
                                     std::unique_ptr<google::protobuf::Message> sample) {
  if (queue_.size() >= kQueueLimit) {
    queue_.pop_front();
    ++dropped_;
  }
  queue_.emplace_back(std::move(topic), std::move(sample));
}

void ChannelPublisher::onStep(SimTime now, const std::vector<VehicleReport>& vehicles) {
  const double t = std::chrono::duration<double>(now).count();
  const auto stamp = google::protobuf::util::TimeUtil::NanosecondsToTimestamp(now.count());
  bool queued = false;
  std::lock_guard lock(mutex_);
  if (t < last_t_) next_clock_s_ = next_truth_s_ = next_state_s_ = 0.0;  // Reset restarted time
  last_t_ = t;
  if (t + 1e-9 >= next_clock_s_) {
    next_clock_s_ = t + 1.0 / rates_.clock_hz;
    auto clock = std::make_unique<v1::Clock>();
    *clock->mutable_header()->mutable_stamp() = stamp;
    *clock->mutable_time() = stamp;
    clock->set_time_scale(time_.lock_step.load() ? 0.0 : time_.time_scale.load());
    enqueueLocked("clock", std::move(clock));
    queued = true;
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
      enqueueLocked(prefix + "ground_truth/pose", std::move(pose));
      auto twist = std::make_unique<v1::TwistStamped>();
      *twist->mutable_header() = full.header();
      *twist->mutable_twist() = full.twist();
      enqueueLocked(prefix + "ground_truth/twist", std::move(twist));
    }
    if (state) {
      auto status = std::make_unique<v1::FlightStatus>(flightStatusMessage(
          *report.robot_id, now, *report.platform, report.snapshot.battery_ratio));
      enqueueLocked(prefix + "flight_state", std::move(status));
    }
    queued = true;
  }
  if (queued) cv_.notify_one();
}

void ChannelPublisher::run() {
  std::unique_lock lock(mutex_);
  while (true) {
    cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
    if (stopping_) return;
    auto [topic, sample] = std::move(queue_.front());
    queue_.pop_front();
    lock.unlock();
    if (client_.publish(topic, *sample).ok()) {
      ++published_;
    } else {
      ++dropped_;
    }
    lock.lock();
  }
}

}  // namespace behaviorlib::sim
