#include "coordinator/telemetry/vehicle_telemetry.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <thread>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "google/protobuf/message.h"
#include "google/protobuf/util/time_util.h"

namespace behaviorlib::coordinator {

namespace {

using google::protobuf::util::TimeUtil;

constexpr size_t kMaxRobotIdBytes = 128;
constexpr double kDefaultMaxAgeS = 1.0;

// What each kind is: its topic below robots/{id}/ and the message it carries.
struct KindInfo {
  v1::VehicleSampleKind kind;
  const char* suffix;
  const google::protobuf::Descriptor* (*descriptor)();
};

const KindInfo kKinds[] = {
    {v1::VEHICLE_SAMPLE_KIND_POSE, "self_localization/pose", &v1::PoseStamped::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_TWIST, "self_localization/twist", &v1::TwistStamped::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_FLIGHT_STATE, "flight_state", &v1::FlightStatus::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_BATTERY, "battery", &v1::BatteryState::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_IMU, "imu", &v1::Imu::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_GPS, "gps", &v1::PositionFix::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_BARO, "baro", &v1::Altitude::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_LINEAR_SPEED, "linear_speed", &v1::TwistStamped::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_GROUND_TRUTH_POSE, "ground_truth/pose", &v1::PoseStamped::descriptor},
    {v1::VEHICLE_SAMPLE_KIND_GROUND_TRUTH_TWIST, "ground_truth/twist",
     &v1::TwistStamped::descriptor},
};

const KindInfo* infoOf(v1::VehicleSampleKind kind) {
  for (const KindInfo& info : kKinds) {
    if (info.kind == kind) return &info;
  }
  return nullptr;
}

absl::Status badField(const std::string& field, const std::string& message) {
  return errors::withFieldViolation(
      errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST), field, message);
}

// "ground_truth_pose" for VEHICLE_SAMPLE_KIND_GROUND_TRUTH_POSE (the
// clients' name).
std::string kindName(v1::VehicleSampleKind kind) {
  return absl::AsciiStrToLower(
      absl::StripPrefix(v1::VehicleSampleKind_Name(kind), "VEHICLE_SAMPLE_KIND_"));
}

// The stamp of a sample: every message of the list has a Header as its
// field `header` (a stamp of 0 when it has none).
google::protobuf::Timestamp stampOf(const google::protobuf::Any& any,
                                    const google::protobuf::Descriptor* descriptor) {
  const google::protobuf::FieldDescriptor* field = descriptor->FindFieldByName("header");
  if (field == nullptr || field->message_type() != v1::Header::descriptor()) return {};
  std::unique_ptr<google::protobuf::Message> message(
      google::protobuf::MessageFactory::generated_factory()->GetPrototype(descriptor)->New());
  if (!message->ParseFromString(any.value())) return {};
  const auto& header =
      static_cast<const v1::Header&>(message->GetReflection()->GetMessage(*message, field));
  return header.stamp();
}

}  // namespace

class VehicleTelemetry::WatchImpl final : public VehicleTelemetry::Watch {
 public:
  WatchImpl(VehicleTelemetry* owner, std::string caller)
      : owner_(owner), caller_(std::move(caller)) {}
  ~WatchImpl() override { owner_->retire(std::move(subscription), std::move(caller_)); }
  std::unique_ptr<channel::Subscription> subscription;

 private:
  VehicleTelemetry* owner_;
  std::string caller_;
};

VehicleTelemetry::VehicleTelemetry(channel::ChannelClient& channel, const Clock* vehicle_clock,
                                   std::function<bool(const std::string&)> known_robot,
                                   VehicleTelemetryLimits limits,
                                   std::function<void(size_t)> watches_changed)
    : channel_(channel),
      vehicle_clock_(vehicle_clock),
      known_robot_(std::move(known_robot)),
      limits_(limits),
      watches_changed_(std::move(watches_changed)),
      reaper_([this] { reap(); }) {}

VehicleTelemetry::~VehicleTelemetry() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
  }
  reaper_.join();
}

absl::StatusOr<std::string> VehicleTelemetry::topicOf(const std::string& robot_id,
                                                      v1::VehicleSampleKind kind) {
  const KindInfo* info = infoOf(kind);
  if (info == nullptr) {
    return badField("kind", absl::StrCat("kind ", static_cast<int>(kind),
                                         " is not a vehicle sample: use one of POSE, TWIST, "
                                         "FLIGHT_STATE, BATTERY, IMU, GPS, BARO, LINEAR_SPEED, "
                                         "GROUND_TRUTH_POSE, GROUND_TRUTH_TWIST"));
  }
  return "robots/" + robot_id + "/" + info->suffix;
}

