// The sensors' faults (SensorSystem::setFault, SensorOutput, SensorChannel)
// on hand-built vehicle states in simulated time: each fault has the effect
// it claims on every sensor, acts on the samples stamped after it was set,
// is reproducible from the seed, and is cleared by OK and by reset().

#include "simulator/sensors/sensor_faults.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <functional>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <string>
#include <vector>

#include "formats/world/world.h"
#include "simulator/sensors/sensor_system.h"

namespace behaviorlib::sim {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

/// A published sample and the simulated time of the step that published it.
struct Published {
  SensorSample sample;
  SimTime at{0};
};

/// Collects every sample with the simulated time it was published at.
class Collector {
 public:
  SensorSystem::Sink sink() {
    return [this](SensorSample sample) {
      std::lock_guard lock(mutex_);
      samples_.push_back({std::move(sample), SimTime(now_.load())});
    };
  }
  void setNow(SimTime now) { now_.store(now.count()); }
  std::vector<Published> of(SensorKind kind) {
    std::lock_guard lock(mutex_);
    std::vector<Published> out;
    for (const auto& p : samples_) {
      if (p.sample.kind == kind) out.push_back(p);
    }
    return out;
  }
  void clear() {
    std::lock_guard lock(mutex_);
    samples_.clear();
  }

 private:
  std::atomic<int64_t> now_{0};
  std::mutex mutex_;
  std::vector<Published> samples_;
};

/// Flying east at 1 m/s at 2 m, yawing slowly: every measurement changes.
VehicleSnapshot moving(double t) {
  VehicleSnapshot s;
  s.position_m = {t, 0.0, 2.0};
  s.velocity_m_s = {1.0, 0.0, 0.0};
  s.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(0.05 * t, Eigen::Vector3d::UnitZ()));
  s.yaw_rad = 0.05 * t;
  s.angular_velocity_rad_s = {0.0, 0.0, 0.05};
  s.on_ground = false;
  s.battery_ratio = 0.9 - 0.001 * t;
  s.battery_voltage_v = 15.5;
  s.battery_current_a = 20.0;
  return s;
}

/// A wall 10 m east of the origin, for the lidar and the camera to see.
std::shared_ptr<const world::World> wallWorld() {
  auto world = std::make_shared<world::World>("wall");
  world->addBox(world::Box{
      "wall", {10.1, 0.0, 5.0}, {0.2, 40.0, 10.0}, 0.0, {200, 120, 60}, world::Box::Kind::kWall});
  return world;
}

/// Steps drone1 along `moving` from `from` to `to` (1 ms steps, lock-step).
void drive(SensorSystem& sensors, Collector& out, SimTime from, SimTime to) {
  static const std::string kId = "drone1";
  std::vector<VehicleReport> reports(1);
  for (SimTime now = from + milliseconds(1); now <= to; now += milliseconds(1)) {
    out.setNow(now);
    reports[0] = {&kId, moving(std::chrono::duration<double>(now).count()), nullptr};
    sensors.onStep(now, reports, /*wait_for_frames=*/true);
  }
  sensors.waitIdle();
}

/// Only `kind` enabled (the camera's info stays off unless it is the camera).
SensorConfig only(SensorKind kind) {
  SensorConfig c;
  if (kind != SensorKind::kImu) c.imu.rate_hz = 0;
  if (kind != SensorKind::kGps) c.gps.rate_hz = 0;
  if (kind != SensorKind::kBaro) c.baro.rate_hz = 0;
  if (kind != SensorKind::kLinearSpeed) c.linear_speed.rate_hz = 0;
  if (kind != SensorKind::kBattery) c.battery.rate_hz = 0;
  if (kind != SensorKind::kLidar) c.lidar.rate_hz = 0;
  if (kind != SensorKind::kCamera) {
    c.camera.rate_hz = 0;
  } else {
    c.camera.width_px = 160;  // small: fast to render and encode
    c.camera.height_px = 120;
  }
  return c;
}

