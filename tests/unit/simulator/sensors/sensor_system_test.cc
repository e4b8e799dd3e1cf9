#include "simulator/sensors/sensor_system.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <functional>
#include <map>
#include <mutex>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <stdexcept>
#include <vector>

#include "formats/world/world.h"
#include "simulator/world/camera.h"

namespace behaviorlib::sim {
namespace {

using std::chrono::milliseconds;
using ::testing::ElementsAre;

constexpr double kGravity = 9.80665;

/// Collects every sample (thread-safe: workers call it too).
class Collector {
 public:
  SensorSystem::Sink sink() {
    return [this](SensorSample sample) {
      std::lock_guard lock(mutex_);
      samples_.push_back(std::move(sample));
    };
  }
  std::vector<SensorSample> of(SensorKind kind, const std::string& robot_id = "drone1") {
    std::lock_guard lock(mutex_);
    std::vector<SensorSample> out;
    for (const auto& s : samples_) {
      if (s.kind == kind && s.robot_id == robot_id) out.push_back(s);
    }
    return out;
  }
  std::vector<SensorSample> all() {
    std::lock_guard lock(mutex_);
    return samples_;
  }

 private:
  std::mutex mutex_;
  std::vector<SensorSample> samples_;
};

/// The state of each vehicle as a function of simulated time.
using Trajectory = std::function<VehicleSnapshot(double t_s)>;

/// Steps `sensors` from `start` for `duration` in steps of `step`, with one
/// vehicle per entry of `vehicles`; waits for the last frames.
SimTime drive(SensorSystem& sensors, const std::map<std::string, Trajectory>& vehicles,
              SimDuration duration, SimDuration step = milliseconds(1), SimTime start = SimTime{0},
              bool wait_for_frames = true) {
  std::vector<std::string> ids;
  for (const auto& [id, trajectory] : vehicles) ids.push_back(id);
  SimTime now = start;
  const SimTime end = start + duration;
  std::vector<VehicleReport> reports;
  while (now < end) {
    now += step;
    reports.clear();
    const double t = std::chrono::duration<double>(now).count();
    for (const std::string& id : ids) reports.push_back({&id, vehicles.at(id)(t), nullptr});
    sensors.onStep(now, reports, wait_for_frames);
  }
  sensors.waitIdle();
  return now;
}

VehicleSnapshot landedAt(const Eigen::Vector3d& position_m, double yaw_rad = 0.0) {
  VehicleSnapshot s;
  s.position_m = position_m;
  s.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
  s.yaw_rad = yaw_rad;
  s.battery_ratio = 0.8;
  s.battery_voltage_v = 15.9;
  s.battery_current_a = 1.2;
  return s;
}

Trajectory still(const VehicleSnapshot& state) {
  return [state](double) { return state; };
}

/// Flying a circle, banked, climbing slowly: every state variable changes.
VehicleSnapshot circling(double t) {
  VehicleSnapshot s;
  s.position_m = {3.0 * std::cos(0.5 * t), 3.0 * std::sin(0.5 * t), 1.0 + 0.1 * t};
  s.velocity_m_s = {-1.5 * std::sin(0.5 * t), 1.5 * std::cos(0.5 * t), 0.1};
  s.acceleration_m_s2 = {-0.75 * std::cos(0.5 * t), -0.75 * std::sin(0.5 * t), 0.0};
  s.orientation = Eigen::AngleAxisd(0.5 * t + std::numbers::pi / 2, Eigen::Vector3d::UnitZ()) *
                  Eigen::AngleAxisd(-0.08, Eigen::Vector3d::UnitX());
  s.angular_velocity_rad_s = {0.0, 0.04, 0.5};
  s.on_ground = false;
  s.battery_ratio = 1.0 - 0.001 * t;
  s.battery_voltage_v = 16.0 - 0.01 * t;
  s.battery_current_a = 20.0;
  return s;
}

struct Stats {
  double mean = 0.0;
  double stddev = 0.0;
};

Stats stats(const std::vector<double>& values) {
  Stats s;
  for (double v : values) s.mean += v;
  s.mean /= static_cast<double>(values.size());
  for (double v : values) s.stddev += (v - s.mean) * (v - s.mean);
  s.stddev = std::sqrt(s.stddev / static_cast<double>(values.size() - 1));
  return s;
}

/// Only the sensors named enabled (rates as configured), the rest off.
SensorConfig only(std::initializer_list<SensorKind> kinds, SensorConfig config = {}) {
  auto keep = [&](SensorKind kind) {
    return std::find(kinds.begin(), kinds.end(), kind) != kinds.end();
  };
  if (!keep(SensorKind::kImu)) config.imu.rate_hz = 0;
  if (!keep(SensorKind::kGps)) config.gps.rate_hz = 0;
  if (!keep(SensorKind::kBaro)) config.baro.rate_hz = 0;
  if (!keep(SensorKind::kLinearSpeed)) config.linear_speed.rate_hz = 0;
  if (!keep(SensorKind::kBattery)) config.battery.rate_hz = 0;
  if (!keep(SensorKind::kLidar)) config.lidar.rate_hz = 0;
  if (!keep(SensorKind::kCamera)) config.camera.rate_hz = 0;
  return config;
}

TEST(SensorSystem, ImuOnTheGroundReadsGravityUpWithTheConfiguredNoise) {
  SensorConfig config = only({SensorKind::kImu});
  config.imu.gyro_bias_stddev_rad_s = 0.0;
  config.imu.gyro_bias_walk_rad_s_sqrt_s = 0.0;
  config.imu.accel_bias_stddev_m_s2 = 0.0;
  config.imu.accel_bias_walk_m_s2_sqrt_s = 0.0;
  config.imu.gyro_noise_stddev_rad_s = 0.01;
  config.imu.accel_noise_stddev_m_s2 = 0.05;
  Collector out;
  SensorSystem sensors(config, out.sink());
  drive(sensors, {{"drone1", still(landedAt({1, 2, 0}, 0.7))}}, std::chrono::seconds(20));
  const auto samples = out.of(SensorKind::kImu);
  ASSERT_EQ(samples.size(), 4000u);
  std::vector<double> ax, ay, az, gx, gz;
  double worst_tilt = 0.0;
  for (const auto& s : samples) {
    const auto& imu = std::get<ImuData>(s.data);
    ax.push_back(imu.specific_force_m_s2.x());
    ay.push_back(imu.specific_force_m_s2.y());
    az.push_back(imu.specific_force_m_s2.z());
    gx.push_back(imu.angular_velocity_rad_s.x());
    gz.push_back(imu.angular_velocity_rad_s.z());
    worst_tilt =
        std::max(worst_tilt, imu.orientation.angularDistance(landedAt({0, 0, 0}, 0.7).orientation));
  }
  // Means within 4 standard errors (0.05 / sqrt(4000) = 0.0008).
  EXPECT_NEAR(stats(az).mean, kGravity, 0.0032);
  EXPECT_NEAR(stats(ax).mean, 0.0, 0.0032);
  EXPECT_NEAR(stats(ay).mean, 0.0, 0.0032);
  EXPECT_NEAR(stats(gx).mean, 0.0, 0.00064);
  // Standard deviations within 5 % (the estimate's own error is 1.1 %).
  EXPECT_NEAR(stats(az).stddev, 0.05, 0.0025);
  EXPECT_NEAR(stats(ax).stddev, 0.05, 0.0025);
  EXPECT_NEAR(stats(gz).stddev, 0.01, 0.0005);
  EXPECT_LT(worst_tilt, 0.02) << "orientation error of 0.002 rad per axis";
}

TEST(SensorSystem, ImuReportsSpecificForceAndRatesInTheBodyFrameWithBias) {
  SensorConfig config = only({SensorKind::kImu});
  config.imu.gyro_noise_stddev_rad_s = 0.0;
  config.imu.accel_noise_stddev_m_s2 = 0.0;
  config.imu.orientation_noise_stddev_rad = 0.0;
  config.imu.gyro_bias_walk_rad_s_sqrt_s = 0.0;
  config.imu.accel_bias_walk_m_s2_sqrt_s = 0.0;
  config.imu.accel_bias_stddev_m_s2 = 0.0;
  config.imu.gyro_bias_stddev_rad_s = 0.0;
  Collector out;
  SensorSystem sensors(config, out.sink());
  // Facing north (yaw 90 degrees), accelerating east at 1 m/s^2 and turning.
  VehicleSnapshot state = landedAt({0, 0, 5}, std::numbers::pi / 2);
  state.acceleration_m_s2 = {1.0, 0.0, 0.0};
  state.angular_velocity_rad_s = {0.1, -0.2, 0.3};
  drive(sensors, {{"drone1", still(state)}}, milliseconds(10));
  const auto samples = out.of(SensorKind::kImu);
  ASSERT_FALSE(samples.empty());
  const auto& imu = std::get<ImuData>(samples.front().data);
  // East is the body's right (-y).
  EXPECT_NEAR(imu.specific_force_m_s2.x(), 0.0, 1e-12);
  EXPECT_NEAR(imu.specific_force_m_s2.y(), -1.0, 1e-12);
  EXPECT_NEAR(imu.specific_force_m_s2.z(), kGravity, 1e-12);
  EXPECT_TRUE(imu.angular_velocity_rad_s.isApprox(Eigen::Vector3d(0.1, -0.2, 0.3)));

  // A bias is drawn per unit: constant over a run without a walk.
  config.imu.gyro_bias_stddev_rad_s = 0.05;
  Collector biased;
  SensorSystem with_bias(config, biased.sink());
  drive(with_bias, {{"drone1", still(state)}}, std::chrono::seconds(1));
  const auto b = biased.of(SensorKind::kImu);
  ASSERT_EQ(b.size(), 200u);
  const Eigen::Vector3d first = std::get<ImuData>(b.front().data).angular_velocity_rad_s;
  EXPECT_GT((first - state.angular_velocity_rad_s).norm(), 1e-4);
  EXPECT_TRUE(first.isApprox(std::get<ImuData>(b.back().data).angular_velocity_rad_s, 1e-12));
}

TEST(SensorSystem, GpsNoiseMatchesTheConfiguredStandardDeviations) {
  SensorConfig config = only({SensorKind::kGps});
  config.gps.rate_hz = 100.0;
  config.gps.horizontal_stddev_m = 0.5;
  config.gps.vertical_stddev_m = 1.2;
  Collector out;
  SensorSystem sensors(config, out.sink());
  drive(sensors, {{"drone1", still(landedAt({10, -4, 2}))}}, std::chrono::seconds(40),
        milliseconds(10));
  const auto samples = out.of(SensorKind::kGps);
  ASSERT_EQ(samples.size(), 4000u);
  std::vector<double> x, y, z;
  for (const auto& s : samples) {
    const auto& fix = std::get<PositionFixData>(s.data);
    x.push_back(fix.position_m.x());
    y.push_back(fix.position_m.y());
    z.push_back(fix.position_m.z());
    EXPECT_EQ(fix.horizontal_stddev_m, 0.5);
    EXPECT_EQ(fix.vertical_stddev_m, 1.2);
  }
  EXPECT_NEAR(stats(x).mean, 10.0, 4 * 0.5 / std::sqrt(4000.0));
  EXPECT_NEAR(stats(y).mean, -4.0, 4 * 0.5 / std::sqrt(4000.0));
  EXPECT_NEAR(stats(z).mean, 2.0, 4 * 1.2 / std::sqrt(4000.0));
  EXPECT_NEAR(stats(x).stddev, 0.5, 0.025);
  EXPECT_NEAR(stats(y).stddev, 0.5, 0.025);
  EXPECT_NEAR(stats(z).stddev, 1.2, 0.06);
}

TEST(SensorSystem, BarometerLinearSpeedAndBatteryFollowTheState) {
  SensorConfig config = only({SensorKind::kBaro, SensorKind::kLinearSpeed, SensorKind::kBattery});
  config.baro.noise_stddev_m = 0.1;
  config.baro.drift_walk_m_sqrt_s = 0.0;
  config.linear_speed.noise_stddev_m_s = 0.0;
  config.battery.voltage_noise_stddev_v = 0.0;
  config.battery.current_noise_stddev_a = 0.0;
  Collector out;
  SensorSystem sensors(config, out.sink());
  VehicleSnapshot state = landedAt({0, 0, 7.5}, std::numbers::pi / 2);
  state.velocity_m_s = {0.0, 2.0, -0.5};  // north = body forward
  drive(sensors, {{"drone1", still(state)}}, std::chrono::seconds(20));
  std::vector<double> altitude;
  for (const auto& s : out.of(SensorKind::kBaro)) {
    altitude.push_back(std::get<AltitudeData>(s.data).altitude_m);
  }
  ASSERT_EQ(altitude.size(), 500u);
  EXPECT_NEAR(stats(altitude).mean, 7.5, 4 * 0.1 / std::sqrt(500.0));
  EXPECT_NEAR(stats(altitude).stddev, 0.1, 0.015);
  const auto speed = out.of(SensorKind::kLinearSpeed);
  ASSERT_EQ(speed.size(), 600u);
  EXPECT_TRUE(std::get<LinearSpeedData>(speed.back().data)
                  .velocity_m_s.isApprox(Eigen::Vector3d(2.0, 0.0, -0.5), 1e-12));
  const auto battery = out.of(SensorKind::kBattery);
  ASSERT_EQ(battery.size(), 40u);
  const auto& b = std::get<BatteryData>(battery.back().data);
  EXPECT_EQ(b.charge_ratio, 0.8);
  EXPECT_EQ(b.voltage_v, 15.9);
  EXPECT_EQ(b.current_a, 1.2);

  // The barometer drifts when asked to: a random walk of 0.5 m/sqrt(s) moves
  // the mean of the last second far from the first's (P(< 0.3 m) ~ 0.06).
  config.baro.drift_walk_m_sqrt_s = 0.5;
  config.baro.noise_stddev_m = 0.0;
  Collector drifting;
  SensorSystem drifting_sensors(config, drifting.sink());
  drive(drifting_sensors, {{"drone1", still(state)}}, std::chrono::seconds(100));
  const auto d = drifting.of(SensorKind::kBaro);
  double spread = 0.0;
  for (const auto& s : d) {
    spread = std::max(spread, std::abs(std::get<AltitudeData>(s.data).altitude_m - 7.5));
  }
  EXPECT_GT(spread, 0.3);
}

TEST(SensorSystem, RatesAreHonouredInSimulatedTime) {
  Collector out;
  SensorSystem sensors(SensorConfig{}, out.sink());
  drive(sensors, {{"drone1", circling}}, std::chrono::seconds(2));
  EXPECT_EQ(out.of(SensorKind::kImu).size(), 400u);
  EXPECT_EQ(out.of(SensorKind::kGps).size(), 20u);
  EXPECT_EQ(out.of(SensorKind::kBaro).size(), 50u);
  EXPECT_EQ(out.of(SensorKind::kLinearSpeed).size(), 60u);
  EXPECT_EQ(out.of(SensorKind::kBattery).size(), 4u);
  EXPECT_EQ(out.of(SensorKind::kLidar).size(), 20u);
  EXPECT_EQ(out.of(SensorKind::kCameraInfo).size(), 2u);
  EXPECT_EQ(out.of(SensorKind::kCamera).size(), 0u) << "nobody wants the camera";
  // Stamps: the step at or after each due time k / rate; seq counts from 0.
  const auto imu = out.of(SensorKind::kImu);
  for (std::size_t i = 0; i < imu.size(); ++i) {
    EXPECT_EQ(imu[i].stamp, SimTime(milliseconds(5 * (i + 1))));
    EXPECT_EQ(imu[i].seq, i);
  }
  const auto lidar = out.of(SensorKind::kLidar);
  for (std::size_t i = 0; i < lidar.size(); ++i) {
    EXPECT_EQ(lidar[i].stamp, SimTime(milliseconds(100 * (i + 1)))) << i;
    EXPECT_EQ(lidar[i].seq, i);
  }
  // 15 Hz on a 1 ms step: 30 frames in 2 s, due every 66666667 ns (the
  // period rounded to the nanosecond), each at most one step late.
  sensors.setCameraWanted("drone1", true);
  drive(sensors, {{"drone1", circling}}, std::chrono::seconds(2), milliseconds(1),
        SimTime(std::chrono::seconds(2)));
  const auto camera = out.of(SensorKind::kCamera);
  ASSERT_EQ(camera.size(), 30u);
  for (std::size_t i = 0; i < camera.size(); ++i) {
    const SimTime due(static_cast<int64_t>(30 + i) * 66666667);
    EXPECT_GE(camera[i].stamp, due) << i;
    EXPECT_LT(camera[i].stamp, due + milliseconds(1)) << i;
  }
  // A rate of 0 disables a sensor.
  Collector none;
  SensorSystem disabled(only({}), none.sink());
  disabled.setCameraWanted("drone1", true);
  drive(disabled, {{"drone1", circling}}, std::chrono::seconds(1));
  EXPECT_TRUE(none.all().empty());
}

/// A wall whose near face is the plane x = 5 (from y = -10 to 10, 4 m high).
std::shared_ptr<const world::World> wallWorld() {
  auto world = std::make_shared<world::World>("wall");
  world->addBox(world::Box{
      "wall", {5.1, 0.0, 2.0}, {0.2, 20.0, 4.0}, 0.0, {200, 200, 200}, world::Box::Kind::kWall});
  return world;
}

TEST(SensorSystem, LidarRangeToAKnownWallIsWithinItsNoise) {
  SensorConfig config = only({SensorKind::kLidar});
  config.lidar.noise_stddev_m = 0.02;
  Collector out;
  SensorSystem sensors(config, out.sink());
  sensors.reset(wallWorld(), 3);
  // Facing north: the wall (east) is on the body's right, azimuth -90 degrees.
  drive(sensors, {{"drone1", still(landedAt({0, 0, 1}, std::numbers::pi / 2))}},
        std::chrono::seconds(2));
  const auto scans = out.of(SensorKind::kLidar);
  ASSERT_EQ(scans.size(), 20u);
  std::vector<double> right;
  for (const auto& s : scans) {
    const auto& scan = std::get<LidarData>(s.data);
    ASSERT_FALSE(scan.three_d);
    ASSERT_EQ(scan.ranges_m.size(), 360u);
    EXPECT_DOUBLE_EQ(scan.angle_min_rad, -std::numbers::pi);
    EXPECT_NEAR(scan.angle_increment_rad, 2 * std::numbers::pi / 360, 1e-12);
    EXPECT_NEAR(scan.angle_max_rad, std::numbers::pi - scan.angle_increment_rad, 1e-12);
    const int beam = static_cast<int>(
        std::lround((-std::numbers::pi / 2 - scan.angle_min_rad) / scan.angle_increment_rad));
    right.push_back(scan.ranges_m[beam]);
    EXPECT_TRUE(std::isinf(scan.ranges_m[beam + 180]) && scan.ranges_m[beam + 180] > 0)
        << "nothing on the left within 30 m";
  }
  for (double r : right) EXPECT_NEAR(r, 5.0, 4 * 0.02);
  EXPECT_NEAR(stats(right).mean, 5.0, 4 * 0.02 / std::sqrt(20.0));
  EXPECT_GT(stats(right).stddev, 0.005) << "noisy";

  // 3-D: points in the lidar frame, the wall's at y = -5 (body right).
  config.lidar.channels = 16;
  Collector points_out;
  SensorSystem three_d(config, points_out.sink());
  three_d.reset(wallWorld(), 3);
  drive(three_d, {{"drone1", still(landedAt({0, 0, 1}, std::numbers::pi / 2))}}, milliseconds(100));
  const auto clouds = points_out.of(SensorKind::kLidar);
  ASSERT_EQ(clouds.size(), 1u);
  const auto& cloud = std::get<LidarData>(clouds.front().data);
  ASSERT_TRUE(cloud.three_d);
  int on_wall = 0;
  for (const Eigen::Vector3f& p : cloud.points_m) {
    if (std::abs(p.y() + 5.0f) < 0.1f) ++on_wall;
  }
  // The ground at z = -1.1 in the lidar frame is hit by the downward channels.
  EXPECT_GT(on_wall, 16 * 20);
}

/// A 4 m wide panel whose near face is x = 3, with a 0.8 m marker at z = 1.
std::shared_ptr<const world::World> markerWorld(const std::string& text) {
  auto world = std::make_shared<world::World>("marker");
  world->addBox(world::Box{
      "panel", {3.1, 0.0, 1.5}, {0.2, 4.0, 3.0}, 0.0, {90, 110, 160}, world::Box::Kind::kBox});
  world::Marker marker;
  marker.name = "m";
  marker.text = text;
  marker.center_m = {3.0, 0.0, 1.0};
  marker.normal = {-1, 0, 0};
  marker.up = {0, 0, 1};
  marker.size_m = 0.8;
  marker.attached_to = "panel";
  world->addMarker(marker);
  return world;
}

TEST(SensorSystem, CameraFramesDecodeToTheMarkerTextAndOnlyWhileWanted) {
  SensorConfig config = only({SensorKind::kCamera});
  Collector out;
  SensorSystem sensors(config, out.sink());
  sensors.reset(markerWorld("behaviorlib sensor test"), 1);
  // The camera (mounted 0.05 m up) at z = 1, facing the marker.
  const auto state = still(landedAt({0, 0, 0.95}));
  SimTime now = drive(sensors, {{"drone1", state}}, std::chrono::seconds(1));
  EXPECT_TRUE(out.of(SensorKind::kCamera).empty());
  ASSERT_EQ(out.of(SensorKind::kCameraInfo).size(), 1u) << "the info is always published";

  sensors.setCameraWanted("drone1", true);
  drive(sensors, {{"drone1", state}}, milliseconds(200), milliseconds(1), now);
  const auto frames = out.of(SensorKind::kCamera);
  ASSERT_EQ(frames.size(), 3u);
  EXPECT_EQ(sensors.droppedCount(SensorKind::kCamera), 0u);
  const auto& image = std::get<CameraImageData>(frames.front().data);
  EXPECT_EQ(image.encoding, "jpeg");
  EXPECT_EQ(image.width_px, 640);
  EXPECT_EQ(image.height_px, 480);
  const cv::Mat decoded = cv::imdecode(cv::Mat(1, static_cast<int>(image.data.size()), CV_8UC1,
                                               const_cast<char*>(image.data.data())),
                                       cv::IMREAD_COLOR);
  ASSERT_FALSE(decoded.empty());
  EXPECT_THAT(decodeQr(decoded), ElementsAre("behaviorlib sensor test"));

  // The info matches the camera model: pinhole, optical z = body forward.
  const CameraInfoData info =
      std::get<CameraInfoData>(out.of(SensorKind::kCameraInfo).front().data);
  EXPECT_EQ(info.width_px, 640);
  EXPECT_NEAR(info.fx_px, 320.0 / std::tan(std::numbers::pi / 6), 1e-9);
  EXPECT_EQ(info.fx_px, info.fy_px);
  EXPECT_DOUBLE_EQ(info.cx_px, 319.5);
  EXPECT_DOUBLE_EQ(info.cy_px, 239.5);
  EXPECT_TRUE(info.position_in_body_m.isApprox(Eigen::Vector3d(0.1, 0.0, 0.05)));
  EXPECT_TRUE(
      (info.body_from_camera * Eigen::Vector3d::UnitZ()).isApprox(Eigen::Vector3d::UnitX()));
  EXPECT_TRUE(
      (info.body_from_camera * Eigen::Vector3d::UnitX()).isApprox(-Eigen::Vector3d::UnitY()));

  // No longer wanted: no more frames.
  sensors.setWantedCameras({});
  const std::size_t before = out.of(SensorKind::kCamera).size();
  drive(sensors, {{"drone1", state}}, milliseconds(500), milliseconds(1), now + milliseconds(200));
  EXPECT_EQ(out.of(SensorKind::kCamera).size(), before);

  // PNG on request.
  config.camera.format = "png";
  Collector png_out;
  SensorSystem png(config, png_out.sink());
  png.reset(markerWorld("png"), 1);
  png.setCameraWanted("drone1", true);
  drive(png, {{"drone1", state}}, milliseconds(70));
  ASSERT_EQ(png_out.of(SensorKind::kCamera).size(), 1u);
  const CameraImageData png_image =
      std::get<CameraImageData>(png_out.of(SensorKind::kCamera)[0].data);
  EXPECT_EQ(png_image.encoding, "png");
  EXPECT_EQ(png_image.data.substr(1, 3), "PNG");
}

/// The bytes of a sample's measurement, stamp and sequence number.
std::string fingerprint(const SensorSample& s) {
  std::string out;
  auto add = [&out](const void* p, std::size_t n) { out.append(static_cast<const char*>(p), n); };
  auto vec = [&add](const Eigen::Vector3d& v) { add(v.data(), sizeof(double) * 3); };
  const int64_t stamp = s.stamp.count();
  add(&stamp, sizeof stamp);
  add(&s.seq, sizeof s.seq);
  std::visit(
      [&](const auto& d) {
        using T = std::decay_t<decltype(d)>;
        if constexpr (std::is_same_v<T, ImuData>) {
          add(d.orientation.coeffs().data(), sizeof(double) * 4);
          vec(d.angular_velocity_rad_s);
          vec(d.specific_force_m_s2);
        } else if constexpr (std::is_same_v<T, PositionFixData>) {
          vec(d.position_m);
        } else if constexpr (std::is_same_v<T, AltitudeData>) {
          add(&d.altitude_m, sizeof(double));
        } else if constexpr (std::is_same_v<T, LinearSpeedData>) {
          vec(d.velocity_m_s);
        } else if constexpr (std::is_same_v<T, BatteryData>) {
          add(&d.voltage_v, sizeof(double));
          add(&d.current_a, sizeof(double));
        } else if constexpr (std::is_same_v<T, LidarData>) {
          add(d.ranges_m.data(), sizeof(float) * d.ranges_m.size());
          add(d.points_m.data(), sizeof(Eigen::Vector3f) * d.points_m.size());
        } else if constexpr (std::is_same_v<T, CameraImageData>) {
          out += d.data;
        } else {
          add(&d.fx_px, sizeof(double));
        }
      },
      s.data);
  return out;
}

/// Per sensor, the fingerprints of drone1's samples, in order.
std::map<SensorKind, std::vector<std::string>> run(
    uint64_t seed, const std::map<std::string, Trajectory>& vehicles,
    SimDuration duration = std::chrono::seconds(3)) {
  Collector out;
  SensorSystem sensors(SensorConfig{}, out.sink());
  sensors.reset(wallWorld(), seed);
  sensors.setCameraWanted("drone1", true);
  drive(sensors, vehicles, duration);
  std::map<SensorKind, std::vector<std::string>> prints;
  for (const auto& s : out.all()) {
    if (s.robot_id == "drone1") prints[s.kind].push_back(fingerprint(s));
  }
  return prints;
}

TEST(SensorSystem, TheSameSeedGivesIdenticalSamplesAndAnotherSeedDiffers) {
  const auto a = run(7, {{"drone1", circling}});
  const auto b = run(7, {{"drone1", circling}});
  ASSERT_EQ(a.size(), 8u) << "every sensor published";
  EXPECT_EQ(a.at(SensorKind::kLidar).size(), 30u);
  EXPECT_EQ(a.at(SensorKind::kCamera).size(), 44u) << "the 45th is due 150 ns after 3 s";
  EXPECT_TRUE(a == b) << "bit for bit";

  const auto other = run(8, {{"drone1", circling}});
  for (SensorKind kind : {SensorKind::kImu, SensorKind::kGps, SensorKind::kBaro,
                          SensorKind::kLinearSpeed, SensorKind::kBattery, SensorKind::kLidar}) {
    ASSERT_EQ(other.at(kind).size(), a.at(kind).size());
    for (std::size_t i = 0; i < a.at(kind).size(); ++i) {
      EXPECT_NE(other.at(kind)[i], a.at(kind)[i]) << sensorName(kind) << " sample " << i;
    }
  }
  // Noise-free outputs do not depend on the seed.
  EXPECT_EQ(other.at(SensorKind::kCamera), a.at(SensorKind::kCamera));

  // Another vehicle in the world changes nothing of drone1's.
  const auto crowded = run(7, {{"drone1", circling}, {"drone0", circling}, {"drone2", circling}});
  EXPECT_TRUE(crowded == a);
}

TEST(SensorSystem, ResetRestartsEverySensorLikeAFreshSystem) {
  Collector out;
  SensorSystem sensors(SensorConfig{}, out.sink());
  sensors.reset(wallWorld(), 11);
  drive(sensors, {{"drone1", circling}}, std::chrono::seconds(2));
  const auto first = out.all();
  sensors.reset(wallWorld(), 11);
  drive(sensors, {{"drone1", circling}}, std::chrono::seconds(2));
  const auto all = out.all();
  ASSERT_EQ(all.size(), 2 * first.size());
  // Order may differ between the physics thread and the workers: compare per sensor.
  std::map<SensorKind, std::vector<std::string>> before, after;
  for (std::size_t i = 0; i < all.size(); ++i) {
    (i < first.size() ? before : after)[all[i].kind].push_back(fingerprint(all[i]));
  }
  EXPECT_TRUE(before == after);
}

TEST(SensorSystem, FramesThatCannotBeMadeInTimeAreDroppedAndCountedUnlessWaiting) {
  // A 3-D lidar of 64 x 2000 beams sampled every step: each scan takes far
  // longer than a step of this loop.
  SensorConfig config = only({SensorKind::kLidar});
  config.lidar.rate_hz = 1000;
  config.lidar.channels = 64;
  config.lidar.beams = 2000;
  config.worker_threads = 1;
  Collector out;
  SensorSystem sensors(config, out.sink());
  sensors.reset(wallWorld(), 1);
  drive(sensors, {{"drone1", circling}}, milliseconds(100), milliseconds(1), SimTime{0},
        /*wait_for_frames=*/false);
  const uint64_t published = out.of(SensorKind::kLidar).size();
  EXPECT_GT(sensors.droppedCount(SensorKind::kLidar), 0u);
  EXPECT_EQ(published + sensors.droppedCount(SensorKind::kLidar), 100u);
  EXPECT_EQ(sensors.publishedCount(SensorKind::kLidar), published);
  // Frames come out in order, each stamped with its own step.
  const auto scans = out.of(SensorKind::kLidar);
  for (std::size_t i = 1; i < scans.size(); ++i) EXPECT_GT(scans[i].stamp, scans[i - 1].stamp);

  // Lock-step waits instead: no frame lost.
  Collector all_out;
  SensorSystem waiting(config, all_out.sink());
  waiting.reset(wallWorld(), 1);
  drive(waiting, {{"drone1", circling}}, milliseconds(20));
  EXPECT_EQ(all_out.of(SensorKind::kLidar).size(), 20u);
  EXPECT_EQ(waiting.droppedCount(SensorKind::kLidar), 0u);
}

TEST(SensorSystem, SeedsDependOnSeedRobotAndSensor) {
  EXPECT_EQ(sensorSeed(1, "drone1", "imu"), sensorSeed(1, "drone1", "imu"));
  EXPECT_NE(sensorSeed(1, "drone1", "imu"), sensorSeed(2, "drone1", "imu"));
  EXPECT_NE(sensorSeed(1, "drone1", "imu"), sensorSeed(1, "drone2", "imu"));
  EXPECT_NE(sensorSeed(1, "drone1", "imu"), sensorSeed(1, "drone1", "gps"));
  EXPECT_NE(sensorSeed(1, "drone1/", "imu"), sensorSeed(1, "drone1", "/imu"));
}

TEST(SensorSystem, RefusesAnInvalidConfiguration) {
  SensorConfig config;
  config.lidar.range_max_m = 0.0;
  EXPECT_THROW(SensorSystem(config, [](SensorSample) {}), std::invalid_argument);
}

}  // namespace
}  // namespace behaviorlib::sim
