#include "behaviorlib/multi_sensor_fusion/ekf_behavior.h"

#include <cmath>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::fusion {
namespace {

std::string topic(const std::string& robot, const char* name) {
  return "robots/" + robot + "/" + name;
}

Eigen::Vector3d vec(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

BehaviorOptions ekfOptions() {
  BehaviorOptions o = flight::flightBehaviorOptions(Duration::zero());
  o.frequency_hz = 10.0;
  return o;
}

}  // namespace

EkfSelfLocalizationBehavior::EkfSelfLocalizationBehavior(channel::ChannelClient* channel)
    : Behavior(ekfOptions()), channel_(channel), estimate_(channel) {}

EkfSelfLocalizationBehavior::~EkfSelfLocalizationBehavior() { stopSubscriptions(); }

absl::Status EkfSelfLocalizationBehavior::onConfigure(
    const config::v1::SelfLocalizeWithEkfSensorFusionConfig& config) {
  imu_timeout_ = behaviorlib::seconds(config.imu_timeout_s());
  gps_timeout_ = behaviorlib::seconds(config.gps_timeout_s());
  start_timeout_ = behaviorlib::seconds(config.start_timeout_s());
  max_horizontal_stddev_m_ = config.max_horizontal_stddev_m();
  max_rejected_ratio_ = config.max_rejected_ratio();
  gps_window_ = config.gps_window();
  baro_stddev_m_ = config.baro_stddev_m();
  linear_speed_stddev_m_s_ = config.linear_speed_stddev_m_s();
  yaw_stddev_rad_ = config.yaw_stddev_rad();
  noise_.gyro_noise_rad_s = config.gyro_noise_rad_s();
  noise_.accel_noise_m_s2 = config.accel_noise_m_s2();
  noise_.baro_drift_m_sqrt_s = config.baro_drift_m_sqrt_s();
  if (noise_.baro_drift_m_sqrt_s == 0.0) noise_.initial_baro_offset_stddev_m = 0.0;
  return absl::OkStatus();
}

void EkfSelfLocalizationBehavior::onImu(const v1::Imu& imu) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(imu.header());
  const auto& qo = imu.orientation();
  // Published every second sample, counted before this one.
  const bool every_second = ins_.imuCount() % 2 == 0;
  const bool predicted = ins_.imu(
      stamp.time_since_epoch(), Eigen::Quaterniond(qo.w(), qo.x(), qo.y(), qo.z()).normalized(),
      vec(imu.angular_velocity_rad_s()), vec(imu.linear_acceleration_m_s2()));
  last_imu_ = stamp;
  if (!predicted || !publishing_ || !every_second) return;
  const InsEkf& ekf = ins_.ekf();
  estimate_.publish(imu.header().stamp(), robotId(),
                    {.position_m = ekf.position(),
                     .orientation = ekf.orientation(),
                     .velocity_m_s = ekf.velocity(),
                     .body_rates_rad_s = ins_.bodyRates(),
                     .horizontal_stddev_m = ekf.horizontalStddevM()});
}

void EkfSelfLocalizationBehavior::onGps(const v1::PositionFix& fix) {
  if (!running_) return;
  last_gps_ = flight::stampTime(fix.header());
  const Eigen::Vector3d position = vec(fix.position_m());
  InsEkf& ekf = ins_.ekf();
  if (!ekf.initialized()) {
    if (ins_.imuOrientation() && position.allFinite())
      ekf.initialize(position, Eigen::Vector3d::Zero(), *ins_.imuOrientation());
    return;
  }
  const UpdateResult r = ekf.updatePosition(position, std::max(fix.horizontal_stddev_m(), 0.05),
                                            std::max(fix.vertical_stddev_m(), 0.05));
  gps_accepted_.push_back(r.accepted);
  while (gps_accepted_.size() > static_cast<size_t>(gps_window_)) gps_accepted_.pop_front();
}

void EkfSelfLocalizationBehavior::onBaro(const v1::Altitude& altitude) {
  if (!running_ || !use_barometer_) return;
  ins_.altitude(altitude.altitude_m(), altitude.stddev_m());
}

void EkfSelfLocalizationBehavior::onLinearSpeed(const v1::TwistStamped& twist) {
  if (!running_ || !use_linear_speed_) return;
  ins_.bodyVelocity(vec(twist.twist().linear_m_s()));
}

