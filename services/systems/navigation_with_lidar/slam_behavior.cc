#include "behaviorlib/navigation_with_lidar/slam_behavior.h"

#include <algorithm>
#include <cmath>
#include <utility>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::nav {
namespace {

std::string topic(const std::string& robot, const char* name) {
  return "robots/" + robot + "/" + name;
}

Eigen::Vector3d vec(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

double seconds(TimePoint t) { return std::chrono::duration<double>(t.time_since_epoch()).count(); }

BehaviorOptions slamOptions() {
  BehaviorOptions o = flight::flightBehaviorOptions(Duration::zero());
  o.frequency_hz = 10.0;
  return o;
}

// The estimate's history covers the scans' latency (a scan is cast and
// sent after its stamp) with room to spare.
constexpr Duration kHistory = std::chrono::seconds(2);
constexpr Duration kPoseMatch = std::chrono::milliseconds(50);
// A match direction with this variance (m^2, rad^2) carries no information.
constexpr double kNoInformation = 1.0;

}  // namespace

SlamBehavior::SlamBehavior(channel::ChannelClient* channel, const Eigen::Vector3d& lidar_mount_m)
    : Behavior(slamOptions()),
      channel_(channel),
      lidar_mount_m_(lidar_mount_m),
      estimate_(channel) {
  // The start pose is given: the filter starts sure of it.
  noise_.initial_position_stddev_m = 0.02;
  noise_.initial_velocity_stddev_m_s = 0.1;
}

SlamBehavior::~SlamBehavior() { stopSubscriptions(); }

absl::Status SlamBehavior::onConfigure(
    const config::v1::SelfLocalizeAndMapWithLidarConfig& config) {
  imu_timeout_ = behaviorlib::seconds(config.imu_timeout_s());
  lidar_timeout_ = behaviorlib::seconds(config.lidar_timeout_s());
  start_timeout_ = behaviorlib::seconds(config.start_timeout_s());
  max_degenerate_ = behaviorlib::seconds(config.max_degenerate_s());
  max_rejected_ratio_ = config.max_rejected_ratio();
  match_window_ = config.match_window();
  max_horizontal_stddev_m_ = config.max_horizontal_stddev_m();
  baro_stddev_m_ = config.baro_stddev_m();
  linear_speed_stddev_m_s_ = config.linear_speed_stddev_m_s();
  imu_yaw_stddev_rad_ = config.imu_yaw_stddev_rad();
  noise_.gyro_noise_rad_s = config.gyro_noise_rad_s();
  noise_.accel_noise_m_s2 = config.accel_noise_m_s2();
  slam_config_.grid.resolution_m = config.resolution_m();
  slam_config_.grid.likelihood_sigma_m = config.likelihood_sigma_m();
  slam_config_.grid.max_extent_m = config.max_extent_m();
  slam_config_.scan.max_free_range_m = config.max_free_range_m();
  const double cells = slam_config_.grid.max_extent_m / slam_config_.grid.resolution_m;
  if (cells * cells > 2.5e7) {
    return absl::InvalidArgumentError(
        "max_extent_m / resolution_m: a map of more than 25 million cells (about 1 GB)");
  }
  slam_config_.match.step_m = slam_config_.grid.resolution_m;
  return absl::OkStatus();
}

Pose2 SlamBehavior::currentPose() const {
  return {ekf().position().x(), ekf().position().y(), yawOf(ekf().orientation())};
}

std::optional<Pose2> SlamBehavior::poseAt(TimePoint stamp) const {
  const Stamped* best = nullptr;
  for (const auto& h : history_) {
    if (!best || std::chrono::abs(h.stamp - stamp) < std::chrono::abs(best->stamp - stamp))
      best = &h;
  }
  if (!best || std::chrono::abs(best->stamp - stamp) > kPoseMatch) return std::nullopt;
  return best->pose;
}

void SlamBehavior::start(const Eigen::Quaterniond& imu_orientation) {
  const auto& p = parameters();
  const double yaw = p.has_initial_yaw_rad() ? p.initial_yaw_rad() : yawOf(imu_orientation);
  const Eigen::Quaterniond orientation =
      Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ())) *
      tiltOf(imu_orientation);
  const Eigen::Vector3d position(p.initial_position_m().x(), p.initial_position_m().y(),
                                 last_baro_m_.value_or(p.initial_position_m().z()));
  ekf().initialize(position, Eigen::Vector3d::Zero(), orientation.normalized());
  slam_->start({position.x(), position.y(), yaw});
}

void SlamBehavior::publishEstimate(const v1::Header& imu_header) {
  estimate_.publish(imu_header.stamp(), robotId(),
                    {.position_m = ekf().position(),
                     .orientation = ekf().orientation(),
                     .velocity_m_s = ekf().velocity(),
                     .body_rates_rad_s = ins_.bodyRates(),
                     .horizontal_stddev_m = ekf().horizontalStddevM()});
}

