#include "behaviorlib/recorder/recorder.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/util/time_util.h>

#include <chrono>
#include <set>
#include <thread>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/embedded_descriptor_pool.h"
#include "behaviorlib/v1/mission.pb.h"

namespace behaviorlib::recorder {

namespace {

constexpr char kTypeUrlPrefix[] = "type.googleapis.com/";

void addFile(const google::protobuf::FileDescriptor* file, std::set<std::string>* added,
             google::protobuf::FileDescriptorSet* set) {
  if (!added->insert(file->name()).second) return;
  for (int i = 0; i < file->dependency_count(); ++i) addFile(file->dependency(i), added, set);
  file->CopyTo(set->add_file());
}

uint64_t systemNowNs() {
  return static_cast<uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(
                                   std::chrono::system_clock::now().time_since_epoch())
                                   .count());
}

uint64_t nanos(const google::protobuf::Timestamp& stamp) {
  if (stamp.seconds() <= 0 && stamp.nanos() <= 0) return 0;
  return static_cast<uint64_t>(google::protobuf::util::TimeUtil::TimestampToNanoseconds(stamp));
}

std::string typeOfUrl(const std::string& type_url) {
  const size_t slash = type_url.rfind('/');
  return slash == std::string::npos ? type_url : type_url.substr(slash + 1);
}

// The broker's topic rule (services/channel/topic.cc) for one segment.
bool validSegment(std::string_view segment) {
  if (segment.empty()) return false;
  for (char c : segment) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '-' || c == '.';
    if (!ok) return false;
  }
  return true;
}

follower::FollowerOptions followerOptions(const RecorderOptions& options) {
  follower::FollowerOptions follower;
  follower.data_channel = options.data_channel;
  for (const std::string& entry : options.topics) {
    if (auto topic = parseTopic(entry); topic.ok()) follower.vehicle_topics.push_back(*topic);
  }
  follower.vehicle_period = std::chrono::milliseconds(0);  // what the broker sends
  follower.max_robots = options.max_robots;
  follower.mission_poll = options.mission_poll;
  follower.max_watched_missions = options.max_watched_missions;
  return follower;
}

}  // namespace

std::vector<std::string> defaultTopics() {
  return {"ground_truth/pose@30", "ground_truth/twist@30", "self_localization/pose@30",
          "flight_state",         "markers/detections",    "map/occupied"};
}

absl::StatusOr<follower::FollowerOptions::VehicleTopic> parseTopic(const std::string& entry) {
  follower::FollowerOptions::VehicleTopic topic;
  const size_t at = entry.find('@');
  topic.name = entry.substr(0, at);
  for (absl::string_view segment : absl::StrSplit(topic.name, '/')) {
    if (!validSegment(std::string_view(segment.data(), segment.size()))) {
      return absl::InvalidArgumentError(
          absl::StrCat("recorded topic '", entry,
                       "': a name is '/'-separated segments of letters, digits, '_', '-' and '.'"));
    }
  }
  if (at == std::string::npos) return topic;
  if (!absl::SimpleAtod(entry.substr(at + 1), &topic.max_rate_hz) ||
      !(topic.max_rate_hz > 0 && topic.max_rate_hz <= 100000)) {
    return absl::InvalidArgumentError(
        absl::StrCat("recorded topic '", entry,
                     "': the rate after '@' is samples a second, a number in (0, 100000]"));
  }
  return topic;
}

absl::StatusOr<std::string> schemaOf(const std::string& type) {
  const google::protobuf::Descriptor* descriptor =
      embedded::descriptorPool().FindMessageTypeByName(type);
  if (descriptor == nullptr) {
    return absl::NotFoundError(absl::StrCat("no descriptor of the message type ", type));
  }
  google::protobuf::FileDescriptorSet set;
  std::set<std::string> added;
  addFile(descriptor->file(), &added, &set);
  return set.SerializeAsString();
}

Recorder::Recorder(std::shared_ptr<grpc::Channel> coordinator, RecorderOptions options,
                   std::unique_ptr<mcap::Writer> writer)
    : options_(std::move(options)),
      writer_(std::move(writer)),
      follower_(std::move(coordinator), followerOptions(options_), this) {}