absl::Status VehicleTelemetry::checkRobot(const std::string& robot_id) const {
  if (robot_id.empty()) return badField("robot_id", "robot_id is required");
  if (robot_id.size() > kMaxRobotIdBytes) {
    return badField("robot_id",
                    absl::StrCat("robot_id is longer than ", kMaxRobotIdBytes, " bytes"));
  }
  if (!known_robot_ || !known_robot_(robot_id)) {
    return errors::withReason(absl::NotFoundError(absl::StrCat(
                                  "robot '", robot_id,
                                  "' is not known to the coordinator: no behavior system "
                                  "of it is registered and no --flight-controller names it")),
                              v1::UNKNOWN_ROBOT, {{"robot", robot_id}});
  }
  return absl::OkStatus();
}

absl::StatusOr<v1::VehicleSample> VehicleTelemetry::toSample(
    const std::string& robot_id, v1::VehicleSampleKind kind,
    const v1::SubscribeResponse& response) const {
  const KindInfo* info = infoOf(kind);
  const google::protobuf::Descriptor* descriptor = info->descriptor();
  if (response.sample().type_url() !=
      absl::StrCat(errors::kTypeUrlPrefix, descriptor->full_name())) {
    return errors::withReason(absl::FailedPreconditionError(absl::StrCat(
                                  response.topic(), " carries ", response.sample().type_url(),
                                  ", not ", descriptor->full_name())),
                              v1::TOPIC_EMPTY, {{"topic", response.topic()}});
  }
  v1::VehicleSample out;
  out.set_robot_id(robot_id);
  out.set_kind(kind);
  out.set_topic(response.topic());
  *out.mutable_sample() = response.sample();
  *out.mutable_stamp() = stampOf(response.sample(), descriptor);
  out.set_topic_seq(response.topic_seq());
  if (vehicle_clock_ != nullptr && vehicle_clock_->valid()) {
    const TimePoint stamp(std::chrono::seconds(out.stamp().seconds()) +
                          std::chrono::nanoseconds(out.stamp().nanos()));
    const Duration age = std::max(Duration::zero(), vehicle_clock_->now() - stamp);
    *out.mutable_age() = TimeUtil::NanosecondsToDuration(age.count());
  }
  return out;
}

