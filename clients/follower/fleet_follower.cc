#include "behaviorlib/follower/fleet_follower.h"

#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>

#include <algorithm>
#include <utility>

#include "absl/time/time.h"
#include "behaviorlib/follower/event_cursor.h"

namespace behaviorlib::follower {

namespace {

constexpr std::chrono::milliseconds kFirstRetry{100};
constexpr std::chrono::milliseconds kMaxRetry{2000};

bool ended(v1::MissionState state) {
  return state == v1::MISSION_STATE_SUCCEEDED || state == v1::MISSION_STATE_FAILED ||
         state == v1::MISSION_STATE_ABORTED;
}

std::string deterministic(const google::protobuf::Message& message) {
  std::string bytes;
  google::protobuf::io::StringOutputStream stream(&bytes);
  google::protobuf::io::CodedOutputStream out(&stream);
  out.SetSerializationDeterministic(true);
  message.SerializeToCodedStream(&out);
  out.Trim();
  return bytes;
}

}  // namespace

FleetFollower::FleetFollower(std::shared_ptr<grpc::Channel> coordinator, FollowerOptions options,
                             FleetSink* sink)
    : stub_(v1::Coordinator::NewStub(coordinator)), options_(std::move(options)), sink_(sink) {
  if (options_.data_channel) data_ = v1::DataChannel::NewStub(options_.data_channel);
}

FleetFollower::~FleetFollower() { shutdown(); }

void FleetFollower::start() {
  {
    absl::MutexLock lock(&mutex_);
    if (started_ || stopping_) return;
    started_ = true;
  }
  events_thread_ = std::thread([this] { followEvents(); });
  missions_thread_ = std::thread([this] { followMissions(); });
  beliefs_thread_ = std::thread([this] { followBeliefs(); });
}

void FleetFollower::shutdown() {
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    stopping_ = true;
    for (auto& [name, context] : streams_) context->TryCancel();
  }
  if (events_thread_.joinable()) events_thread_.join();
  if (missions_thread_.joinable()) missions_thread_.join();
  if (beliefs_thread_.joinable()) beliefs_thread_.join();
  std::map<std::string, std::thread> watchers;
  std::vector<std::thread> topics;
  {
    absl::MutexLock lock(&mutex_);
    watchers.swap(mission_watchers_);
    topics.swap(topic_threads_);
  }
  for (auto& [id, thread] : watchers) {
    if (thread.joinable()) thread.join();
  }
  for (auto& thread : topics) thread.join();
}

bool FleetFollower::sleepFor(std::chrono::milliseconds wait, bool kickable) {
  absl::MutexLock lock(&mutex_);
  auto woken = [this, kickable]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || (kickable && kicked_);
  };
  mutex_.AwaitWithTimeout(absl::Condition(&woken), absl::FromChrono(wait));
  if (kickable) kicked_ = false;
  return !stopping_;
}

void FleetFollower::kick() {
  absl::MutexLock lock(&mutex_);
  kicked_ = true;
}

void FleetFollower::setCoordinatorUp(bool up, const std::string& why) {
  {
    absl::MutexLock lock(&mutex_);
    if (coordinator_known_ && coordinator_up_ == up) return;
    coordinator_known_ = true;
    coordinator_up_ = up;
  }
  sink_->onCoordinator(up, why);
}

template <typename Response, typename Open, typename Handle, typename Ended>
void FleetFollower::followStream(const std::string& key, Open open, Handle handle, Ended ended) {
  auto retry = kFirstRetry;
  while (true) {
    grpc::ClientContext context;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      streams_[key] = &context;
    }
    auto reader = open(&context);
    Response response;
    while (reader->Read(&response)) {
      retry = kFirstRetry;
      handle(response);
    }
    const grpc::Status status = reader->Finish();
    {
      absl::MutexLock lock(&mutex_);
      streams_.erase(key);
    }
    ended(status);
    if (!sleepFor(retry, false)) return;
    retry = std::min(retry * 2, kMaxRetry);
  }
}