void SlamBehavior::onImu(const v1::Imu& imu) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(imu.header());
  const auto& qo = imu.orientation();
  const Eigen::Quaterniond orientation =
      Eigen::Quaterniond(qo.w(), qo.x(), qo.y(), qo.z()).normalized();
  ins_.imu(stamp.time_since_epoch(), orientation, vec(imu.angular_velocity_rad_s()),
           vec(imu.linear_acceleration_m_s2()));
  // The filter starts at the first sample with an orientation (after the
  // feed, which therefore did not predict with it), and predicts from the
  // next one on.
  if (!ekf().initialized() && orientation.coeffs().allFinite()) start(orientation);
  last_imu_ = stamp;
  if (!ekf().initialized()) return;
  history_.push_back({stamp, currentPose()});
  while (!history_.empty() && stamp - history_.front().stamp > kHistory) history_.pop_front();
  if (publishing_ && ins_.imuCount() % 2 == 0) publishEstimate(imu.header());
}

void SlamBehavior::onBaro(const v1::Altitude& altitude) {
  if (!running_) return;
  last_baro_m_ = altitude.altitude_m();
  ins_.altitude(altitude.altitude_m(), altitude.stddev_m());
}

void SlamBehavior::onLinearSpeed(const v1::TwistStamped& twist) {
  if (!running_) return;
  ins_.bodyVelocity(vec(twist.twist().linear_m_s()));
}

void SlamBehavior::onScan(const v1::LaserScan& scan) {
  if (!running_) return;
  const TimePoint stamp = flight::stampTime(scan.header());
  last_scan_ = stamp;
  if (!ekf().initialized()) return;
  const std::optional<Pose2> predicted = poseAt(stamp);
  if (!predicted) return;  // older than the history, or before the start
  PlanarScan planar;
  planar.angle_min_rad = scan.angle_min_rad();
  planar.angle_increment_rad = scan.angle_increment_rad();
  planar.range_min_m = scan.range_min_m();
  planar.range_max_m = scan.range_max_m();
  planar.ranges_m.assign(scan.ranges_m().begin(), scan.ranges_m().end());
  // The vehicle is not below the ground, whatever the barometer says: a
  // landed vehicle's level rays are not ground hits.
  const LevelScan level = levelScan(planar, tiltOf(ekf().orientation()), lidar_mount_m_,
                                    std::max(0.0, ekf().position().z()), slam_config_.scan);
  const ScanUpdate u =
      slam_->addScan(level, *predicted, seconds(stamp), std::abs(scan.angle_increment_rad()));
  bool accepted = false;
  if (u.matched) {
    // The correction found at the scan's stamp, applied to the state now.
    const Pose2 now = currentPose();
    const Eigen::Vector2d shift = u.pose.position() - predicted->position();
    const Eigen::Matrix2d covariance = u.covariance.topLeftCorner<2, 2>();
    accepted = ekf().updateHorizontalPosition(now.position() + shift, covariance).accepted;
    if (u.covariance(2, 2) < kNoInformation) {
      ekf().updateYaw(wrapAngle(now.yaw_rad + wrapAngle(u.pose.yaw_rad - predicted->yaw_rad)),
                      std::sqrt(u.covariance(2, 2)));
    }
    match_accepted_.push_back(accepted);
    while (match_accepted_.size() > static_cast<size_t>(match_window_)) match_accepted_.pop_front();
  }
  if (!u.matched || u.degenerate) {
    if (!degenerate_since_) degenerate_since_ = stamp;
    degenerate_reason_ = !u.matched ? (u.points < slam_config_.match.min_points
                                           ? std::to_string(u.points) + " points hit a surface"
                                           : "only " + std::to_string(u.inliers) + " of " +
                                                 std::to_string(u.points) + " points fit the map")
                                    : "the scan cannot tell positions apart along one direction";
  } else {
    degenerate_since_.reset();
  }
}

absl::Status SlamBehavior::onActivate() {
  ins_ = fusion::InsFeed(noise_, {.use_imu_yaw = parameters().use_imu_yaw(),
                                  .yaw_stddev_rad = imu_yaw_stddev_rad_,
                                  .yaw_every = 20,
                                  .baro_stddev_m = baro_stddev_m_,
                                  .linear_speed_stddev_m_s = linear_speed_stddev_m_s_});
  estimate_.reset();
  slam_ = std::make_unique<LidarSlam>(slam_config_);
  last_imu_.reset();
  last_scan_.reset();
  last_baro_m_.reset();
  history_.clear();
  match_accepted_.clear();
  degenerate_since_.reset();
  running_ = publishing_ = true;
  const std::string robot = robotId();
  imu_sub_ = channel_->subscribeTyped<v1::Imu>(
      topic(robot, "imu"), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 2000},
      onWorker<v1::Imu>([this](const v1::Imu& m) { onImu(m); }, Delivery::kEvery, 2000));
  const channel::SubscribeOptions queued{.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 200};
  baro_sub_ = channel_->subscribeTyped<v1::Altitude>(
      topic(robot, "baro"), queued,
      onWorker<v1::Altitude>([this](const v1::Altitude& m) { onBaro(m); }));
  speed_sub_ = channel_->subscribeTyped<v1::TwistStamped>(
      topic(robot, "linear_speed"), queued,
      onWorker<v1::TwistStamped>([this](const v1::TwistStamped& m) { onLinearSpeed(m); }));
  scan_sub_ = channel_->subscribeTyped<v1::LaserScan>(
      topic(robot, "lidar/scan"), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 20},
      onWorker<v1::LaserScan>([this](const v1::LaserScan& m) { onScan(m); }, Delivery::kEvery, 20));
  activated_at_ = now();
  active_ = true;
  return absl::OkStatus();
}