/// The numbers a sample carries (the image as its decoded pixels).
std::vector<double> values(const SampleData& data) {
  std::vector<double> out;
  auto vec = [&out](const Eigen::Vector3d& v) { out.insert(out.end(), v.data(), v.data() + 3); };
  std::visit(
      [&](const auto& d) {
        using T = std::decay_t<decltype(d)>;
        if constexpr (std::is_same_v<T, ImuData>) {
          out.insert(out.end(), d.orientation.coeffs().data(), d.orientation.coeffs().data() + 4);
          vec(d.angular_velocity_rad_s);
          vec(d.specific_force_m_s2);
        } else if constexpr (std::is_same_v<T, PositionFixData>) {
          vec(d.position_m);
        } else if constexpr (std::is_same_v<T, AltitudeData>) {
          out.push_back(d.altitude_m);
        } else if constexpr (std::is_same_v<T, LinearSpeedData>) {
          vec(d.velocity_m_s);
        } else if constexpr (std::is_same_v<T, BatteryData>) {
          out.insert(out.end(), {d.charge_ratio, d.voltage_v, d.current_a});
        } else if constexpr (std::is_same_v<T, LidarData>) {
          out.insert(out.end(), d.ranges_m.begin(), d.ranges_m.end());
        } else if constexpr (std::is_same_v<T, CameraImageData>) {
          const cv::Mat bytes(1, static_cast<int>(d.data.size()), CV_8UC1,
                              const_cast<char*>(d.data.data()));
          const cv::Mat image = cv::imdecode(bytes, cv::IMREAD_GRAYSCALE);
          out.assign(image.begin<uint8_t>(), image.end<uint8_t>());
        } else {
          out.push_back(d.fx_px);
        }
      },
      data);
  return out;
}

/// Mean absolute difference of two equally long value lists; NaN counts as
/// a large difference.
double difference(const std::vector<double>& a, const std::vector<double>& b) {
  if (a.size() != b.size() || a.empty()) return 1e9;
  double sum = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const double d = std::abs(a[i] - b[i]);
    sum += std::isfinite(d) ? d : 1e3;
  }
  return sum / static_cast<double>(a.size());
}

constexpr SensorKind kFaultable[] = {
    SensorKind::kImu,     SensorKind::kGps,   SensorKind::kBaro,  SensorKind::kLinearSpeed,
    SensorKind::kBattery, SensorKind::kLidar, SensorKind::kCamera};

/// One sensor run twice over the same 2 s, healthy and with `fault` from 1 s.
struct Comparison {
  std::vector<Published> healthy;
  std::vector<Published> faulty;
  uint64_t fault_dropped = 0;
};

Comparison compare(SensorKind kind, const SensorFault& fault, uint64_t seed = 5) {
  Comparison result;
  for (bool inject : {false, true}) {
    Collector out;
    SensorSystem sensors(only(kind), out.sink());
    sensors.reset(wallWorld(), seed);
    sensors.setCameraWanted("drone1", true);
    drive(sensors, out, SimTime{0}, seconds(1));
    if (inject) sensors.setFault("drone1", kind, seconds(1), fault);
    drive(sensors, out, seconds(1), seconds(2));
    (inject ? result.faulty : result.healthy) = out.of(kind);
    if (inject) {
      for (const auto& s : sensors.stats()) {
        if (s.robot_id == "drone1" && s.kind == kind) result.fault_dropped = s.fault_dropped;
      }
    }
  }
  return result;
}

/// The samples stamped after 1 s.
std::vector<Published> afterFault(const std::vector<Published>& samples) {
  std::vector<Published> out;
  for (const auto& p : samples) {
    if (p.sample.stamp > seconds(1)) out.push_back(p);
  }
  return out;
}

class EverySensor : public ::testing::TestWithParam<SensorKind> {};