void FleetFollower::followEvents() {
  EventCursor cursor;
  followStream<v1::WatchFleetEventsResponse>(
      "events",
      [&](grpc::ClientContext* context) { return stub_->WatchEvents(context, cursor.request()); },
      [&](const v1::WatchFleetEventsResponse& response) {
        setCoordinatorUp(true, "");
        for (const auto& event : cursor.accept(response)) sink_->onEvent(event);
        absl::MutexLock lock(&mutex_);
        events_seq_ = cursor.sinceSeq();
        events_incarnation_ = cursor.incarnation();
      },
      [&](const grpc::Status& status) { setCoordinatorUp(false, status.error_message()); });
}

bool FleetFollower::catchUp(std::chrono::milliseconds timeout) {
  if (timeout <= std::chrono::milliseconds::zero()) return false;
  const auto deadline = std::chrono::system_clock::now() + timeout;
  // Where the coordinator's log ends now: the start message of a stream
  // that resumes where ours is (the replay that would follow is not read).
  v1::WatchFleetEventsRequest probe;
  {
    absl::MutexLock lock(&mutex_);
    probe.set_since_seq(events_seq_);
    probe.set_incarnation(events_incarnation_);
  }
  v1::WatchFleetEventsResponse first;
  {
    grpc::ClientContext context;
    context.set_deadline(deadline);
    auto reader = stub_->WatchEvents(&context, probe);
    const bool read = reader->Read(&first);
    context.TryCancel();
    reader->Finish().IgnoreError();
    if (!read || !first.has_start()) return false;
  }
  grpc::ClientContext context;
  context.set_deadline(deadline);
  v1::ListMissionsRequest request;
  request.set_page_size(100);
  v1::ListMissionsResponse response;
  if (!stub_->ListMissions(&context, request, &response).ok()) return false;
  for (const auto& status : response.missions()) changedMission(status);
  const std::string incarnation = first.start().incarnation();
  const uint64_t latest = first.start().latest_seq();
  absl::MutexLock lock(&mutex_);
  const auto caught_up = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || (events_incarnation_ == incarnation && events_seq_ >= latest);
  };
  return mutex_.AwaitWithDeadline(absl::Condition(&caught_up), absl::FromChrono(deadline)) &&
         !stopping_;
}

void FleetFollower::changedMission(const v1::MissionStatus& status) {
  std::string bytes = deterministic(status);
  {
    absl::MutexLock lock(&mutex_);
    std::string& last = missions_[status.mission_id()];
    if (last == bytes) return;
    last = std::move(bytes);
  }
  sink_->onMission(status);
}

void FleetFollower::watchMission(const std::string& mission_id) {
  grpc::ClientContext context;
  const std::string key = "mission/" + mission_id;
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    streams_[key] = &context;
  }
  v1::WatchMissionRequest request;
  request.set_mission_id(mission_id);
  auto reader = stub_->WatchMission(&context, request);
  v1::WatchMissionResponse response;
  while (reader->Read(&response)) changedMission(response.status());
  reader->Finish();
  absl::MutexLock lock(&mutex_);
  streams_.erase(key);
  finished_watchers_.push_back(mission_id);
}