absl::StatusOr<std::unique_ptr<Recorder>> Recorder::start(
    std::shared_ptr<grpc::Channel> coordinator, RecorderOptions options) {
  if (!options.now_ns) options.now_ns = systemNowNs;
  for (const std::string& entry : options.topics) {
    if (auto topic = parseTopic(entry); !topic.ok()) return topic.status();
  }
  auto writer = mcap::Writer::create(options.path, kProfile, "behaviorlib recorder");
  if (!writer.ok()) return writer.status();
  std::unique_ptr<Recorder> recorder(
      new Recorder(std::move(coordinator), std::move(options), std::move(*writer)));
  recorder->follower_.start();
  return recorder;
}

Recorder::~Recorder() { stop().IgnoreError(); }

absl::Status Recorder::flush() {
  absl::MutexLock lock(&mutex_);
  if (stopped_) return absl::OkStatus();
  return writer_->flush();
}

absl::Status Recorder::stop() {
  {
    absl::MutexLock lock(&mutex_);
    if (stopped_) return absl::OkStatus();
  }
  // What the coordinator had when the stop was asked is in the file: a
  // recorder stopped right after a mission ended still holds its end.
  const bool drained = follower_.catchUp(options_.drain_timeout);
  follower_.shutdown();
  absl::MutexLock lock(&mutex_);
  stopped_ = true;
  stats_.drained = drained;
  const absl::Status closed = writer_->close();
  stats_.bytes = writer_->bytesWritten();
  return closed;
}

RecorderStats Recorder::stats() {
  absl::MutexLock lock(&mutex_);
  RecorderStats stats = stats_;
  if (!stopped_) stats.bytes = writer_->bytesWritten();
  return stats;
}

void Recorder::record(const std::string& topic, const std::string& type, const std::string& data,
                      uint64_t publish_time_ns) {
  const uint64_t now = options_.now_ns();
  absl::MutexLock lock(&mutex_);
  if (stopped_) return;
  if (writer_->bytesWritten() + data.size() > options_.max_bytes) {
    ++stats_.dropped;
    return;
  }
  const std::string key = absl::StrCat(topic, "\n", type);
  auto channel = channels_.find(key);
  if (channel == channels_.end()) {
    const absl::StatusOr<std::string> schema = schemaOf(type);
    absl::StatusOr<uint16_t> schema_id =
        schema.ok() ? writer_->addSchema(type, "protobuf", *schema) : schema.status();
    absl::StatusOr<uint16_t> channel_id =
        schema_id.ok() ? writer_->addChannel(*schema_id, topic, "protobuf") : schema_id.status();
    if (!channel_id.ok()) {
      ++stats_.dropped;
      return;
    }
    channel = channels_.emplace(key, *channel_id).first;
  }
  if (!writer_->write(channel->second, now, publish_time_ns == 0 ? now : publish_time_ns, data)
           .ok()) {
    ++stats_.dropped;
    return;
  }
  ++stats_.messages[topic];
}

void Recorder::onEvent(const v1::FleetEvent& event) {
  record(kEventsTopic, event.GetDescriptor()->full_name(), event.SerializeAsString(),
         nanos(event.wall_time()));
}

void Recorder::onMission(const v1::MissionStatus& status) {
  record(kMissionsTopic, status.GetDescriptor()->full_name(), status.SerializeAsString(), 0);
}

void Recorder::onBelief(const v1::Belief& belief) {
  record(kBeliefsTopic, belief.GetDescriptor()->full_name(), belief.SerializeAsString(),
         nanos(belief.update_time()));
}

void Recorder::onSample(const v1::SubscribeResponse& sample) {
  {
    // The broker's count of samples this subscription lost (a queue that
    // overflowed), cumulative per subscription: a new one starts at 0.
    absl::MutexLock lock(&mutex_);
    uint64_t& seen = broker_drops_[sample.topic()];
    if (sample.dropped_count() < seen) seen = 0;
    stats_.dropped += sample.dropped_count() - seen;
    seen = sample.dropped_count();
  }
  record(sample.topic(), typeOfUrl(sample.sample().type_url()), sample.sample().value(),
         nanos(sample.receive_time()));
}

void Recorder::onCoordinator(bool, const std::string&) {}