TEST_P(EverySensor, OffPublishesNothingAfterTheFault) {
  const SensorKind kind = GetParam();
  const Comparison c = compare(kind, {SensorFaultType::kOff});
  ASSERT_FALSE(afterFault(c.healthy).empty());
  EXPECT_TRUE(afterFault(c.faulty).empty());
  EXPECT_EQ(c.faulty.size(), c.healthy.size() - afterFault(c.healthy).size())
      << "samples stamped up to the fault are untouched";
  EXPECT_EQ(c.fault_dropped, afterFault(c.healthy).size());
}

TEST_P(EverySensor, StuckRepeatsTheLastValueWithAdvancingStamps) {
  const SensorKind kind = GetParam();
  const Comparison c = compare(kind, {SensorFaultType::kStuck});
  const auto before = c.faulty.size() - afterFault(c.faulty).size();
  ASSERT_GT(before, 0u);
  const std::vector<double> frozen = values(c.faulty[before - 1].sample.data);
  const auto stuck = afterFault(c.faulty);
  ASSERT_EQ(stuck.size(), afterFault(c.healthy).size());
  ASSERT_GE(stuck.size(), 1u);
  for (std::size_t i = 0; i < stuck.size(); ++i) {
    EXPECT_EQ(values(stuck[i].sample.data), frozen) << i;
    if (i > 0) {
      EXPECT_GT(stuck[i].sample.stamp, stuck[i - 1].sample.stamp);
    }
    EXPECT_EQ(stuck[i].sample.seq, before + i);
  }
  // Healthy, the same sensor moves on (the vehicle flies and yaws).
  EXPECT_NE(values(afterFault(c.healthy).back().sample.data), frozen);
}

TEST_P(EverySensor, GarbageIsFarFromTheHealthyValues) {
  const SensorKind kind = GetParam();
  const Comparison c = compare(kind, {SensorFaultType::kGarbage});
  const auto healthy = afterFault(c.healthy);
  const auto garbage = afterFault(c.faulty);
  ASSERT_EQ(garbage.size(), healthy.size());
  ASSERT_FALSE(garbage.empty());
  // Far beyond any sensor's own noise (the healthy runs are identical up to
  // the fault: the same seed).
  for (std::size_t i = 0; i < garbage.size(); ++i) {
    EXPECT_GT(difference(values(garbage[i].sample.data), values(healthy[i].sample.data)), 0.3)
        << sensorName(kind) << " sample " << i;
  }
}

TEST_P(EverySensor, NoisyPerturbsEverySample) {
  const SensorKind kind = GetParam();
  const Comparison c = compare(kind, {SensorFaultType::kNoisy, 1.0});
  const auto healthy = afterFault(c.healthy);
  const auto noisy = afterFault(c.faulty);
  ASSERT_EQ(noisy.size(), healthy.size());
  ASSERT_FALSE(noisy.empty());
  for (std::size_t i = 0; i < noisy.size(); ++i) {
    EXPECT_GT(difference(values(noisy[i].sample.data), values(healthy[i].sample.data)), 0.0) << i;
  }
}

TEST_P(EverySensor, DelayedSamplesArriveLaterWithTheirStamps) {
  const SensorKind kind = GetParam();
  const Comparison c = compare(kind, {SensorFaultType::kDelayed, 0.0, milliseconds(200)});
  const auto healthy = afterFault(c.healthy);
  const auto delayed = afterFault(c.faulty);
  ASSERT_FALSE(healthy.empty());
  // Those due by the end of the run arrived, 200 ms after their stamp (at
  // the first step at or after it).
  std::size_t expected = 0;
  for (const auto& p : healthy) expected += p.sample.stamp + milliseconds(200) <= seconds(2);
  ASSERT_EQ(delayed.size(), expected);
  for (std::size_t i = 0; i < delayed.size(); ++i) {
    EXPECT_EQ(delayed[i].sample.stamp, healthy[i].sample.stamp);
    EXPECT_EQ(values(delayed[i].sample.data), values(healthy[i].sample.data));
    EXPECT_GE(delayed[i].at - delayed[i].sample.stamp, milliseconds(200));
    EXPECT_LT(delayed[i].at - delayed[i].sample.stamp, milliseconds(201));
  }
}