void SlamBehavior::stopSubscriptions() {
  running_ = publishing_ = false;
  imu_sub_.reset();
  baro_sub_.reset();
  speed_sub_.reset();
  scan_sub_.reset();
}

void SlamBehavior::onDeactivate() {
  active_ = false;
  stopSubscriptions();
}

void SlamBehavior::onPause() { publishing_ = false; }

void SlamBehavior::onResume() { publishing_ = true; }

absl::Status SlamBehavior::onModify(const v1::SelfLocalizeAndMapWithLidarParameters& p) {
  ins_.setUseImuYaw(p.use_imu_yaw());
  return absl::OkStatus();
}

Situation SlamBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  if (auto missing =
          flight::missingSensor(*channel_, robotId(),
                                {{"imu", imu_timeout_, "IMU"},
                                 {"linear_speed", imu_timeout_ * 4, "body speed (optical flow)"},
                                 {"lidar/scan", lidar_timeout_, "lidar"}},
                                now())) {
    return Situation::infeasible(missing->code, missing->reason);
  }
  return Situation::ok();
}

Verdict SlamBehavior::checkProgress() {
  if (!ekf().initialized()) return Verdict::keepGoing();
  if (degenerate_since_ && now() - *degenerate_since_ > max_degenerate_) {
    return Verdict::finish(
        "scan matching has been degenerate for " + flight::secondsText(now() - *degenerate_since_) +
        " (limit " + flight::secondsText(max_degenerate_) + "; last: " + degenerate_reason_ +
        "): the lidar sees too little structure to localize (a long featureless corridor, an "
        "open field); the estimate runs on odometry alone");
  }
  if (match_accepted_.size() >= static_cast<size_t>(match_window_)) {
    const auto rejected = std::count(match_accepted_.begin(), match_accepted_.end(), false);
    if (static_cast<double>(rejected) >
        max_rejected_ratio_ * static_cast<double>(match_accepted_.size())) {
      return Verdict::finish("the filter rejects the scan matches: " + std::to_string(rejected) +
                             " of the last " + std::to_string(match_accepted_.size()) +
                             " disagree with the odometry (a lidar giving garbage, or a map that "
                             "no longer fits)");
    }
  }
  if (ekf().horizontalStddevM() > max_horizontal_stddev_m_) {
    return Verdict::finish("the estimate is diverging: horizontal standard deviation " +
                           flight::fixed2(ekf().horizontalStddevM()) + " m (limit " +
                           flight::fixed2(max_horizontal_stddev_m_) + " m)");
  }
  return Verdict::keepGoing();
}

Verdict SlamBehavior::checkProcesses() {
  const TimePoint t = now();
  if (!estimate_.error().ok()) {
    return Verdict::finish("cannot publish the estimate: " +
                           std::string(estimate_.error().message()));
  }
  if (!ekf().finite()) return Verdict::finish("the filter's state is no longer a finite number");
  if (!ekf().initialized()) {
    if (t - activated_at_ > start_timeout_) {
      return Verdict::finish(std::string("the filter did not start within ") +
                             flight::secondsText(start_timeout_) + ": no IMU sample arrived");
    }
    return Verdict::keepGoing();
  }
  const std::string robot = robotId();
  if (last_imu_ && t - *last_imu_ > imu_timeout_) {
    return Verdict::finish("the IMU on " + topic(robot, "imu") + " is silent: last sample " +
                           flight::secondsText(t - *last_imu_) + " ago (limit " +
                           flight::secondsText(imu_timeout_) + ")");
  }
  const TimePoint last_scan = last_scan_.value_or(activated_at_);
  if (t - last_scan > lidar_timeout_) {
    return Verdict::finish("the lidar on " + topic(robot, "lidar/scan") + " is silent: " +
                           (last_scan_ ? "last scan " + flight::secondsText(t - last_scan) + " ago"
                                       : "no scan since the activation " +
                                             flight::secondsText(t - last_scan) + " ago") +
                           " (limit " + flight::secondsText(lidar_timeout_) + ")");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::nav
