#include "behaviorlib/basic_quadrotor_behaviors/estimate_with_linear_speed_behavior.h"

#include <cmath>
#include <tuple>
#include <vector>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::basic {
EstimatePositionWithLinearSpeedBehavior::EstimatePositionWithLinearSpeedBehavior(
    channel::ChannelClient* channel)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())),
      channel_(channel),
      estimate_(channel) {}

EstimatePositionWithLinearSpeedBehavior::~EstimatePositionWithLinearSpeedBehavior() {
  stopSubscriptions();
}

absl::Status EstimatePositionWithLinearSpeedBehavior::onConfigure(
    const config::v1::EstimatePositionWithLinearSpeedConfig& config) {
  speed_timeout_ = seconds(config.linear_speed_timeout_s());
  imu_timeout_ = seconds(config.imu_timeout_s());
  frozen_timeout_ = seconds(config.frozen_timeout_s());
  max_initial_estimate_age_ = seconds(config.max_initial_estimate_age_s());
  drift_ratio_ = config.drift_ratio();
  drift_rate_m_s_ = config.drift_rate_m_s();
  return absl::OkStatus();
}

double EstimatePositionWithLinearSpeedBehavior::driftBound() const {
  if (!reckoning_) return 0.0;
  return drift_ratio_ * reckoning_->distanceM() +
         drift_rate_m_s_ * std::max(reckoning_->lastTimeS() - start_s_, 0.0);
}

void EstimatePositionWithLinearSpeedBehavior::onImu(const v1::Imu& imu) {
  if (!running_) return;
  const Eigen::Vector3d gyro = toEigen(imu.angular_velocity_rad_s());
  Eigen::VectorXd value(6);
  value << gyro, toEigen(imu.linear_acceleration_m_s2());
  imu_->add(flight::stampTime(imu.header()), value);
  if (auto q = toOrientation(imu.orientation())) {
    orientation_ = *q;
    gyro_ = gyro;
  }
}

void EstimatePositionWithLinearSpeedBehavior::onSpeed(const v1::TwistStamped& speed) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(speed.header());
  const Eigen::Vector3d velocity = toEigen(speed.twist().linear_m_s());
  speed_->add(stamp, velocity);
  if (!(velocity.norm() <= max_speed_m_s_)) {
    // Not integrated: one such sample would carry the estimate away.
    if (implausible_.empty()) {
      implausible_ = "the linear speed on " + speed_->topic() + " reads " +
                     flight::fixed2(velocity.norm()) + " m/s, beyond max_speed_m_s " +
                     flight::fixed2(max_speed_m_s_) + ": a faulty sensor";
    }
    return;
  }
  if (!orientation_ || !reckoning_) return;  // the IMU's monitoring tells
  const double max_gap_s = std::chrono::duration<double>(speed_timeout_).count();
  if (!reckoning_->add(toSeconds(stamp), velocity, *orientation_, max_gap_s)) return;
  if (!publishing_) return;
  estimate_.publish(speed.header().stamp(), robotId(),
                    {.position_m = reckoning_->position(),
                     .orientation = *orientation_,
                     .velocity_m_s = reckoning_->velocity(),
                     .body_rates_rad_s = gyro_,
                     .horizontal_stddev_m = std::nullopt});  // not known
}

absl::StatusOr<Eigen::Vector3d> EstimatePositionWithLinearSpeedBehavior::initialPosition(
    TimePoint at) {
  const auto& p = parameters();
  const bool given[3] = {p.has_initial_x_m(), p.has_initial_y_m(), p.has_initial_z_m()};
  if (given[0] && given[1] && given[2]) {
    return Eigen::Vector3d(p.initial_x_m(), p.initial_y_m(), p.initial_z_m());
  }
  if (given[0] || given[1] || given[2]) {
    std::vector<std::string> missing;
    const char* names[3] = {"initial_x_m", "initial_y_m", "initial_z_m"};
    for (int i = 0; i < 3; ++i) {
      if (!given[i]) missing.push_back(std::string("'") + names[i] + "'");
    }
    std::string list = missing[0];
    for (size_t i = 1; i < missing.size(); ++i) list += " and " + missing[i];
    return absl::InvalidArgumentError(
        "parameter " + list + (missing.size() > 1 ? " are" : " is") +
        " missing: give initial_x_m, initial_y_m and initial_z_m together, or none of them to "
        "start from the latest pose estimate");
  }
  const std::string topic = flight::poseEstimateTopic(robotId());
  auto sample = channel_->getLatest(topic, flight::kChannelReadTimeout);
  if (!sample.ok()) {
    return absl::FailedPreconditionError(
        sample.status().code() == absl::StatusCode::kNotFound
            ? "no pose estimate on " + topic +
                  " to start from: give initial_x_m, initial_y_m and initial_z_m"
            : "cannot read the pose estimate on " + topic + ": " +
                  std::string(sample.status().message()));
  }
  v1::PoseStamped pose;
  if (!sample->sample().UnpackTo(&pose)) {
    return absl::FailedPreconditionError(topic + " does not carry behaviorlib.v1.PoseStamped");
  }
  if (auto stale = flight::staleness([&] { return "the latest pose estimate on " + topic; },
                                     pose.header(), at, max_initial_estimate_age_)) {
    return absl::FailedPreconditionError(
        *stale + ": too old to start from; give initial_x_m, initial_y_m and initial_z_m");
  }
  Eigen::Vector3d position = toEigen(pose.pose().position_m());
  // Carry it over its age along the velocity estimate, when there is one.
  auto twist_sample =
      channel_->getLatest(flight::twistEstimateTopic(robotId()), flight::kChannelReadTimeout);
  v1::TwistStamped twist;
  if (twist_sample.ok() && twist_sample->sample().UnpackTo(&twist)) {
    const double age = std::chrono::duration<double>(at - flight::stampTime(pose.header())).count();
    const Eigen::Vector3d velocity = toEigen(twist.twist().linear_m_s());
    if (age > 0 && velocity.allFinite()) position += velocity * age;
  }
  if (!position.allFinite()) {
    return absl::FailedPreconditionError("the latest pose estimate on " + topic +
                                         " is not a finite position");
  }
  return position;
}