absl::Status EkfSelfLocalizationBehavior::onActivate() {
  ins_ = InsFeed(noise_, {.use_imu_yaw = parameters().use_imu_yaw(),
                          .yaw_stddev_rad = yaw_stddev_rad_,
                          .yaw_every = 20,
                          .baro_stddev_m = baro_stddev_m_,
                          .linear_speed_stddev_m_s = linear_speed_stddev_m_s_});
  last_imu_.reset();
  last_gps_.reset();
  gps_accepted_.clear();
  estimate_.reset();
  use_linear_speed_ = parameters().use_linear_speed();
  use_barometer_ = parameters().use_barometer();
  running_ = publishing_ = true;
  const std::string robot = robotId();
  // Every IMU sample predicts: a queue, not latest-only.
  imu_sub_ = channel_->subscribeTyped<v1::Imu>(
      topic(robot, "imu"), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 2000},
      onWorker<v1::Imu>([this](const v1::Imu& m) { onImu(m); }, Delivery::kEvery, 2000));
  const channel::SubscribeOptions queued{.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 200};
  gps_sub_ = channel_->subscribeTyped<v1::PositionFix>(
      topic(robot, "gps"), queued,
      onWorker<v1::PositionFix>([this](const v1::PositionFix& m) { onGps(m); }));
  baro_sub_ = channel_->subscribeTyped<v1::Altitude>(
      topic(robot, "baro"), queued,
      onWorker<v1::Altitude>([this](const v1::Altitude& m) { onBaro(m); }));
  speed_sub_ = channel_->subscribeTyped<v1::TwistStamped>(
      topic(robot, "linear_speed"), queued,
      onWorker<v1::TwistStamped>([this](const v1::TwistStamped& m) { onLinearSpeed(m); }));
  activated_at_ = now();
  active_ = true;
  return absl::OkStatus();
}

void EkfSelfLocalizationBehavior::stopSubscriptions() {
  running_ = publishing_ = false;
  imu_sub_.reset();
  gps_sub_.reset();
  baro_sub_.reset();
  speed_sub_.reset();
}

void EkfSelfLocalizationBehavior::onDeactivate() {
  active_ = false;
  stopSubscriptions();
}

void EkfSelfLocalizationBehavior::onPause() { publishing_ = false; }

void EkfSelfLocalizationBehavior::onResume() { publishing_ = true; }

absl::Status EkfSelfLocalizationBehavior::onModify(
    const v1::SelfLocalizeWithEkfSensorFusionParameters& p) {
  use_linear_speed_ = p.use_linear_speed();
  use_barometer_ = p.use_barometer();
  ins_.setUseImuYaw(p.use_imu_yaw());
  return absl::OkStatus();
}

Situation EkfSelfLocalizationBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  if (auto missing = flight::missingSensor(
          *channel_, robotId(), {{"imu", imu_timeout_, "IMU"}, {"gps", gps_timeout_, "GPS"}},
          now())) {
    return Situation::infeasible(missing->code, missing->reason);
  }
  return Situation::ok();
}

Verdict EkfSelfLocalizationBehavior::checkProgress() {
  const InsEkf& ekf = ins_.ekf();
  if (!ekf.initialized()) return Verdict::keepGoing();
  if (ekf.horizontalStddevM() > max_horizontal_stddev_m_) {
    return Verdict::finish("the filter is diverging: horizontal standard deviation " +
                           flight::fixed2(ekf.horizontalStddevM()) + " m (limit " +
                           flight::fixed2(max_horizontal_stddev_m_) + " m)");
  }
  if (gps_accepted_.size() >= static_cast<size_t>(gps_window_)) {
    const auto rejected = std::count(gps_accepted_.begin(), gps_accepted_.end(), false);
    if (static_cast<double>(rejected) >
        max_rejected_ratio_ * static_cast<double>(gps_accepted_.size())) {
      return Verdict::finish(
          "the filter rejects the GPS: " + std::to_string(rejected) + " of the last " +
          std::to_string(gps_accepted_.size()) +
          " fixes disagree with the prediction (garbage GPS, or a diverged filter)");
    }
  }
  return Verdict::keepGoing();
}

Verdict EkfSelfLocalizationBehavior::checkProcesses() {
  const TimePoint t = now();
  if (!estimate_.error().ok()) {
    return Verdict::finish("cannot publish the estimate: " +
                           std::string(estimate_.error().message()));
  }
  const InsEkf& ekf = ins_.ekf();
  if (!ekf.finite()) return Verdict::finish("the filter's state is no longer a finite number");
  if (!ekf.initialized()) {
    if (t - activated_at_ > start_timeout_) {
      return Verdict::finish(std::string("the filter did not start within ") +
                             flight::secondsText(start_timeout_) +
                             (last_imu_ ? ": no GPS fix arrived" : ": no IMU sample arrived"));
    }
    return Verdict::keepGoing();
  }
  const std::string robot = robotId();
  if (last_imu_ && t - *last_imu_ > imu_timeout_) {
    return Verdict::finish("the IMU on " + topic(robot, "imu") + " is silent: last sample " +
                           flight::secondsText(t - *last_imu_) + " ago (limit " +
                           flight::secondsText(imu_timeout_) + ")");
  }
  if (last_gps_ && t - *last_gps_ > gps_timeout_) {
    return Verdict::finish("the GPS on " + topic(robot, "gps") + " is silent: last fix " +
                           flight::secondsText(t - *last_gps_) + " ago (limit " +
                           flight::secondsText(gps_timeout_) + ")");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::fusion