INSTANTIATE_TEST_SUITE_P(SensorFaults, EverySensor, ::testing::ValuesIn(kFaultable),
                         [](const auto& info) { return std::string(sensorName(info.param)); });

TEST(SensorFaults, IntermittentDropsTheGivenFractionReproducibly) {
  const Comparison c = compare(SensorKind::kImu, {SensorFaultType::kIntermittent, 0.5});
  const auto healthy = afterFault(c.healthy);
  const auto kept = afterFault(c.faulty);
  ASSERT_EQ(healthy.size(), 200u);
  // Binomial(200, 0.5): 100 +- 7 (one standard deviation).
  EXPECT_GT(kept.size(), 70u);
  EXPECT_LT(kept.size(), 130u);
  EXPECT_EQ(kept.size() + c.fault_dropped, healthy.size());
  // The kept samples are the healthy ones (same stamps, same values), numbered
  // consecutively.
  std::map<int64_t, std::vector<double>> by_stamp;
  for (const auto& p : healthy) by_stamp[p.sample.stamp.count()] = values(p.sample.data);
  for (std::size_t i = 0; i < kept.size(); ++i) {
    ASSERT_TRUE(by_stamp.count(kept[i].sample.stamp.count()));
    EXPECT_EQ(values(kept[i].sample.data), by_stamp.at(kept[i].sample.stamp.count()));
    EXPECT_EQ(kept[i].sample.seq, 200u + i);
  }
  // The same seed drops the same samples; another seed others.
  const Comparison again = compare(SensorKind::kImu, {SensorFaultType::kIntermittent, 0.5});
  const Comparison other = compare(SensorKind::kImu, {SensorFaultType::kIntermittent, 0.5}, 6);
  auto stamps = [](const std::vector<Published>& v) {
    std::vector<int64_t> out;
    for (const auto& p : v) out.push_back(p.sample.stamp.count());
    return out;
  };
  EXPECT_EQ(stamps(afterFault(again.faulty)), stamps(kept));
  EXPECT_NE(stamps(afterFault(other.faulty)), stamps(kept));
}

TEST(SensorFaults, NoisyScalesTheConfiguredStandardDeviation) {
  // GPS horizontal noise 0.5 m; intensity 0.25 makes it 0.5 (1 + 5) = 3 m.
  SensorConfig config = only(SensorKind::kGps);
  config.gps.rate_hz = 1000;
  Collector out;
  SensorSystem sensors(config, out.sink());
  sensors.reset(wallWorld(), 9);
  sensors.setFault("drone1", SensorKind::kGps, SimTime{0}, {SensorFaultType::kNoisy, 0.25});
  drive(sensors, out, SimTime{0}, seconds(4));
  const auto fixes = out.of(SensorKind::kGps);
  ASSERT_EQ(fixes.size(), 4000u);
  double sum_sq = 0.0;
  for (const auto& p : fixes) {
    const auto& fix = std::get<PositionFixData>(p.sample.data);
    const double t = std::chrono::duration<double>(p.sample.stamp).count();
    sum_sq += std::pow(fix.position_m.y() - moving(t).position_m.y(), 2);
    EXPECT_EQ(fix.horizontal_stddev_m, 0.5) << "the declared accuracy does not change";
  }
  const double stddev = std::sqrt(sum_sq / static_cast<double>(fixes.size()));
  EXPECT_NEAR(stddev, 0.5 * noisyScale(0.25), 0.1 * 0.5 * noisyScale(0.25));
}

