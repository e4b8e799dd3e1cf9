#include "behaviorlib/flight_common/flight_support.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>

#include <memory>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::flight {
namespace {

// The code of a failed read of the pose or velocity estimate (Vehicle): none
// published yet, no data channel configured, or the channel not reachable.
v1::SituationReason estimateReadCode(const absl::Status& status) {
  if (status.code() == absl::StatusCode::kNotFound) return v1::SITUATION_REASON_INPUT_MISSING;
  if (status.code() == absl::StatusCode::kFailedPrecondition) {
    return v1::SITUATION_REASON_CONFIGURATION;
  }
  return v1::SITUATION_REASON_PLATFORM_UNAVAILABLE;
}

}  // namespace

absl::Status FlightSettings::configure(const config::v1::FlightConfig& config) {
  pose_timeout = seconds(config.pose_timeout_s());
  lease_ttl = seconds(config.lease_ttl_s());
  preempt_lease = config.preempt_lease();
  min_battery_ratio = config.min_battery_ratio();
  full_battery_ratio = config.full_battery_ratio();
  progress_window = seconds(config.progress_window_s());
  wind.mass_kg = config.mass_kg();
  wind.linear_drag_n_s_m = config.linear_drag_n_s_m();
  wind.quadratic_drag_n_s2_m2 = config.quadratic_drag_n_s2_m2();
  wind.time_constant_s = config.wind_time_constant_s();
  calm_wind_m_s = config.calm_wind_m_s();
  max_wind_m_s = config.max_wind_m_s();
  if (wind.linear_drag_n_s_m <= 0.0 && wind.quadratic_drag_n_s2_m2 <= 0.0) {
    return absl::InvalidArgumentError(
        "linear_drag_n_s_m and quadratic_drag_n_s2_m2 cannot both be 0");
  }
  if (max_wind_m_s <= calm_wind_m_s) {
    return absl::InvalidArgumentError("max_wind_m_s must be above calm_wind_m_s");
  }
  return absl::OkStatus();
}

BehaviorOptions flightBehaviorOptions(Duration maximum_execution_time) {
  BehaviorOptions options;
  options.frequency_hz = 20.0;
  options.maximum_execution_time = maximum_execution_time;
  options.watchdog_timeout = std::chrono::seconds(2);
  return options;
}

bool airborne(v1::FlightState state) {
  return state == v1::FLIGHT_STATE_TAKING_OFF || state == v1::FLIGHT_STATE_FLYING ||
         state == v1::FLIGHT_STATE_HOVERING || state == v1::FLIGHT_STATE_LANDING;
}

bool flying(v1::FlightState state) {
  return state == v1::FLIGHT_STATE_FLYING || state == v1::FLIGHT_STATE_HOVERING;
}

std::optional<std::string> staleness(absl::FunctionRef<std::string()> what,
                                     const v1::Header& header, TimePoint now, Duration limit) {
  const Duration age = now - stampTime(header);
  if (age <= limit) return std::nullopt;
  return what() + " is " + secondsText(age) + " old (limit " + secondsText(limit) + ")";
}

void refuseFirst(Situation* situation, v1::SituationReason code, std::string reason) {
  situation->feasible = false;
  situation->performance_ratio = 0.0;
  situation->codes.resize(situation->reasons.size(), v1::SITUATION_REASON_UNSPECIFIED);
  situation->reasons.insert(situation->reasons.begin(), std::move(reason));
  situation->codes.insert(situation->codes.begin(), code);
}

std::optional<SituationProblem> missingSensor(channel::ChannelClient& channel,
                                              const std::string& robot_id,
                                              const std::vector<SensorNeed>& needs, TimePoint now) {
  namespace pb = google::protobuf;
  for (const SensorNeed& need : needs) {
    const std::string topic = "robots/" + robot_id + "/" + need.name;
    auto sample = channel.getLatest(topic, kChannelReadTimeout);
    if (!sample.ok()) {
      if (sample.status().code() == absl::StatusCode::kNotFound) {
        return SituationProblem{v1::SITUATION_REASON_INPUT_MISSING,
                                "no " + need.what + ": nothing on " + topic +
                                    " (is the simulator, or the sensor driver, publishing it?)"};
      }
      return SituationProblem{v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
                              "cannot read " + topic + " from the channel at " + channel.address() +
                                  ": " + std::string(sample.status().message())};
    }
    // The sample's own type, found by its type URL, and its header.
    const std::string& url = sample->sample().type_url();
    const pb::Descriptor* type =
        pb::DescriptorPool::generated_pool()->FindMessageTypeByName(url.substr(url.rfind('/') + 1));
    std::unique_ptr<pb::Message> message(
        type ? pb::MessageFactory::generated_factory()->GetPrototype(type)->New() : nullptr);
    const pb::FieldDescriptor* field = type ? type->FindFieldByName("header") : nullptr;
    v1::Header header;
    if (message && field && field->message_type() == v1::Header::descriptor() &&
        sample->sample().UnpackTo(message.get())) {
      header.CopyFrom(message->GetReflection()->GetMessage(*message, field));
    }
    if (auto stale = staleness([&] { return "the latest sample on " + topic; }, header, now,
                               2 * need.limit)) {
      return SituationProblem{v1::SITUATION_REASON_INPUT_STALE, "no " + need.what + ": " + *stale};
    }
  }
  return std::nullopt;
}

