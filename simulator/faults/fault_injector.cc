#include "simulator/faults/fault_injector.h"

#include <google/protobuf/util/time_util.h>

#include <cmath>
#include <cstdio>
#include <optional>

#include "behaviorlib/error_details.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;

const char kComponents[] =
    "FAILURE_COMPONENT_GPS, _IMU, _BARO, _LINEAR_SPEED, _LIDAR, _CAMERA, _MOTOR, _BATTERY or "
    "_WIND";
const char kSensorTypes[] =
    "FAILURE_TYPE_OFF, _STUCK, _NOISY, _GARBAGE, _INTERMITTENT, _DELAYED or _OK";

std::string number(double value) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%g", value);
  return buffer;
}

std::string typeName(v1::FailureType type) {
  const std::string& name = v1::FailureType_Name(type);
  return name.empty() ? std::to_string(static_cast<int>(type)) : name;
}

std::string componentFullName(v1::FailureComponent component) {
  const std::string& name = v1::FailureComponent_Name(component);
  return name.empty() ? std::to_string(static_cast<int>(component)) : name;
}

/// The sensor a component names, if it is one.
std::optional<SensorKind> sensorOf(v1::FailureComponent component) {
  switch (component) {
    case v1::FAILURE_COMPONENT_GPS:
      return SensorKind::kGps;
    case v1::FAILURE_COMPONENT_IMU:
      return SensorKind::kImu;
    case v1::FAILURE_COMPONENT_BARO:
      return SensorKind::kBaro;
    case v1::FAILURE_COMPONENT_LINEAR_SPEED:
      return SensorKind::kLinearSpeed;
    case v1::FAILURE_COMPONENT_LIDAR:
      return SensorKind::kLidar;
    case v1::FAILURE_COMPONENT_CAMERA:
      return SensorKind::kCamera;
    case v1::FAILURE_COMPONENT_BATTERY:
      return SensorKind::kBattery;
    default:
      return std::nullopt;
  }
}

std::optional<SensorFaultType> sensorFaultOf(v1::FailureType type) {
  switch (type) {
    case v1::FAILURE_TYPE_OK:
      return SensorFaultType::kOk;
    case v1::FAILURE_TYPE_OFF:
      return SensorFaultType::kOff;
    case v1::FAILURE_TYPE_STUCK:
      return SensorFaultType::kStuck;
    case v1::FAILURE_TYPE_NOISY:
      return SensorFaultType::kNoisy;
    case v1::FAILURE_TYPE_GARBAGE:
      return SensorFaultType::kGarbage;
    case v1::FAILURE_TYPE_INTERMITTENT:
      return SensorFaultType::kIntermittent;
    case v1::FAILURE_TYPE_DELAYED:
      return SensorFaultType::kDelayed;
    default:
      return std::nullopt;
  }
}

/// The types whose strength is `intensity` and so need it above 0.
bool needsIntensity(v1::FailureType type) {
  return type == v1::FAILURE_TYPE_NOISY || type == v1::FAILURE_TYPE_INTERMITTENT ||
         type == v1::FAILURE_TYPE_DEGRADED;
}

absl::Status notAccepted(v1::FailureComponent component, v1::FailureType type,
                         const std::string& accepted) {
  return absl::InvalidArgumentError(componentFullName(component) + " accepts " + accepted +
                                    ", not " + typeName(type));
}