void FleetFollower::followMissions() {
  while (true) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
    v1::ListMissionsRequest request;
    request.set_page_size(100);
    v1::ListMissionsResponse response;
    std::vector<std::thread> done;
    if (stub_->ListMissions(&context, request, &response).ok()) {
      std::set<std::string> listed;
      for (const auto& status : response.missions()) {
        listed.insert(status.mission_id());
        changedMission(status);
        absl::MutexLock lock(&mutex_);
        if (!stopping_ && !ended(status.state()) &&
            mission_watchers_.count(status.mission_id()) == 0 &&
            mission_watchers_.size() < options_.max_watched_missions) {
          const std::string id = status.mission_id();
          mission_watchers_.emplace(id, std::thread([this, id] { watchMission(id); }));
        }
      }
      absl::MutexLock lock(&mutex_);
      // Missions the coordinator forgot are forgotten here too.
      for (auto it = missions_.begin(); it != missions_.end();) {
        it = listed.count(it->first) ? std::next(it) : missions_.erase(it);
      }
    }
    {
      absl::MutexLock lock(&mutex_);
      for (const auto& id : finished_watchers_) {
        auto it = mission_watchers_.find(id);
        if (it == mission_watchers_.end()) continue;
        done.push_back(std::move(it->second));
        mission_watchers_.erase(it);
      }
      finished_watchers_.clear();
    }
    for (auto& thread : done) thread.join();
    if (data_) followRobots();
    if (!sleepFor(options_.mission_poll, true)) return;
  }
}

// Every belief write, resumed after the last version seen; a coordinator
// without belief memory is asked again later.
void FleetFollower::followBeliefs() {
  uint64_t since_version = 0;
  followStream<v1::WatchBeliefsResponse>(
      "beliefs",
      [&](grpc::ClientContext* context) {
        v1::WatchBeliefsRequest request;
        request.set_since_version(since_version);
        return stub_->WatchBeliefs(context, request);
      },
      [&](const v1::WatchBeliefsResponse& response) {
        if (response.belief().version() <= since_version) return;
        since_version = response.belief().version();
        sink_->onBelief(response.belief());
      },
      [](const grpc::Status&) {});
}

// Starts following the vehicle topics of robots that registered since.
void FleetFollower::followRobots() {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::ListSystemsRequest request;
  request.set_page_size(100);
  v1::ListSystemsResponse response;
  if (!stub_->ListSystems(&context, request, &response).ok()) return;
  absl::MutexLock lock(&mutex_);
  for (const auto& system : response.systems()) {
    const std::string& robot = system.robot_id();
    if (stopping_ || robot.empty() || robots_.count(robot) > 0 ||
        robots_.size() >= options_.max_robots) {
      continue;
    }
    robots_.insert(robot);
    for (const auto& topic : options_.vehicle_topics) {
      const std::string name = "robots/" + robot + "/" + topic.name;
      const double rate = topic.max_rate_hz;
      topic_threads_.emplace_back([this, name, rate] { followTopic(name, rate); });
    }
  }
}

// One vehicle topic until shutdown; reconnects when the channel goes away.
// The latest sample a new subscription is sent first is not handed on
// again when it was already.
void FleetFollower::followTopic(const std::string& topic, double max_rate_hz) {
  const bool every = options_.vehicle_period.count() == 0 && max_rate_hz <= 0;
  auto last = std::chrono::steady_clock::time_point();
  uint64_t last_seq = 0;
  followStream<v1::SubscribeResponse>(
      "topic/" + topic,
      [&](grpc::ClientContext* context) {
        v1::SubscribeRequest request;
        request.set_topic(topic);
        request.set_mode(every ? v1::DELIVERY_MODE_QUEUE : v1::DELIVERY_MODE_LATEST);
        if (every) request.set_queue_size(options_.sample_queue);
        request.set_max_rate_hz(max_rate_hz);
        request.set_send_latest_first(true);
        return data_->Subscribe(context, request);
      },
      [&](const v1::SubscribeResponse& sample) {
        if (sample.topic_seq() != 0 && sample.topic_seq() == last_seq) return;
        last_seq = sample.topic_seq();
        // The broker keeps a rate itself, and always sends the last sample,
        // which a filter here could drop.
        if (max_rate_hz <= 0 && options_.vehicle_period.count() > 0) {
          const auto now = std::chrono::steady_clock::now();
          if (now - last < options_.vehicle_period) return;
          last = now;
        }
        sink_->onSample(sample);
      },
      [](const grpc::Status&) {});
}

}  // namespace behaviorlib::follower