TEST(SensorFaults, GarbageGpsJumpsTensOfMetresAndGarbageLidarHasNaN) {
  const Comparison gps = compare(SensorKind::kGps, {SensorFaultType::kGarbage});
  for (const auto& p : afterFault(gps.faulty)) {
    const double t = std::chrono::duration<double>(p.sample.stamp).count();
    const double error =
        (std::get<PositionFixData>(p.sample.data).position_m - moving(t).position_m).norm();
    EXPECT_GT(error, 15.0);
    EXPECT_LT(error, 210.0);
  }
  const Comparison lidar = compare(SensorKind::kLidar, {SensorFaultType::kGarbage});
  std::size_t nan = 0, beams = 0;
  for (const auto& p : afterFault(lidar.faulty)) {
    for (float r : std::get<LidarData>(p.sample.data).ranges_m) {
      nan += std::isnan(r);
      ++beams;
    }
  }
  ASSERT_EQ(beams, 3600u);
  EXPECT_NEAR(static_cast<double>(nan) / static_cast<double>(beams), 0.1, 0.02);
  const Comparison imu = compare(SensorKind::kImu, {SensorFaultType::kGarbage});
  double mean_rate = 0.0;
  const auto garbage = afterFault(imu.faulty);
  for (const auto& p : garbage) {
    mean_rate += std::get<ImuData>(p.sample.data).angular_velocity_rad_s.norm();
  }
  EXPECT_GT(mean_rate / static_cast<double>(garbage.size()), 10.0) << "wrong magnitude";
}

TEST(SensorFaults, OkClearsAFaultAndFlushesDelayedSamplesInOrder) {
  Collector out;
  SensorSystem sensors(only(SensorKind::kGps), out.sink());
  sensors.reset(wallWorld(), 3);
  sensors.setFault("drone1", SensorKind::kGps, SimTime{0},
                   {SensorFaultType::kDelayed, 0.0, seconds(1)});
  drive(sensors, out, SimTime{0}, milliseconds(1500));
  EXPECT_EQ(out.of(SensorKind::kGps).size(), 5u) << "0.1 .. 0.5 s are due by 1.5 s";
  sensors.setFault("drone1", SensorKind::kGps, milliseconds(1500), {SensorFaultType::kOk});
  EXPECT_EQ(sensors.fault("drone1", SensorKind::kGps).type, SensorFaultType::kOk);
  drive(sensors, out, milliseconds(1500), seconds(2));
  const auto fixes = out.of(SensorKind::kGps);
  ASSERT_EQ(fixes.size(), 20u) << "none lost";
  for (std::size_t i = 0; i < fixes.size(); ++i) {
    EXPECT_EQ(fixes[i].sample.seq, i);
    EXPECT_EQ(fixes[i].sample.stamp, milliseconds(100) * static_cast<int64_t>(i + 1));
  }
  // The first sample after the fault ends brings the ten still delayed along.
  EXPECT_EQ(fixes[5].at, milliseconds(1600));
  EXPECT_EQ(fixes[15].at, milliseconds(1600));
  EXPECT_EQ(fixes[16].at, milliseconds(1700));
}

TEST(SensorFaults, ResetClearsEveryFaultButKeepsTheCounters) {
  Collector out;
  SensorSystem sensors(only(SensorKind::kBaro), out.sink());
  sensors.reset(wallWorld(), 3);
  sensors.setFault("drone1", SensorKind::kBaro, SimTime{0}, {SensorFaultType::kOff});
  drive(sensors, out, SimTime{0}, seconds(1));
  EXPECT_TRUE(out.of(SensorKind::kBaro).empty());
  sensors.reset(wallWorld(), 3);
  EXPECT_EQ(sensors.fault("drone1", SensorKind::kBaro).type, SensorFaultType::kOk);
  drive(sensors, out, SimTime{0}, seconds(1));
  EXPECT_EQ(out.of(SensorKind::kBaro).size(), 25u);
  bool found = false;
  for (const auto& s : sensors.stats()) {
    if (s.robot_id != "drone1" || s.kind != SensorKind::kBaro) continue;
    found = true;
    EXPECT_EQ(s.published, 25u);
    EXPECT_EQ(s.fault_dropped, 25u);
    EXPECT_EQ(s.fault, SensorFaultType::kOk);
  }
  EXPECT_TRUE(found);
}