/// Checks what does not depend on the component.
absl::Status validateCommon(const v1::InjectFailureRequest& r) {
  if (r.component() == v1::FAILURE_COMPONENT_UNSPECIFIED ||
      !v1::FailureComponent_IsValid(r.component())) {
    return absl::InvalidArgumentError(std::string("component must be one of ") + kComponents +
                                      ", got " + componentFullName(r.component()));
  }
  if (r.type() == v1::FAILURE_TYPE_UNSPECIFIED || !v1::FailureType_IsValid(r.type())) {
    return absl::InvalidArgumentError(
        "type must be set: FAILURE_TYPE_OK clears a failure; sensors take " +
        std::string(kSensorTypes) +
        "; a motor FAILURE_TYPE_OFF or _DEGRADED; the wind FAILURE_TYPE_SET; got " +
        typeName(r.type()));
  }
  if (!std::isfinite(r.intensity()) || r.intensity() < 0.0 || r.intensity() > 1.0) {
    return absl::InvalidArgumentError("intensity must be within [0, 1], got " +
                                      number(r.intensity()));
  }
  if (needsIntensity(r.type()) && r.intensity() <= 0.0) {
    return absl::InvalidArgumentError(typeName(r.type()) +
                                      " needs an intensity in (0, 1] (its strength), got 0");
  }
  if (r.has_delay()) {
    if (r.delay().seconds() < 0 || r.delay().nanos() < 0 || r.delay().nanos() > 999999999) {
      return absl::InvalidArgumentError("delay must not be negative, got " +
                                        TimeUtil::ToString(r.delay()));
    }
  }
  if (r.type() == v1::FAILURE_TYPE_DELAYED) {
    const int64_t ns = r.has_delay() ? TimeUtil::DurationToNanoseconds(r.delay()) : 0;
    if (ns <= 0 || ns > FaultInjector::kMaxDelay.count()) {
      return absl::InvalidArgumentError(
          "FAILURE_TYPE_DELAYED needs a delay in (0, 10 s], got " +
          (r.has_delay() ? TimeUtil::ToString(r.delay()) : std::string("none")));
    }
  }
  if (r.component() != v1::FAILURE_COMPONENT_WIND && r.robot_id().empty()) {
    return absl::InvalidArgumentError("robot_id is required for " +
                                      componentFullName(r.component()));
  }
  return absl::OkStatus();
}

}  // namespace

FaultInjector::FaultInjector(Simulation& simulation, SensorSystem* sensors)
    : simulation_(simulation), sensors_(sensors) {}

std::string_view FaultInjector::componentName(v1::FailureComponent component) {
  switch (component) {
    case v1::FAILURE_COMPONENT_GPS:
      return "gps";
    case v1::FAILURE_COMPONENT_IMU:
      return "imu";
    case v1::FAILURE_COMPONENT_BARO:
      return "baro";
    case v1::FAILURE_COMPONENT_LIDAR:
      return "lidar";
    case v1::FAILURE_COMPONENT_CAMERA:
      return "camera";
    case v1::FAILURE_COMPONENT_MOTOR:
      return "motor";
    case v1::FAILURE_COMPONENT_BATTERY:
      return "battery";
    case v1::FAILURE_COMPONENT_WIND:
      return "wind";
    case v1::FAILURE_COMPONENT_LINEAR_SPEED:
      return "linear_speed";
    default:
      return "";
  }
}

absl::Status FaultInjector::inject(const v1::InjectFailureRequest& request) {
  if (absl::Status s = validateCommon(request); !s.ok()) return s;
  switch (request.component()) {
    case v1::FAILURE_COMPONENT_MOTOR:
      return injectMotor(request);
    case v1::FAILURE_COMPONENT_WIND:
      return injectWind(request);
    case v1::FAILURE_COMPONENT_BATTERY:
      if (request.type() == v1::FAILURE_TYPE_DEGRADED) return injectBattery(request);
      break;
    default:
      break;
  }
  const std::optional<SensorKind> kind = sensorOf(request.component());
  if (!kind) {
    return absl::InvalidArgumentError(std::string("component must be one of ") + kComponents);
  }
  return injectSensor(request, *kind);
}

absl::Status FaultInjector::injectSensor(const v1::InjectFailureRequest& request, SensorKind kind) {
  const std::optional<SensorFaultType> type = sensorFaultOf(request.type());
  if (!type) {
    return notAccepted(
        request.component(), request.type(),
        std::string(kSensorTypes) +
            (kind == SensorKind::kBattery ? " (and _DEGRADED: loss of charge)" : ""));
  }
  if (sensors_ == nullptr) {
    return errors::withReason(
        absl::FailedPreconditionError(
            "this simulator publishes no sensors: start it with --channel to fail " +
            componentFullName(request.component())),
        v1::FEATURE_NOT_ENABLED, {{"feature", "sensors"}});
  }
  SensorFault fault;
  fault.type = *type;
  fault.intensity = request.intensity();
  if (*type == SensorFaultType::kDelayed) {
    fault.delay = SimDuration(TimeUtil::DurationToNanoseconds(request.delay()));
  }
  const std::string& robot_id = request.robot_id();
  auto applied = simulation_.withModel(robot_id, [&](VehicleModel&, SimTime now) {
    sensors_->setFault(robot_id, kind, now, fault);
    return true;
  });
  if (!applied.ok()) return applied.status();
  setActive(robot_id, componentName(request.component()), *type == SensorFaultType::kOk ? 0 : 1);
  return absl::OkStatus();
}