std::optional<std::string> checkFlightInputs(Vehicle& vehicle, TimePoint now,
                                             const FlightSettings& settings,
                                             const VehicleLease* lease, bool need_twist,
                                             Held<v1::FlightStatus>* status,
                                             Held<v1::PoseStamped>* pose,
                                             Held<v1::TwistStamped>* twist) {
  // Shared, not copied: this runs every tick of every flight behavior.
  if (absl::Status s = vehicle.readFlightStatus(status); !s.ok()) return std::string(s.message());
  if (lease) {
    if (absl::Status s = lease->status();
        !s.ok() && s.code() != absl::StatusCode::kFailedPrecondition) {
      return std::string(s.message());
    }
  }
  if (absl::Status s = vehicle.readPoseEstimate(pose); !s.ok()) {
    return "pose estimate: " + std::string(s.message());
  }
  if (auto stale = staleness([&] { return "the pose estimate on " + vehicle.poseTopic(); },
                             (*pose)->header(), now, settings.pose_timeout)) {
    return stale;
  }
  if (need_twist) {
    if (absl::Status s = vehicle.readTwistEstimate(twist); !s.ok()) {
      return "velocity estimate: " + std::string(s.message());
    }
    if (auto stale = staleness([] { return std::string("the velocity estimate"); },
                               (*twist)->header(), now, settings.pose_timeout)) {
      return stale;
    }
  }
  return std::nullopt;
}

std::optional<v1::FlightStatus> checkFlightPreconditions(Vehicle& vehicle, TimePoint now,
                                                         const FlightSettings& settings,
                                                         bool check_battery, bool need_twist,
                                                         Situation* situation) {
  auto add = [&](v1::SituationReason code, std::string reason) {
    situation->feasible = false;
    situation->performance_ratio = 0.0;
    situation->add(code, std::move(reason));
  };
  std::optional<v1::FlightStatus> result;
  auto flight = vehicle.flightStatus();
  if (!flight.ok()) {
    add(v1::SITUATION_REASON_PLATFORM_UNAVAILABLE, std::string(flight.status().message()));
  } else {
    result = *flight;
    if (check_battery && flight->battery_ratio() < settings.min_battery_ratio) {
      add(v1::SITUATION_REASON_BATTERY_LOW, "battery at " + fixed2(flight->battery_ratio()) +
                                                ", below the minimum " +
                                                fixed2(settings.min_battery_ratio));
    } else if (situation->feasible) {
      situation->performance_ratio = batteryPerformance(
          flight->battery_ratio(), check_battery ? settings.min_battery_ratio : 0.0,
          settings.full_battery_ratio);
    }
  }
  auto pose = vehicle.poseEstimate();
  if (!pose.ok()) {
    add(estimateReadCode(pose.status()),
        "no pose estimate: " + std::string(pose.status().message()));
  } else if (auto stale = staleness([&] { return "the pose estimate on " + vehicle.poseTopic(); },
                                    pose->header(), now, settings.pose_timeout)) {
    add(v1::SITUATION_REASON_INPUT_STALE, *stale + "; is a localization behavior active?");
  }
  if (need_twist) {
    auto twist = vehicle.twistEstimate();
    if (!twist.ok()) {
      add(estimateReadCode(twist.status()),
          "no velocity estimate: " + std::string(twist.status().message()));
    } else if (auto stale = staleness([] { return std::string("the velocity estimate"); },
                                      twist->header(), now, settings.pose_timeout)) {
      add(v1::SITUATION_REASON_INPUT_STALE, *stale + "; is a localization behavior active?");
    }
  }
  return result;
}

Situation activeFlightSituation(const v1::FlightStatus& status, const VehicleLease* lease,
                                const FlightSettings& settings, bool check_battery) {
  if (status.state() == v1::FLIGHT_STATE_EMERGENCY || status.state() == v1::FLIGHT_STATE_CRASHED) {
    return Situation::infeasible(
        v1::SITUATION_REASON_FLIGHT_STATE,
        "the platform reports " + platform::flightStateName(status.state()));
  }
  if (lease) {
    if (absl::Status s = lease->status(); s.code() == absl::StatusCode::kFailedPrecondition) {
      return Situation::infeasible(v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
                                   std::string(s.message()));
    }
  }
  if (check_battery && status.battery_ratio() < settings.min_battery_ratio) {
    return Situation::infeasible(v1::SITUATION_REASON_BATTERY_LOW,
                                 "battery at " + fixed2(status.battery_ratio()) +
                                     ", below the minimum " + fixed2(settings.min_battery_ratio));
  }
  return Situation::ok(batteryPerformance(status.battery_ratio(),
                                          check_battery ? settings.min_battery_ratio : 0.0,
                                          settings.full_battery_ratio));
}

}  // namespace behaviorlib::flight