absl::Status EstimatePositionWithLinearSpeedBehavior::onActivate() {
  const TimePoint start = now();
  auto initial = initialPosition(start);
  if (!initial.ok()) return initial.status();
  const std::string robot = robotId();
  start_s_ = toSeconds(start);
  reckoning_.emplace(*initial, start_s_);
  max_speed_m_s_ = parameters().max_speed_m_s();
  orientation_.reset();
  gyro_.setZero();
  speed_.emplace(sensorTopic(robot, "linear_speed"), speed_timeout_, frozen_timeout_);
  imu_.emplace(sensorTopic(robot, "imu"), imu_timeout_, frozen_timeout_);
  implausible_.clear();
  estimate_.reset();
  running_ = publishing_ = true;
  setMaximumExecutionTime(seconds(parameters().max_duration_s()));
  activated_at_ = start;
  active_ = true;
  // The orientation is read at the speed samples' rate: the newest is enough.
  imu_sub_ = channel_->subscribeTyped<v1::Imu>(
      sensorTopic(robot, "imu"), {.mode = v1::DELIVERY_MODE_LATEST, .send_latest_first = true},
      onWorker<v1::Imu>([this](const v1::Imu& m) { onImu(m); }, Delivery::kLatest));
  speed_sub_ = channel_->subscribeTyped<v1::TwistStamped>(
      sensorTopic(robot, "linear_speed"), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 500},
      onWorker<v1::TwistStamped>([this](const v1::TwistStamped& m) { onSpeed(m); }));
  return absl::OkStatus();
}

void EstimatePositionWithLinearSpeedBehavior::stopSubscriptions() {
  running_ = publishing_ = false;
  imu_sub_.reset();
  speed_sub_.reset();
}

void EstimatePositionWithLinearSpeedBehavior::onDeactivate() {
  active_ = false;
  stopSubscriptions();
}

void EstimatePositionWithLinearSpeedBehavior::onPause() { publishing_ = false; }

void EstimatePositionWithLinearSpeedBehavior::onResume() { publishing_ = true; }

absl::Status EstimatePositionWithLinearSpeedBehavior::onModify(
    const v1::EstimatePositionWithLinearSpeedParameters& p) {
  const auto& current = parameters();
  if (p.has_initial_x_m() != current.has_initial_x_m() ||
      p.has_initial_y_m() != current.has_initial_y_m() ||
      p.has_initial_z_m() != current.has_initial_z_m() ||
      p.initial_x_m() != current.initial_x_m() || p.initial_y_m() != current.initial_y_m() ||
      p.initial_z_m() != current.initial_z_m()) {
    return absl::InvalidArgumentError(
        "parameters 'initial_x_m', 'initial_y_m', 'initial_z_m' cannot change while active "
        "(deactivate and activate again to restart the dead reckoning)");
  }
  { max_speed_m_s_ = p.max_speed_m_s(); }
  setMaximumExecutionTime(seconds(p.max_duration_s()));
  return absl::OkStatus();
}

Situation EstimatePositionWithLinearSpeedBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) {
    const double ratio = driftBound() / parameters().max_drift_m();
    return Situation::ok(std::clamp(1.0 - ratio, 0.0, 1.0));
  }
  const TimePoint t = now();
  const std::string robot = robotId();
  if (auto problem = freshSampleProblem<v1::TwistStamped>(
          *channel_, sensorTopic(robot, "linear_speed"), t, 2 * speed_timeout_)) {
    return Situation::infeasible(problem->code, problem->reason);
  }
  if (auto problem =
          freshSampleProblem<v1::Imu>(*channel_, sensorTopic(robot, "imu"), t, 2 * imu_timeout_)) {
    return Situation::infeasible(problem->code, problem->reason);
  }
  return Situation::ok();
}

Verdict EstimatePositionWithLinearSpeedBehavior::checkProgress() {
  if (!implausible_.empty()) return Verdict::finish(implausible_);
  const double bound = driftBound();
  if (bound > parameters().max_drift_m()) {
    return Verdict::finish("the dead-reckoning drift bound reached " + flight::fixed2(bound) +
                           " m (" + flight::fixed2(drift_ratio_ * 100) + " % of " +
                           flight::fixed2(reckoning_->distanceM()) + " m travelled + " +
                           flight::fixed2(drift_rate_m_s_ * 1000) + " mm/s over " +
                           flight::fixed2(reckoning_->lastTimeS() - start_s_) +
                           " s), beyond max_drift_m " + flight::fixed2(parameters().max_drift_m()));
  }
  return Verdict::keepGoing();
}

Verdict EstimatePositionWithLinearSpeedBehavior::checkProcesses() {
  const TimePoint t = now();
  if (!estimate_.error().ok()) {
    return Verdict::finish("cannot publish the estimate: " +
                           std::string(estimate_.error().message()));
  }
  if (reckoning_ && !reckoning_->position().allFinite()) {
    return Verdict::finish("the dead-reckoned position is no longer a finite number");
  }
  for (const SensorStream* stream : {&*speed_, &*imu_}) {
    if (auto problem = stream->problem(t, activated_at_)) return Verdict::finish(*problem);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