absl::StatusOr<v1::VehicleSample> VehicleTelemetry::latest(const std::string& robot_id,
                                                           v1::VehicleSampleKind kind,
                                                           double max_age_s) {
  if (absl::Status s = checkRobot(robot_id); !s.ok()) return s;
  absl::StatusOr<std::string> topic = topicOf(robot_id, kind);
  if (!topic.ok()) return topic.status();
  if (!std::isfinite(max_age_s)) return badField("max_age_s", "max_age_s must be a finite number");
  const double limit_s = max_age_s == 0 ? kDefaultMaxAgeS : max_age_s;
  // A topic its publisher gates by interest keeps its last sample while
  // nobody wants it, and the broker's GetLatest makes it wanted: a stale
  // sample is asked for again (every 20 ms, within the read timeout) until a
  // fresh one came or the time is up.
  const auto give_up = std::chrono::steady_clock::now() + limits_.read_timeout;
  for (;;) {
    absl::StatusOr<v1::SubscribeResponse> response =
        channel_.getLatest(*topic, limits_.read_timeout);
    if (!response.ok()) {
      if (response.status().code() == absl::StatusCode::kNotFound) {
        return errors::withReason(
            absl::NotFoundError(absl::StrCat(
                "no ", kindName(kind), " sample of ", robot_id, " yet (nothing on ", *topic,
                kind == v1::VEHICLE_SAMPLE_KIND_POSE || kind == v1::VEHICLE_SAMPLE_KIND_TWIST
                    ? "): is a localization behavior such as SELF_LOCALIZE_WITH_GROUND_TRUTH "
                      "active?"
                    : ")")),
            v1::TOPIC_EMPTY, {{"topic", *topic}});
      }
      return errors::rewrap(response.status(),
                            absl::StrCat("cannot read ", *topic,
                                         " from the data channel: ", response.status().message()));
    }
    absl::StatusOr<v1::VehicleSample> sample = toSample(robot_id, kind, *response);
    if (!sample.ok() || max_age_s < 0 || !sample->has_age()) return sample;
    const double age_s = static_cast<double>(TimeUtil::DurationToNanoseconds(sample->age())) * 1e-9;
    if (age_s <= limit_s) return sample;
    if (std::chrono::steady_clock::now() >= give_up) {
      return errors::withReason(
          absl::FailedPreconditionError(absl::StrFormat(
              "the newest %s sample of %s is %.3f s old (limit %.3f s): nothing publishes %s",
              kindName(kind), robot_id, age_s, limit_s, *topic)),
          v1::SAMPLE_STALE,
          {{"topic", *topic},
           {"age_s", absl::StrFormat("%.3f", age_s)},
           {"max_age_s", absl::StrFormat("%.3f", limit_s)}});
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

absl::StatusOr<std::unique_ptr<VehicleTelemetry::Watch>> VehicleTelemetry::watch(
    const std::string& caller, const v1::WatchVehicleRequest& request,
    std::function<void(v1::WatchVehicleResponse)> on_sample) {
  if (absl::Status s = checkRobot(request.robot_id()); !s.ok()) return s;
  absl::StatusOr<std::string> topic = topicOf(request.robot_id(), request.kind());
  if (!topic.ok()) return topic.status();
  const double rate = request.max_rate_hz();
  if (!std::isfinite(rate) || rate < 0 || rate > limits_.max_rate_hz) {
    return badField("max_rate_hz", absl::StrFormat("max_rate_hz must be within 0 .. %g (0: %g)",
                                                   limits_.max_rate_hz, limits_.default_rate_hz));
  }
  {
    absl::MutexLock lock(&mutex_);
    size_t& mine = per_caller_[caller];
    const bool all = open_ >= limits_.max_watches;
    if (all || mine >= limits_.max_watches_per_caller) {
      if (mine == 0) per_caller_.erase(caller);
      const size_t limit = all ? limits_.max_watches : limits_.max_watches_per_caller;
      return errors::withReason(
          absl::ResourceExhaustedError(absl::StrCat(
              all ? "the coordinator serves " : "this caller has ", limit,
              " vehicle watches open, the most it may (--max-vehicle-watches): close one first")),
          v1::LIMIT_EXCEEDED, {{"limit", std::to_string(limit)}});
    }
    ++mine;
    ++open_;
    if (watches_changed_) watches_changed_(open_);
  }
  auto watch = std::make_unique<WatchImpl>(this, caller);
  channel::SubscribeOptions options;
  options.mode = v1::DELIVERY_MODE_LATEST;
  options.send_latest_first = request.send_latest_first();
  options.shared_memory = false;  // the broker applies the rate on the stream
  options.max_rate_hz = rate == 0 ? limits_.default_rate_hz : rate;
  watch->subscription = channel_.subscribe(
      *topic, options,
      [this, robot = request.robot_id(), kind = request.kind(),
       on_sample = std::move(on_sample)](const v1::SubscribeResponse& response) {
        absl::StatusOr<v1::VehicleSample> sample = toSample(robot, kind, response);
        if (!sample.ok()) return;  // a foreign type on the topic: the broker refuses it
        v1::WatchVehicleResponse message;
        *message.mutable_sample() = *std::move(sample);
        message.set_dropped_count(response.dropped_count());
        on_sample(std::move(message));
      });
  return std::unique_ptr<Watch>(std::move(watch));
}

size_t VehicleTelemetry::openWatches() const {
  absl::MutexLock lock(&mutex_);
  return open_;
}

void VehicleTelemetry::retire(std::unique_ptr<channel::Subscription> subscription,
                              std::string caller) {
  absl::MutexLock lock(&mutex_);
  retired_.emplace_back(std::move(subscription), std::move(caller));
}

void VehicleTelemetry::reap() {
  for (;;) {
    std::vector<std::pair<std::unique_ptr<channel::Subscription>, std::string>> batch;
    {
      absl::MutexLock lock(&mutex_);
      mutex_.Await(absl::Condition(
          +[](VehicleTelemetry* t) ABSL_EXCLUSIVE_LOCKS_REQUIRED(t->mutex_) {
            return t->stopping_ || !t->retired_.empty();
          },
          this));
      if (retired_.empty()) return;  // stopping, and nothing left to end
      batch.swap(retired_);
    }
    for (auto& [subscription, caller] : batch) {
      subscription.reset();  // joins the reader: no callback runs after this
      absl::MutexLock lock(&mutex_);
      --open_;
      auto it = per_caller_.find(caller);
      if (it != per_caller_.end() && --it->second == 0) per_caller_.erase(it);
      if (watches_changed_) watches_changed_(open_);
    }
  }
}

}  // namespace behaviorlib::coordinator