std::string replayTopic(const std::string& mcap_topic, const std::string& type,
                        const std::string& data) {
  std::string robot;
  std::string name;
  if (mcap_topic == kEventsTopic && type == v1::FleetEvent::descriptor()->full_name()) {
    v1::FleetEvent event;
    if (!event.ParseFromString(data)) return "";
    robot = event.has_behavior_event() ? event.behavior_event().robot_id()
                                       : event.system_state_changed().system().robot_id();
    name = "events";
  } else if (mcap_topic == kMissionsTopic && type == v1::MissionStatus::descriptor()->full_name()) {
    v1::MissionStatus status;
    if (!status.ParseFromString(data)) return "";
    robot = status.robot_id();
    name = "missions";
  } else if (mcap_topic == kBeliefsTopic && type == v1::Belief::descriptor()->full_name()) {
    v1::Belief belief;
    if (!belief.ParseFromString(data)) return "";
    robot = std::string(belief.key().substr(0, belief.key().find('/')));
    name = "beliefs";
  } else if (absl::StartsWith(mcap_topic, "robots/") || mcap_topic == "clock") {
    for (absl::string_view segment : absl::StrSplit(mcap_topic, '/')) {
      if (!validSegment(std::string_view(segment.data(), segment.size()))) return "";
    }
    return mcap_topic;
  } else {
    return "";
  }
  if (!validSegment(robot)) return "";
  return absl::StrCat("robots/", robot, "/recording/", name);
}

absl::StatusOr<ReplayStats> replay(const std::string& path, v1::DataChannel::StubInterface* broker,
                                   const ReplayOptions& options) {
  if (!(options.speed >= 0)) return absl::InvalidArgumentError("the speed must be 0 or more");
  const auto started = std::chrono::steady_clock::now();
  auto wait_until = options.wait_until;
  if (!wait_until) {
    wait_until = [started](uint64_t offset_ns) {
      std::this_thread::sleep_until(started + std::chrono::nanoseconds(offset_ns));
    };
  }
  grpc::ClientContext context;
  auto stream = broker->PublishAcked(&context);
  ReplayStats stats;
  uint64_t first_ns = 0;
  bool first = true;
  bool broken = false;
  const auto summary = mcap::scan(
      path, mcap::ReadLimits{}, [&](const mcap::ScanSummary& known, const mcap::Message& message) {
        const mcap::Channel& channel = known.channels.at(message.channel_id);
        if (!options.topic_prefix.empty() &&
            !absl::StartsWith(channel.topic, options.topic_prefix)) {
          return true;
        }
        const auto schema = known.schemas.find(channel.schema_id);
        const std::string type = schema == known.schemas.end() ? "" : schema->second.name;
        const std::string topic = replayTopic(channel.topic, type, message.data);
        if (topic.empty() || type.empty()) {
          ++stats.skipped;
          return true;
        }
        if (first) {
          first_ns = message.log_time_ns;
          first = false;
        }
        if (options.speed > 0 && message.log_time_ns > first_ns) {
          wait_until(static_cast<uint64_t>(static_cast<double>(message.log_time_ns - first_ns) /
                                           options.speed));
        }
        v1::PublishRequest request;
        request.set_topic(topic);
        request.mutable_sample()->set_type_url(kTypeUrlPrefix + type);
        request.mutable_sample()->set_value(message.data);
        if (!stream->Write(request)) {
          broken = true;
          return false;
        }
        ++stats.published;
        ++stats.topics[topic];
        return true;
      });
  // Everything written is taken once the broker answers a sync.
  v1::PublishRequest sync;
  sync.set_sync(true);
  v1::PublishResponse answer;
  if (!broken && stream->Write(sync)) stream->Read(&answer);
  stream->WritesDone();
  const grpc::Status status = stream->Finish();
  if (!summary.ok()) return summary.status();
  if (!status.ok()) {
    return absl::Status(static_cast<absl::StatusCode>(status.error_code()),
                        absl::StrCat("the broker refused the replay: ", status.error_message()));
  }
  if (broken) return absl::UnavailableError("the broker ended the replay stream");
  if (answer.accepted_count() != stats.published) {
    return absl::UnavailableError(absl::StrCat("the broker took ", answer.accepted_count(), " of ",
                                               stats.published, " samples"));
  }
  stats.complete = summary->complete;
  return stats;
}

}  // namespace behaviorlib::recorder
