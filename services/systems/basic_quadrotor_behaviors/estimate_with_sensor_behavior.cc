#include "behaviorlib/basic_quadrotor_behaviors/estimate_with_sensor_behavior.h"

#include <cmath>
#include <tuple>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::basic {

EstimatePositionWithSensorBehavior::EstimatePositionWithSensorBehavior(
    channel::ChannelClient* channel)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())),
      channel_(channel),
      estimate_(channel) {}

EstimatePositionWithSensorBehavior::~EstimatePositionWithSensorBehavior() { stopSubscriptions(); }

absl::Status EstimatePositionWithSensorBehavior::onConfigure(
    const config::v1::EstimatePositionWithSensorConfig& config) {
  imu_timeout_ = seconds(config.imu_timeout_s());
  gps_timeout_ = seconds(config.gps_timeout_s());
  baro_timeout_ = seconds(config.baro_timeout_s());
  frozen_timeout_ = seconds(config.frozen_timeout_s());
  noise_.accel_noise_m_s2 = config.accel_noise_m_s2();
  noise_.accel_bias_walk_m_s2 = config.accel_bias_walk_m_s2();
  noise_.baro_drift_m = config.baro_drift_m();
  noise_.initial_baro_offset_stddev_m = config.baro_offset_stddev_m();
  return absl::OkStatus();
}

void EstimatePositionWithSensorBehavior::onImu(const v1::Imu& imu) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(imu.header());
  const Eigen::Vector3d gyro = toEigen(imu.angular_velocity_rad_s());
  const Eigen::Vector3d force = toEigen(imu.linear_acceleration_m_s2());
  Eigen::VectorXd value(6);
  value << gyro, force;
  imu_->add(stamp, value);
  const auto orientation = toOrientation(imu.orientation());
  if (!orientation) return;
  const double t = toSeconds(stamp);
  if (last_imu_s_ && !(t > *last_imu_s_)) return;  // a repeated or older sample
  if (last_imu_s_) filter_.predict(*orientation, force, t - *last_imu_s_);
  last_imu_s_ = t;
  last_gyro_ = gyro;
  if (!filter_.initialized() || !publishing_ || imu_count_++ % 2 != 0) return;
  estimate_.publish(imu.header().stamp(), robotId(),
                    {.position_m = filter_.position(),
                     .orientation = *orientation,
                     .velocity_m_s = filter_.velocity(),
                     .body_rates_rad_s = gyro,
                     .horizontal_stddev_m = std::nullopt});  // not known
}

void EstimatePositionWithSensorBehavior::countRejection(bool accepted, double innovation_m,
                                                        const std::string& what, uint32_t* run) {
  if (accepted) {
    *run = 0;
    return;
  }
  if (++*run > max_rejected_ && jump_.empty()) {
    jump_ = what + " jumped " + flight::fixed2(innovation_m) + " m from the estimate, " +
            std::to_string(*run) + " samples in a row beyond max_innovation_m " +
            flight::fixed2(max_innovation_m_) + " (max_rejected_samples " +
            std::to_string(max_rejected_) + "): a faulty sensor, or a jump of the vehicle";
  }
}

void EstimatePositionWithSensorBehavior::onFix(const v1::PositionFix& fix) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(fix.header());
  const Eigen::Vector3d position = toEigen(fix.position_m());
  gps_->add(stamp, position);
  const double t = toSeconds(stamp);
  const auto r = filter_.updateFix(position, fix.horizontal_stddev_m(), fix.vertical_stddev_m(), t,
                                   last_imu_s_.value_or(t), max_innovation_m_);
  countRejection(r.accepted, r.innovation_m, "the position fix on " + gps_->topic(),
                 &rejected_fixes_);
}

void EstimatePositionWithSensorBehavior::onAltitude(const v1::Altitude& altitude) {
  if (!running_ || !use_barometer_) return;
  baro_->add(flight::stampTime(altitude.header()),
             Eigen::VectorXd::Constant(1, altitude.altitude_m()));
  if (!filter_.initialized()) return;
  const auto r = filter_.updateAltitude(altitude.altitude_m(), std::max(altitude.stddev_m(), 0.05),
                                        max_innovation_m_);
  countRejection(r.accepted, r.innovation_m, "the altitude on " + baro_->topic(),
                 &rejected_altitudes_);
}