absl::Status FaultInjector::injectMotor(const v1::InjectFailureRequest& request) {
  double efficiency = 1.0;
  switch (request.type()) {
    case v1::FAILURE_TYPE_OK:
      break;
    case v1::FAILURE_TYPE_OFF:
      efficiency = 0.0;
      break;
    case v1::FAILURE_TYPE_DEGRADED:
      efficiency = 1.0 - request.intensity();
      break;
    default:
      return notAccepted(request.component(), request.type(),
                         "FAILURE_TYPE_OFF (stops), FAILURE_TYPE_DEGRADED (loses intensity of its "
                         "thrust) or FAILURE_TYPE_OK");
  }
  const std::string& robot_id = request.robot_id();
  const int motor = static_cast<int>(std::min<uint32_t>(request.motor_index(), 1u << 30));
  // The model's motor count, or -1 once applied.
  auto applied = simulation_.withModel(robot_id, [&](VehicleModel& model, SimTime) {
    const int count = model.motorCount();
    if (motor >= count) return count;
    model.setMotorEfficiency(motor, efficiency);
    return -1;
  });
  if (!applied.ok()) return applied.status();
  if (*applied == 0) {
    return absl::InvalidArgumentError(robot_id + " has no motor that can fail");
  }
  if (*applied > 0) {
    return absl::InvalidArgumentError("motor_index must be within 0.." +
                                      std::to_string(*applied - 1) + " (" + robot_id + " has " +
                                      std::to_string(*applied) + " motors), got " +
                                      std::to_string(request.motor_index()));
  }
  int failed = 0;
  {
    std::lock_guard lock(mutex_);
    std::set<int>& motors = failed_motors_[robot_id];
    if (efficiency < 1.0) {
      motors.insert(motor);
    } else {
      motors.erase(motor);
    }
    failed = static_cast<int>(motors.size());
  }
  setActive(robot_id, "motor", failed);
  return absl::OkStatus();
}

absl::Status FaultInjector::injectBattery(const v1::InjectFailureRequest& request) {
  const std::string& robot_id = request.robot_id();
  auto applied = simulation_.withModel(robot_id, [&](VehicleModel& model, SimTime) {
    model.dropBatteryCharge(request.intensity());
    return true;
  });
  return applied.ok() ? absl::OkStatus() : applied.status();
}

absl::Status FaultInjector::injectWind(const v1::InjectFailureRequest& request) {
  Wind wind;
  switch (request.type()) {
    case v1::FAILURE_TYPE_OK:
      break;
    case v1::FAILURE_TYPE_SET: {
      const v1::Vector3& v = request.wind_velocity_m_s();
      wind.velocity_m_s = Eigen::Vector3d(v.x(), v.y(), v.z());
      wind.gust_stddev_m_s = request.gust_stddev_m_s();
      if (!wind.velocity_m_s.allFinite() || wind.velocity_m_s.norm() > kMaxWindMS) {
        return absl::InvalidArgumentError(
            "wind_velocity_m_s must be finite and at most 30 m/s, got (" + number(v.x()) + ", " +
            number(v.y()) + ", " + number(v.z()) + ")");
      }
      if (!std::isfinite(wind.gust_stddev_m_s) || wind.gust_stddev_m_s < 0.0 ||
          wind.gust_stddev_m_s > kMaxGustStddevMS) {
        return absl::InvalidArgumentError("gust_stddev_m_s must be within [0, 10], got " +
                                          number(wind.gust_stddev_m_s));
      }
      break;
    }
    default:
      return notAccepted(request.component(), request.type(),
                         "FAILURE_TYPE_SET (wind_velocity_m_s, gust_stddev_m_s) or "
                         "FAILURE_TYPE_OK (calm)");
  }
  simulation_.setWind(wind);
  const bool blowing = wind.velocity_m_s.squaredNorm() > 0.0 || wind.gust_stddev_m_s > 0.0;
  setActive("", "wind", blowing ? 1 : 0);
  return absl::OkStatus();
}

void FaultInjector::setActive(const std::string& robot_id, std::string_view component, int count) {
  std::lock_guard lock(mutex_);
  active_[{robot_id, std::string(component)}] = count;
}

void FaultInjector::reset() {
  std::lock_guard lock(mutex_);
  for (auto& [key, count] : active_) count = 0;
  failed_motors_.clear();
}

std::vector<FaultInjector::Active> FaultInjector::active() const {
  std::lock_guard lock(mutex_);
  std::vector<Active> out;
  for (const auto& [key, count] : active_) out.push_back({key.first, key.second, count});
  return out;
}

}  // namespace behaviorlib::sim