TEST(SensorFaults, AFaultSetBeforeTheVehicleSamplesAppliesToItsFirstSamples) {
  Collector out;
  SensorSystem sensors(only(SensorKind::kLinearSpeed), out.sink());
  sensors.reset(nullptr, 3);
  sensors.setFault("drone1", SensorKind::kLinearSpeed, SimTime{0}, {SensorFaultType::kStuck});
  drive(sensors, out, SimTime{0}, seconds(1));
  const auto speeds = out.of(SensorKind::kLinearSpeed);
  ASSERT_EQ(speeds.size(), 30u);
  for (const auto& p : speeds) EXPECT_EQ(values(p.sample.data), values(speeds[0].sample.data));
}

TEST(SensorFaults, AFrameKeepsTheFaultOfItsStamp) {
  SensorChannel channel;
  EXPECT_EQ(channel.faultAt(seconds(5)).type, SensorFaultType::kOk);
  channel.setFault(seconds(1), {SensorFaultType::kOff});
  channel.setFault(seconds(2), {SensorFaultType::kStuck});
  channel.setFault(seconds(2), {SensorFaultType::kGarbage});  // the same instant: replaces
  EXPECT_EQ(channel.faultAt(seconds(1)).type, SensorFaultType::kOk) << "measured at the call";
  EXPECT_EQ(channel.faultAt(milliseconds(1001)).type, SensorFaultType::kOff);
  EXPECT_EQ(channel.faultAt(seconds(2)).type, SensorFaultType::kOff);
  EXPECT_EQ(channel.faultAt(milliseconds(2001)).type, SensorFaultType::kGarbage);
  EXPECT_EQ(channel.current().type, SensorFaultType::kGarbage);
  channel.clearFaults();
  EXPECT_EQ(channel.faultAt(seconds(3)).type, SensorFaultType::kOk);
}

TEST(SensorFaults, TheSameSeedAndFaultsGiveTheSameSamples) {
  auto run = [](uint64_t seed) {
    Collector out;
    SensorSystem sensors(SensorConfig{}, out.sink());
    sensors.reset(wallWorld(), seed);
    drive(sensors, out, SimTime{0}, milliseconds(500));
    sensors.setFault("drone1", SensorKind::kGps, milliseconds(500), {SensorFaultType::kNoisy, 0.5});
    sensors.setFault("drone1", SensorKind::kImu, milliseconds(500),
                     {SensorFaultType::kIntermittent, 0.3});
    sensors.setFault("drone1", SensorKind::kLidar, milliseconds(500), {SensorFaultType::kGarbage});
    drive(sensors, out, milliseconds(500), seconds(1));
    // Bytes, not doubles: garbage lidar ranges are NaN, never equal to themselves.
    std::map<SensorKind, std::vector<std::string>> result;
    for (SensorKind kind : {SensorKind::kGps, SensorKind::kImu, SensorKind::kLidar}) {
      for (const auto& p : out.of(kind)) {
        const std::vector<double> v = values(p.sample.data);
        result[kind].emplace_back(reinterpret_cast<const char*>(v.data()),
                                  v.size() * sizeof(double));
      }
    }
    return result;
  };
  const auto a = run(21);
  EXPECT_TRUE(a == run(21));
  EXPECT_FALSE(a == run(22));
}

TEST(SensorFaults, FramesReportTheirMakingTime) {
  std::atomic<int> lidar{0}, camera{0};
  Collector out;
  SensorConfig config = only(SensorKind::kCamera);
  config.lidar.rate_hz = 10;
  SensorSystem sensors(config, out.sink(), [&](SensorKind kind, std::chrono::nanoseconds wall) {
    EXPECT_GT(wall.count(), 0);
    (kind == SensorKind::kLidar ? lidar : camera)++;
  });
  sensors.reset(wallWorld(), 1);
  sensors.setCameraWanted("drone1", true);
  drive(sensors, out, SimTime{0}, seconds(1));
  EXPECT_EQ(lidar.load(), 10);
  EXPECT_EQ(camera.load(), 14) << "the 15th is due 5 ns after 1 s";
}

}  // namespace
}  // namespace behaviorlib::sim