absl::Status EstimatePositionWithSensorBehavior::onActivate() {
  const std::string robot = robotId();
  filter_ = SensorPositionFilter(noise_);
  use_barometer_ = parameters().use_barometer();
  max_innovation_m_ = parameters().max_innovation_m();
  max_rejected_ = parameters().max_rejected_samples();
  rejected_fixes_ = rejected_altitudes_ = 0;
  last_imu_s_.reset();
  imu_count_ = 0;
  imu_.emplace(sensorTopic(robot, "imu"), imu_timeout_, frozen_timeout_);
  gps_.emplace(sensorTopic(robot, "gps"), gps_timeout_, frozen_timeout_);
  baro_.emplace(sensorTopic(robot, "baro"), baro_timeout_, frozen_timeout_);
  jump_.clear();
  estimate_.reset();
  running_ = publishing_ = true;
  activated_at_ = now();
  active_ = true;
  // Every IMU sample predicts: a queue, not latest-only.
  imu_sub_ = channel_->subscribeTyped<v1::Imu>(
      sensorTopic(robot, "imu"), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 2000},
      onWorker<v1::Imu>([this](const v1::Imu& m) { onImu(m); }, Delivery::kEvery, 2000));
  const channel::SubscribeOptions queued{.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 200};
  gps_sub_ = channel_->subscribeTyped<v1::PositionFix>(
      sensorTopic(robot, "gps"), queued,
      onWorker<v1::PositionFix>([this](const v1::PositionFix& m) { onFix(m); }));
  if (parameters().use_barometer()) {
    baro_sub_ = channel_->subscribeTyped<v1::Altitude>(
        sensorTopic(robot, "baro"), queued,
        onWorker<v1::Altitude>([this](const v1::Altitude& m) { onAltitude(m); }));
  }
  return absl::OkStatus();
}

void EstimatePositionWithSensorBehavior::stopSubscriptions() {
  running_ = publishing_ = false;
  imu_sub_.reset();
  gps_sub_.reset();
  baro_sub_.reset();
}

void EstimatePositionWithSensorBehavior::onDeactivate() {
  active_ = false;
  stopSubscriptions();
}

void EstimatePositionWithSensorBehavior::onPause() { publishing_ = false; }

void EstimatePositionWithSensorBehavior::onResume() { publishing_ = true; }

absl::Status EstimatePositionWithSensorBehavior::onModify(
    const v1::EstimatePositionWithSensorParameters& p) {
  if (p.use_barometer() != use_barometer_) {
    return absl::InvalidArgumentError(
        "parameter 'use_barometer' cannot change while active (deactivate and activate again)");
  }
  max_innovation_m_ = p.max_innovation_m();
  max_rejected_ = p.max_rejected_samples();
  return absl::OkStatus();
}

Situation EstimatePositionWithSensorBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  const TimePoint t = now();
  const std::string robot = robotId();
  // Sampling at their rates, the sensors' latest samples are a little older
  // than a timeout at worst before activation, where the channel read itself
  // takes time.
  if (auto problem =
          freshSampleProblem<v1::Imu>(*channel_, sensorTopic(robot, "imu"), t, 2 * imu_timeout_)) {
    return Situation::infeasible(problem->code, problem->reason);
  }
  if (auto problem = freshSampleProblem<v1::PositionFix>(*channel_, sensorTopic(robot, "gps"), t,
                                                         2 * gps_timeout_)) {
    return Situation::infeasible(problem->code, problem->reason);
  }
  if (auto problem = freshSampleProblem<v1::Altitude>(*channel_, sensorTopic(robot, "baro"), t,
                                                      2 * baro_timeout_)) {
    Situation situation = Situation::ok(0.5);
    situation.add(problem->code, problem->reason +
                                     " (activate with use_barometer: false to take the height "
                                     "from the position fix alone)");
    return situation;
  }
  return Situation::ok();
}

Verdict EstimatePositionWithSensorBehavior::checkProgress() {
  if (!jump_.empty()) return Verdict::finish(jump_);
  return Verdict::keepGoing();
}

Verdict EstimatePositionWithSensorBehavior::checkProcesses() {
  const TimePoint t = now();
  if (!estimate_.error().ok()) {
    return Verdict::finish("cannot publish the estimate: " +
                           std::string(estimate_.error().message()));
  }
  if (!filter_.finite()) return Verdict::finish("the filter's state is no longer a finite number");
  for (const SensorStream* stream : {&*imu_, &*gps_, &*baro_}) {
    if (stream == &*baro_ && !use_barometer_) continue;
    if (auto problem = stream->problem(t, activated_at_)) return Verdict::finish(*problem);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
