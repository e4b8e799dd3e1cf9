// The lifecycle contract of a behavior system, tested on a real process: by
// default the basic_quadrotor_behaviors binary (hosting WAIT) and, for
// simulated time, the real channel_broker, both started on free loopback
// ports and driven over gRPC exactly as the coordinator, scripts or grpcurl
// would. No mocks.
//
// The same suite runs against the contract's systems (decision 47), which
// host WAIT and CONTRACT_PROBE: contract_behaviors in C++ and its twin in
// Python, named by the environment:
//   BEHAVIORLIB_SYSTEM_UNDER_TEST  the command, split at spaces (the program,
//                                  then its leading arguments: a script);
//   BEHAVIORLIB_SYSTEM_NAME        the name the system registers under.
// The LifecycleContractTest cases need CONTRACT_PROBE; they are filtered out
// of the run against basic_quadrotor_behaviors.

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <fstream>
#include <functional>
#include <future>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_split.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.grpc.pb.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "coordinator_test_support.h"
#include "support/deterministic.h"
#include "support/paging.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using std::chrono::milliseconds;
using std::chrono::seconds;
using Clock = std::chrono::steady_clock;

constexpr char kBrokerBinary[] = BEHAVIORLIB_CHANNEL_BROKER_PATH;
constexpr char kCoordinatorBinary[] = BEHAVIORLIB_COORDINATOR_PATH;
constexpr char kSimulatorBinary[] = BEHAVIORLIB_SIMULATOR_PATH;
constexpr char kContractSystemBinary[] = BEHAVIORLIB_CONTRACT_SYSTEM_PATH;
constexpr char kRobot[] = "it-drone-7";

// The system under test: its command (program, then leading arguments) and
// the name it registers under.
struct SystemUnderTest {
  std::vector<std::string> command;
  std::string name;
};

const SystemUnderTest& systemUnderTest() {
  static const SystemUnderTest sut = [] {
    SystemUnderTest s{{BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH}, "basic_quadrotor_behaviors"};
    if (const char* command = std::getenv("BEHAVIORLIB_SYSTEM_UNDER_TEST");
        command != nullptr && *command != '\0') {
      s.command = absl::StrSplit(command, ' ', absl::SkipEmpty());
    }
    if (const char* name = std::getenv("BEHAVIORLIB_SYSTEM_NAME");
        name != nullptr && *name != '\0') {
      s.name = name;
    }
    return s;
  }();
  return sut;
}

const std::string& systemName() { return systemUnderTest().name; }

// A process of the system under test with `args` after the test's flags.
std::unique_ptr<support::ServerProcess> systemProcess(std::vector<std::string> args) {
  const auto& command = systemUnderTest().command;
  return std::make_unique<support::ServerProcess>(
      command.front(), std::vector<std::string>(command.begin() + 1, command.end()),
      std::move(args));
}

// Every RPC and every wait in this file is bounded.
constexpr milliseconds kCallTimeout = seconds(5);
constexpr milliseconds kEventTimeout = seconds(5);

double toSeconds(const google::protobuf::Duration& d) {
  return static_cast<double>(d.seconds()) + static_cast<double>(d.nanos()) * 1e-9;
}

double toSeconds(const google::protobuf::Timestamp& t) {
  return static_cast<double>(t.seconds()) + static_cast<double>(t.nanos()) * 1e-9;
}

double elapsedSeconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

google::protobuf::Struct structFromJson(const std::string& json) {
  google::protobuf::Struct s;
  auto status = google::protobuf::util::JsonStringToMessage(json, &s);
  EXPECT_TRUE(status.ok()) << json << ": " << status.ToString();
  return s;
}

std::string describe(const grpc::Status& s) {
  return std::to_string(static_cast<int>(s.error_code())) + " " + s.error_message();
}

template <class Response>
struct Reply {
  grpc::Status status;
  Response response;
};

// Calls a unary method of a generated stub with a deadline.
template <class Stub, class Request, class Response>
Reply<Response> unary(Stub& stub,
                      grpc::Status (Stub::*method)(grpc::ClientContext*, const Request&, Response*),
                      const Request& request) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
  Reply<Response> reply;
  reply.status = (stub.*method)(&context, request, &reply.response);
  return reply;
}

// Typed (behaviorlib.v1.Wait) and generic (behaviorlib.v1.BehaviorSystem)
// clients of one behavior-system process.
class SystemClient {
 public:
  explicit SystemClient(const std::string& address)
      : channel_(grpc::CreateChannel(address, grpc::InsecureChannelCredentials())),
        wait_(v1::Wait::NewStub(channel_)),
        system_(v1::BehaviorSystem::NewStub(channel_)) {}

  std::shared_ptr<grpc::Channel> channel() const { return channel_; }

  Reply<v1::ActivateResponse> activate(std::optional<double> duration_s,
                                       const std::string& request_id = "") {
    v1::WaitActivateRequest request;
    request.set_request_id(request_id);
    if (duration_s) request.mutable_parameters()->set_duration_s(*duration_s);
    return unary(*wait_, &v1::Wait::Stub::Activate, request);
  }
  Reply<v1::DeactivateResponse> deactivate(const std::string& activation_id = "") {
    v1::DeactivateRequest request;
    request.set_activation_id(activation_id);
    return unary(*wait_, &v1::Wait::Stub::Deactivate, request);
  }
  Reply<v1::CheckActivationResponse> checkActivation() {
    return unary(*wait_, &v1::Wait::Stub::CheckActivation, v1::CheckActivationRequest());
  }
  Reply<v1::PauseResponse> pause(const std::string& activation_id = "") {
    v1::PauseRequest request;
    request.set_activation_id(activation_id);
    return unary(*wait_, &v1::Wait::Stub::Pause, request);
  }
  Reply<v1::ResumeResponse> resume(const std::string& activation_id = "") {
    v1::ResumeRequest request;
    request.set_activation_id(activation_id);
    return unary(*wait_, &v1::Wait::Stub::Resume, request);
  }
  Reply<v1::ModifyResponse> modify(const std::string& activation_id, double duration_s) {
    v1::WaitModifyRequest request;
    request.set_activation_id(activation_id);
    request.mutable_parameters()->set_duration_s(duration_s);
    return unary(*wait_, &v1::Wait::Stub::Modify, request);
  }
  Reply<v1::ActivateResponse> activateBehavior(const std::string& behavior,
                                               const std::string& parameters_json) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    *request.mutable_parameters() = structFromJson(parameters_json);
    return unary(*system_, &v1::BehaviorSystem::Stub::ActivateBehavior, request);
  }
  Reply<v1::ListBehaviorsResponse> listBehaviors() {
    return unary(*system_, &v1::BehaviorSystem::Stub::ListBehaviors, v1::ListBehaviorsRequest());
  }

 private:
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Wait::Stub> wait_;
  std::unique_ptr<v1::BehaviorSystem::Stub> system_;
};

// A BehaviorSystem.WatchEvents subscriber: a reader thread queues every
// message; the test pops them with bounded waits.
class EventWatcher {
 public:
  EventWatcher(const std::string& address, const v1::WatchEventsRequest& request)
      : channel_(grpc::CreateChannel(address, grpc::InsecureChannelCredentials())),
        stub_(v1::BehaviorSystem::NewStub(channel_)) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(90));
    reader_ = stub_->WatchEvents(&context_, request);
    thread_ = std::thread([this] { run(); });
  }
  EventWatcher(const std::string& address, uint64_t since_seq = 0,
               const std::string& incarnation = "")
      : EventWatcher(address, makeRequest(since_seq, incarnation)) {}
  ~EventWatcher() { disconnect(); }
  EventWatcher(const EventWatcher&) = delete;
  EventWatcher& operator=(const EventWatcher&) = delete;

  // Cancels the stream (the client goes away) and joins the reader.
  void disconnect() {
    context_.TryCancel();
    if (thread_.joinable()) thread_.join();
  }

  // The next message, or nullopt when none arrives in time or the stream ended.
  std::optional<v1::WatchEventsResponse> next(milliseconds timeout = kEventTimeout) {
    std::unique_lock lock(mutex_);
    cv_.wait_for(lock, timeout, [this] { return !queue_.empty() || ended_; });
    if (queue_.empty()) return std::nullopt;
    auto message = std::move(queue_.front());
    queue_.pop_front();
    return message;
  }

  // The first message, which must be `start`.
  std::optional<v1::WatchEventsStart> start(milliseconds timeout = kEventTimeout) {
    auto message = next(timeout);
    if (!message) {
      ADD_FAILURE() << "no WatchEventsStart received";
      return std::nullopt;
    }
    if (!message->has_start()) {
      ADD_FAILURE() << "first message is not start: " << message->ShortDebugString();
      return std::nullopt;
    }
    return message->start();
  }

  // The next event (a `start` here is a failure).
  std::optional<v1::BehaviorEvent> nextEvent(milliseconds timeout = kEventTimeout) {
    auto message = next(timeout);
    if (!message) return std::nullopt;
    if (!message->has_event()) {
      ADD_FAILURE() << "expected an event, got " << message->ShortDebugString();
      return std::nullopt;
    }
    return message->event();
  }

  // Pops events until one matches `predicate` (the skipped ones are appended
  // to `skipped` if given); nullopt if none matches in time.
  std::optional<v1::BehaviorEvent> waitFor(
      const std::function<bool(const v1::BehaviorEvent&)>& predicate,
      milliseconds timeout = kEventTimeout, std::vector<v1::BehaviorEvent>* skipped = nullptr) {
    const auto deadline = Clock::now() + timeout;
    while (Clock::now() < deadline) {
      auto event = nextEvent(std::chrono::duration_cast<milliseconds>(deadline - Clock::now()));
      if (!event) return std::nullopt;
      if (predicate(*event)) return event;
      if (skipped) skipped->push_back(*event);
    }
    return std::nullopt;
  }

  std::optional<v1::BehaviorEvent> waitFinished(const std::string& activation_id,
                                                milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::BehaviorEvent& e) {
          return e.has_finished() && e.activation_id() == activation_id;
        },
        timeout);
  }

  // The status the stream ended with, or nullopt if it is still open.
  std::optional<grpc::Status> waitEnded(milliseconds timeout) {
    std::unique_lock lock(mutex_);
    cv_.wait_for(lock, timeout, [this] { return ended_; });
    if (!ended_) return std::nullopt;
    return status_;
  }

 private:
  static v1::WatchEventsRequest makeRequest(uint64_t since_seq, const std::string& incarnation) {
    v1::WatchEventsRequest request;
    request.set_since_seq(since_seq);
    request.set_incarnation(incarnation);
    return request;
  }

  void run() {
    v1::WatchEventsResponse message;
    while (reader_->Read(&message)) {
      std::lock_guard lock(mutex_);
      queue_.push_back(message);
      cv_.notify_all();
    }
    grpc::Status status = reader_->Finish();
    std::lock_guard lock(mutex_);
    status_ = status;
    ended_ = true;
    cv_.notify_all();
  }

  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::BehaviorSystem::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchEventsResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<v1::WatchEventsResponse> queue_;
  bool ended_ = false;
  grpc::Status status_;
};

// A process of basic_quadrotor_behaviors serving robot kRobot on free ports.
class BehaviorSystemTest : public ::testing::Test {
 protected:
  void SetUp() override {
    system_ = systemProcess({"--robot-id", kRobot});
    ASSERT_TRUE(system_->start()) << system_->error();
    client_ = std::make_unique<SystemClient>(system_->address());
  }

  void TearDown() override {
    client_.reset();
    if (system_ && system_->running()) {
      EXPECT_EQ(system_->terminate(), 0);
    }
  }

  std::unique_ptr<support::ServerProcess> system_;
  std::unique_ptr<SystemClient> client_;
};

// ---------------------------------------------------------------------------

TEST_F(BehaviorSystemTest, TypedWaitActivatesReportsAndFinishesWithGoalAchieved) {
  EventWatcher watcher(system_->address());
  auto start = watcher.start();
  ASSERT_TRUE(start);
  EXPECT_FALSE(start->incarnation().empty());
  EXPECT_FALSE(start->incarnation_changed());

  auto activated = client_->activate(0.2);
  ASSERT_TRUE(activated.status.ok()) << describe(activated.status);
  const std::string id = activated.response.activation_id();
  ASSERT_FALSE(id.empty());
  EXPECT_FALSE(activated.response.replayed());
  EXPECT_DOUBLE_EQ(activated.response.parameters().fields().at("duration_s").number_value(), 0.2);

  auto check = client_->checkActivation();
  ASSERT_TRUE(check.status.ok()) << describe(check.status);
  EXPECT_TRUE(check.response.active());
  EXPECT_EQ(check.response.state(), v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_EQ(check.response.activation_id(), id);
  ASSERT_TRUE(check.response.parameters().fields().contains("duration_s"));
  EXPECT_DOUBLE_EQ(check.response.parameters().fields().at("duration_s").number_value(), 0.2);

  auto first = watcher.nextEvent();
  ASSERT_TRUE(first) << "no activated event";
  auto second = watcher.nextEvent(seconds(3));
  ASSERT_TRUE(second) << "no finished event";

  ASSERT_TRUE(first->has_activated()) << first->ShortDebugString();
  EXPECT_EQ(first->activation_id(), id);
  EXPECT_DOUBLE_EQ(first->activated().parameters().fields().at("duration_s").number_value(), 0.2);
  ASSERT_TRUE(second->has_finished()) << second->ShortDebugString();
  EXPECT_EQ(second->activation_id(), id);
  EXPECT_EQ(second->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << second->ShortDebugString();
  EXPECT_GE(toSeconds(second->finished().active_duration()), 0.2);
  EXPECT_LT(toSeconds(second->finished().active_duration()), 1.0);

  EXPECT_GT(first->seq(), 0u);
  EXPECT_EQ(second->seq(), first->seq() + 1);
  for (const auto* event : {&*first, &*second}) {
    EXPECT_EQ(event->robot_id(), kRobot);
    EXPECT_EQ(event->system(), systemName());
    EXPECT_EQ(event->behavior(), "WAIT");
    EXPECT_EQ(event->incarnation(), start->incarnation());
    EXPECT_TRUE(event->has_time());
    EXPECT_TRUE(event->has_wall_time());
  }

  check = client_->checkActivation();
  ASSERT_TRUE(check.status.ok()) << describe(check.status);
  EXPECT_FALSE(check.response.active());
  EXPECT_EQ(check.response.state(), v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_TRUE(check.response.activation_id().empty());
}

TEST_F(BehaviorSystemTest, RefusesBadRequestsWithPreciseCodesAndKeepsServing) {
  // Missing required parameter.
  auto r = client_->activate(std::nullopt);
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("duration_s"), std::string::npos)
      << r.status.error_message();

  // Out of range.
  r = client_->activate(-1);
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("duration_s"), std::string::npos)
      << r.status.error_message();

  // Neither refusal activated anything.
  auto check = client_->checkActivation();
  ASSERT_TRUE(check.status.ok());
  EXPECT_FALSE(check.response.active());

  // Already active.
  auto first = client_->activate(30);
  ASSERT_TRUE(first.status.ok()) << describe(first.status);
  r = client_->activate(30);
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(r.status);
  check = client_->checkActivation();
  EXPECT_EQ(check.response.activation_id(), first.response.activation_id());

  // Deactivate, then Deactivate again while inactive.
  auto d = client_->deactivate();
  ASSERT_TRUE(d.status.ok()) << describe(d.status);
  EXPECT_EQ(d.response.activation_id(), first.response.activation_id());
  EXPECT_EQ(d.response.cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  d = client_->deactivate();
  EXPECT_EQ(d.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(d.status);

  // Calls naming a stale activation while a newer one runs are ABORTED and
  // leave the newer one untouched.
  auto newer = client_->activate(30);
  ASSERT_TRUE(newer.status.ok()) << describe(newer.status);
  const std::string stale = first.response.activation_id();
  ASSERT_NE(stale, newer.response.activation_id());
  d = client_->deactivate(stale);
  EXPECT_EQ(d.status.error_code(), grpc::StatusCode::ABORTED) << describe(d.status);
  auto p = client_->pause(stale);
  EXPECT_EQ(p.status.error_code(), grpc::StatusCode::ABORTED) << describe(p.status);
  auto m = client_->modify(stale, 1);
  EXPECT_EQ(m.status.error_code(), grpc::StatusCode::ABORTED) << describe(m.status);
  check = client_->checkActivation();
  ASSERT_TRUE(check.status.ok());
  EXPECT_TRUE(check.response.active());
  EXPECT_EQ(check.response.state(), v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_EQ(check.response.activation_id(), newer.response.activation_id());
  EXPECT_DOUBLE_EQ(check.response.parameters().fields().at("duration_s").number_value(), 30);
  d = client_->deactivate(newer.response.activation_id());
  ASSERT_TRUE(d.status.ok()) << describe(d.status);

  // Generic calls: unknown behavior, wrong type, unknown field.
  r = client_->activateBehavior("FLY", R"({"duration_s": 1})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("FLY"), std::string::npos) << r.status.error_message();
  EXPECT_NE(r.status.error_message().find("WAIT"), std::string::npos) << r.status.error_message();

  r = client_->activateBehavior("WAIT", R"({"duration_s": "five"})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("duration_s"), std::string::npos)
      << r.status.error_message();

  r = client_->activateBehavior("WAIT", R"({"durationn_s": 1})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("durationn_s"), std::string::npos)
      << r.status.error_message();

  // Still serving: a valid generic activation works and finishes.
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());
  r = client_->activateBehavior("WAIT", R"({"duration_s": 0.05})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  auto finished = watcher.waitFinished(r.response.activation_id());
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_TRUE(system_->running());
}

TEST_F(BehaviorSystemTest, ActivateWithSameRequestIdIsIdempotent) {
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());

  auto a = client_->activate(0.3, "req-42");
  ASSERT_TRUE(a.status.ok()) << describe(a.status);
  EXPECT_FALSE(a.response.replayed());
  auto b = client_->activate(0.3, "req-42");
  ASSERT_TRUE(b.status.ok()) << describe(b.status);
  EXPECT_TRUE(b.response.replayed());
  EXPECT_EQ(b.response.activation_id(), a.response.activation_id());

  // Exactly one activation happened: activated then finished, nothing else.
  auto activated = watcher.nextEvent();
  ASSERT_TRUE(activated);
  EXPECT_TRUE(activated->has_activated());
  EXPECT_EQ(activated->activation_id(), a.response.activation_id());
  auto finished = watcher.nextEvent(seconds(3));
  ASSERT_TRUE(finished);
  EXPECT_TRUE(finished->has_finished()) << finished->ShortDebugString();
  EXPECT_EQ(finished->activation_id(), a.response.activation_id());

  // A late retry after the activation finished still replays, starting nothing.
  auto c = client_->activate(0.3, "req-42");
  ASSERT_TRUE(c.status.ok()) << describe(c.status);
  EXPECT_TRUE(c.response.replayed());
  EXPECT_EQ(c.response.activation_id(), a.response.activation_id());
  EXPECT_FALSE(client_->checkActivation().response.active());
  EXPECT_FALSE(watcher.nextEvent(milliseconds(300))) << "a replay must not emit events";

  // A different request_id starts a new activation.
  auto d = client_->activate(0.05, "req-43");
  ASSERT_TRUE(d.status.ok()) << describe(d.status);
  EXPECT_FALSE(d.response.replayed());
  EXPECT_NE(d.response.activation_id(), a.response.activation_id());
}

TEST_F(BehaviorSystemTest, PauseResumeModifyExcludePausedTimeFromActiveDuration) {
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());

  const auto t0 = Clock::now();
  auto a = client_->activate(0.4);
  ASSERT_TRUE(a.status.ok()) << describe(a.status);
  const std::string id = a.response.activation_id();
  auto p = client_->pause(id);
  ASSERT_TRUE(p.status.ok()) << describe(p.status);
  EXPECT_EQ(p.response.activation_id(), id);

  std::this_thread::sleep_for(milliseconds(300));
  auto check = client_->checkActivation();
  ASSERT_TRUE(check.status.ok());
  EXPECT_TRUE(check.response.active());
  EXPECT_EQ(check.response.state(), v1::BEHAVIOR_STATE_PAUSED);
  // Paused right after activation: hardly any active time accumulated.
  EXPECT_LT(toSeconds(check.response.active_duration()), 0.2);

  auto again = client_->pause(id);
  EXPECT_EQ(again.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(again.status);

  auto r = client_->resume(id);
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  auto m = client_->modify(id, 0.6);
  ASSERT_TRUE(m.status.ok()) << describe(m.status);
  EXPECT_DOUBLE_EQ(m.response.parameters().fields().at("duration_s").number_value(), 0.6);

  std::vector<v1::BehaviorEvent> events;
  for (int i = 0; i < 5; ++i) {
    auto e = watcher.nextEvent(seconds(3));
    ASSERT_TRUE(e) << "event " << i << " missing";
    events.push_back(*e);
  }
  const double wall = elapsedSeconds(t0);
  for (size_t i = 0; i < events.size(); ++i) {
    EXPECT_EQ(events[i].activation_id(), id);
    if (i > 0) {
      EXPECT_EQ(events[i].seq(), events[i - 1].seq() + 1);
    }
  }
  ASSERT_TRUE(events[0].has_activated()) << events[0].ShortDebugString();
  ASSERT_TRUE(events[1].has_paused()) << events[1].ShortDebugString();
  ASSERT_TRUE(events[2].has_resumed()) << events[2].ShortDebugString();
  ASSERT_TRUE(events[3].has_modified()) << events[3].ShortDebugString();
  EXPECT_DOUBLE_EQ(events[3].modified().parameters().fields().at("duration_s").number_value(), 0.6);
  ASSERT_TRUE(events[4].has_finished()) << events[4].ShortDebugString();
  const auto& finished = events[4].finished();
  EXPECT_EQ(finished.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_DOUBLE_EQ(finished.parameters().fields().at("duration_s").number_value(), 0.6);

  // The modified duration was waited, in active time only.
  const double active = toSeconds(finished.active_duration());
  EXPECT_GE(active, 0.6);
  EXPECT_LT(active, 0.6 + 0.25);
  // Paused for >= 300 ms on the behavior's (steady) clock...
  const double paused = toSeconds(events[2].time()) - toSeconds(events[1].time());
  EXPECT_GE(paused, 0.29);
  // ...which the active duration excludes.
  const double total = toSeconds(events[4].time()) - toSeconds(events[0].time());
  EXPECT_NEAR(active, total - paused, 0.05);
  EXPECT_GE(total, 0.6 + 0.29);
  EXPECT_GE(wall, 0.6 + 0.29);
  EXPECT_FALSE(client_->checkActivation().response.active());
}

TEST_F(BehaviorSystemTest, ListBehaviorsDescribesWaitFromItsProto) {
  auto list = client_->listBehaviors();
  ASSERT_TRUE(list.status.ok()) << describe(list.status);
  const auto& r = list.response;
  EXPECT_EQ(r.robot_id(), kRobot);
  EXPECT_EQ(r.system(), systemName());
  EXPECT_FALSE(r.incarnation().empty());
  {
    EventWatcher watcher(system_->address());
    auto start = watcher.start();
    ASSERT_TRUE(start);
    EXPECT_EQ(start->incarnation(), r.incarnation());
  }

  // The system hosts other behaviors too; WAIT is found by name.
  auto find_wait = [](const v1::ListBehaviorsResponse& response) -> const v1::BehaviorDescription* {
    for (const auto& b : response.behaviors()) {
      if (b.name() == "WAIT") return &b;
    }
    return nullptr;
  };
  ASSERT_NE(find_wait(r), nullptr) << r.ShortDebugString();
  const auto& wait = *find_wait(r);
  EXPECT_EQ(wait.name(), "WAIT");
  EXPECT_EQ(wait.service(), "behaviorlib.v1.Wait");
  EXPECT_FALSE(wait.description().empty());
  EXPECT_EQ(wait.kind(), v1::BEHAVIOR_KIND_GOAL_BASED);
  EXPECT_EQ(wait.parameters_type(), "behaviorlib.v1.WaitParameters");
  EXPECT_EQ(wait.state(), v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_GT(wait.frequency_hz(), 0);

  ASSERT_EQ(wait.parameters_size(), 1) << wait.ShortDebugString();
  const auto& p = wait.parameters(0);
  EXPECT_EQ(p.name(), "duration_s");
  EXPECT_EQ(p.unit(), "s");
  EXPECT_EQ(p.type(), "number");
  EXPECT_EQ(p.proto_type(), "double");
  EXPECT_FALSE(p.repeated());
  EXPECT_TRUE(p.required());
  EXPECT_FALSE(p.description().empty());
  ASSERT_TRUE(p.has_range());
  ASSERT_TRUE(p.range().has_max());
  EXPECT_DOUBLE_EQ(p.range().max(), 86400);
  ASSERT_TRUE(p.range().has_min());
  EXPECT_DOUBLE_EQ(p.range().min(), 0);

  // The state reported follows the behavior.
  auto a = client_->activate(30);
  ASSERT_TRUE(a.status.ok()) << describe(a.status);
  list = client_->listBehaviors();
  ASSERT_TRUE(list.status.ok());
  ASSERT_NE(find_wait(list.response), nullptr);
  EXPECT_EQ(find_wait(list.response)->state(), v1::BEHAVIOR_STATE_ACTIVE);
}

TEST_F(BehaviorSystemTest, ListBehaviorsPagesThroughEveryBehaviorOnce) {
  auto stub = v1::BehaviorSystem::NewStub(
      grpc::CreateChannel(system_->address(), grpc::InsecureChannelCredentials()));
  const auto items = [](const v1::ListBehaviorsResponse& r) -> const auto& {
    return r.behaviors();
  };
  const auto name = [](const v1::BehaviorDescription& d) { return d.name(); };
  std::vector<std::vector<std::string>> whole;
  ASSERT_TRUE(support::pageKeys(*stub, &v1::BehaviorSystem::Stub::ListBehaviors,
                                v1::ListBehaviorsRequest(), items, name, &whole)
                  .ok());
  ASSERT_EQ(whole.size(), 1u);  // the default page holds them all
  ASSERT_GE(whole[0].size(), 2u);
  EXPECT_TRUE(std::is_sorted(whole[0].begin(), whole[0].end()));

  v1::ListBehaviorsRequest small;
  small.set_page_size(1);
  std::vector<std::vector<std::string>> pages;
  ASSERT_TRUE(
      support::pageKeys(*stub, &v1::BehaviorSystem::Stub::ListBehaviors, small, items, name, &pages)
          .ok());
  EXPECT_EQ(pages.size(), whole[0].size());
  std::vector<std::string> joined;
  for (const auto& page : pages) {
    EXPECT_EQ(page.size(), 1u);
    joined.insert(joined.end(), page.begin(), page.end());
  }
  EXPECT_EQ(joined, whole[0]);

  grpc::ClientContext context;
  v1::ListBehaviorsRequest bad;
  bad.set_page_token("not a token");
  v1::ListBehaviorsResponse response;
  EXPECT_EQ(stub->ListBehaviors(&context, bad, &response).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  grpc::ClientContext negative_context;
  bad.set_page_token("");
  bad.set_page_size(-1);
  EXPECT_EQ(stub->ListBehaviors(&negative_context, bad, &response).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
}

TEST_F(BehaviorSystemTest, SigtermInterruptsActiveBehaviorNotifiesSubscribersAndExitsZero) {
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());
  auto a = client_->activate(60);
  ASSERT_TRUE(a.status.ok()) << describe(a.status);
  auto activated = watcher.nextEvent();
  ASSERT_TRUE(activated);
  ASSERT_TRUE(activated->has_activated());

  EXPECT_EQ(system_->terminate(), 0);

  auto finished = watcher.nextEvent();
  ASSERT_TRUE(finished) << "no finished event before the stream ended";
  ASSERT_TRUE(finished->has_finished()) << finished->ShortDebugString();
  EXPECT_EQ(finished->activation_id(), a.response.activation_id());
  EXPECT_EQ(finished->seq(), activated->seq() + 1);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_NE(finished->finished().message().find("shutting down"), std::string::npos)
      << finished->finished().message();

  auto status = watcher.waitEnded(seconds(5));
  ASSERT_TRUE(status) << "the stream did not end";
  EXPECT_EQ(status->error_code(), grpc::StatusCode::UNAVAILABLE) << describe(*status);
  // Ended by the server's orderly shutdown (not a dropped connection), which
  // tells the client where to resume.
  EXPECT_NE(status->error_message().find("since_seq=" + std::to_string(finished->seq())),
            std::string::npos)
      << status->error_message();
  EXPECT_FALSE(watcher.next(milliseconds(0))) << "nothing after the finished event";
}

TEST_F(BehaviorSystemTest, WatchEventsResumesWithoutLossAndDetectsRestarts) {
  // The reference subscriber sees everything.
  EventWatcher all(system_->address());
  auto all_start = all.start();
  ASSERT_TRUE(all_start);
  const std::string incarnation = all_start->incarnation();

  auto runWait = [&](double duration_s) -> std::string {
    auto a = client_->activate(duration_s);
    EXPECT_TRUE(a.status.ok()) << describe(a.status);
    auto finished = all.waitFinished(a.response.activation_id());
    EXPECT_TRUE(finished) << "activation " << a.response.activation_id() << " did not finish";
    return a.response.activation_id();
  };

  // A reads the first activation's events, then disconnects.
  uint64_t last_seen = 0;
  {
    EventWatcher a(system_->address());
    auto start = a.start();
    ASSERT_TRUE(start);
    EXPECT_EQ(start->incarnation(), incarnation);
    const std::string id = runWait(0.05);
    auto finished = a.waitFinished(id);
    ASSERT_TRUE(finished);
    last_seen = finished->seq();
    a.disconnect();
  }
  ASSERT_GT(last_seen, 0u);

  // More happens while A is away.
  runWait(0.05);
  runWait(0.05);
  auto pending = client_->activate(30);
  ASSERT_TRUE(pending.status.ok()) << describe(pending.status);
  ASSERT_TRUE(client_->pause().status.ok());
  ASSERT_TRUE(all.waitFor([](const v1::BehaviorEvent& e) { return e.has_paused(); }));
  auto latest = client_->listBehaviors();  // a call that emits nothing
  ASSERT_TRUE(latest.status.ok());

  // What A missed, as the reference subscriber saw it.
  std::vector<v1::BehaviorEvent> missed;
  {
    EventWatcher reference(system_->address());
    ASSERT_TRUE(reference.start());
    while (auto e = reference.nextEvent(milliseconds(300))) {
      if (e->seq() > last_seen) missed.push_back(*e);
    }
  }
  ASSERT_EQ(missed.size(), 6u) << "2 finished WAITs + activated + paused";

  // A comes back and gets exactly the missed events, then live ones.
  {
    EventWatcher a(system_->address(), last_seen, incarnation);
    auto start = a.start();
    ASSERT_TRUE(start);
    EXPECT_EQ(start->incarnation(), incarnation);
    EXPECT_FALSE(start->incarnation_changed());
    EXPECT_FALSE(start->events_dropped());
    EXPECT_EQ(start->dropped_count(), 0u);
    EXPECT_EQ(start->latest_seq(), missed.back().seq());
    for (size_t i = 0; i < missed.size(); ++i) {
      auto e = a.nextEvent();
      ASSERT_TRUE(e) << "missed event " << i << " not replayed";
      EXPECT_EQ(e->seq(), last_seen + 1 + i);
      EXPECT_EQ(e->SerializeAsString(), missed[i].SerializeAsString())
          << e->ShortDebugString() << "\nvs\n"
          << missed[i].ShortDebugString();
    }
    EXPECT_FALSE(a.nextEvent(milliseconds(300))) << "duplicate or extra event";
    // Live events continue the sequence.
    ASSERT_TRUE(client_->resume().status.ok());
    auto live = a.nextEvent();
    ASSERT_TRUE(live);
    EXPECT_TRUE(live->has_resumed());
    EXPECT_EQ(live->seq(), missed.back().seq() + 1);
  }

  // A wrong incarnation: told so, and everything retained is replayed.
  {
    EventWatcher wrong(system_->address(), last_seen, "not-the-incarnation");
    auto start = wrong.start();
    ASSERT_TRUE(start);
    EXPECT_TRUE(start->incarnation_changed());
    EXPECT_EQ(start->incarnation(), incarnation);
    auto first = wrong.nextEvent();
    ASSERT_TRUE(first);
    EXPECT_EQ(first->seq(), start->oldest_retained_seq());
    EXPECT_LE(first->seq(), last_seen);
  }

  // After a restart the old incarnation is unknown: incarnation_changed.
  const uint64_t old_latest = missed.back().seq() + 1;
  all.disconnect();
  EXPECT_EQ(system_->terminate(), 0);
  system_ = systemProcess({"--robot-id", kRobot});
  ASSERT_TRUE(system_->start()) << system_->error();
  {
    EventWatcher after(system_->address(), old_latest, incarnation);
    auto start = after.start();
    ASSERT_TRUE(start);
    EXPECT_TRUE(start->incarnation_changed());
    EXPECT_FALSE(start->incarnation().empty());
    EXPECT_NE(start->incarnation(), incarnation);
    EXPECT_EQ(start->latest_seq(), 0u);
    EXPECT_FALSE(after.next(milliseconds(200))) << "a fresh process has no events";
  }
}

// grpc.health.v1.Health/Check through a generic stub: the request and reply
// are tiny, so they are encoded by hand (HealthCheckRequest{string service =
// 1}, HealthCheckResponse{ServingStatus status = 1}).
grpc::Status healthCheck(const std::shared_ptr<grpc::Channel>& channel, const std::string& service,
                         int* serving_status) {
  std::string request;
  if (!service.empty()) {
    request.push_back(0x0a);
    request.push_back(static_cast<char>(service.size()));  // < 128 here
    request += service;
  }
  grpc::Slice slice(request);
  grpc::ByteBuffer request_buffer(&slice, 1);
  grpc::ByteBuffer response_buffer;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
  grpc::GenericStub stub(channel);
  std::promise<grpc::Status> done;
  stub.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(), &request_buffer,
                 &response_buffer, [&done](grpc::Status s) { done.set_value(std::move(s)); });
  auto future = done.get_future();
  if (future.wait_for(kCallTimeout + seconds(2)) != std::future_status::ready) {
    context.TryCancel();
    future.wait();
    return grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED, "health check did not complete");
  }
  grpc::Status status = future.get();
  *serving_status = -1;
  if (!status.ok()) return status;
  std::vector<grpc::Slice> slices;
  if (!response_buffer.Dump(&slices).ok()) return grpc::Status(grpc::StatusCode::INTERNAL, "dump");
  std::string bytes;
  for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
  // Absent field = UNKNOWN (0); otherwise tag 0x08 then a one-byte varint.
  *serving_status = 0;
  if (bytes.size() == 2 && bytes[0] == 0x08) *serving_status = bytes[1];
  if (bytes.size() != 0 && bytes.size() != 2) *serving_status = -2;
  return status;
}

TEST_F(BehaviorSystemTest, HealthReportsServingForServerAndBehaviorServices) {
  constexpr int kServing = 1;
  for (const std::string service : {"", "behaviorlib.v1.Wait", "behaviorlib.v1.BehaviorSystem"}) {
    int serving = -1;
    auto status = healthCheck(client_->channel(), service, &serving);
    ASSERT_TRUE(status.ok()) << "'" << service << "': " << describe(status);
    EXPECT_EQ(serving, kServing) << "'" << service << "'";
  }
  int serving = -1;
  auto status = healthCheck(client_->channel(), "behaviorlib.v1.NoSuchService", &serving);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(status);
}

// The value of the first sample of `metric` whose label text contains every
// string in `labels`.
std::optional<double> metricValue(const std::string& text, const std::string& metric,
                                  const std::vector<std::string>& labels) {
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(metric + "{", 0) != 0) continue;
    const auto close = line.rfind('}');
    if (close == std::string::npos) continue;
    const std::string label_text = line.substr(metric.size(), close - metric.size() + 1);
    bool all = true;
    for (const auto& l : labels) all = all && label_text.find(l) != std::string::npos;
    if (all) return std::strtod(line.c_str() + close + 1, nullptr);
  }
  return std::nullopt;
}

TEST_F(BehaviorSystemTest, MetricsEndpointCountsActivationsTerminationsAndTimings) {
  ASSERT_GT(system_->metricsPort(), 0);
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());
  auto a = client_->activate(0.05);
  ASSERT_TRUE(a.status.ok()) << describe(a.status);
  auto finished = watcher.waitFinished(a.response.activation_id());
  ASSERT_TRUE(finished);
  ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);

  const std::vector<std::string> wait_labels = {"behavior=\"WAIT\"",
                                                std::string("robot=\"") + kRobot + "\"",
                                                std::string("system=\"") + systemName() + "\""};
  auto with = [&](const std::string& extra) {
    auto labels = wait_labels;
    labels.push_back(extra);
    return labels;
  };
  // The counters are updated right after the event is emitted: poll briefly.
  std::string body;
  const auto deadline = Clock::now() + seconds(3);
  while (true) {
    body = support::httpGet(system_->metricsPort(), "/metrics");
    auto t = metricValue(body, "behaviorlib_terminations_total", with("cause=\"GOAL_ACHIEVED\""));
    if ((t && *t >= 1) || Clock::now() > deadline) break;
    std::this_thread::sleep_for(milliseconds(20));
  }
  ASSERT_FALSE(body.empty()) << "GET /metrics failed";

  auto activations = metricValue(body, "behaviorlib_activations_total", wait_labels);
  ASSERT_TRUE(activations) << body;
  EXPECT_GE(*activations, 1);
  auto goal = metricValue(body, "behaviorlib_terminations_total", with("cause=\"GOAL_ACHIEVED\""));
  ASSERT_TRUE(goal) << body;
  EXPECT_GE(*goal, 1);
  auto interrupted =
      metricValue(body, "behaviorlib_terminations_total", with("cause=\"INTERRUPTED\""));
  ASSERT_TRUE(interrupted) << body;
  EXPECT_EQ(*interrupted, 0);
  auto activation_count = metricValue(body, "behaviorlib_activation_seconds_count", wait_labels);
  ASSERT_TRUE(activation_count) << body;
  EXPECT_GE(*activation_count, 1);
  auto monitoring_count = metricValue(body, "behaviorlib_monitoring_seconds_count", wait_labels);
  ASSERT_TRUE(monitoring_count) << body;
  EXPECT_GE(*monitoring_count, 1);
  auto cpu_count = metricValue(body, "behaviorlib_monitoring_cpu_seconds_count", wait_labels);
  ASSERT_TRUE(cpu_count) << body;
  EXPECT_EQ(*cpu_count, *monitoring_count) << "every tick on both clocks";
  auto active = metricValue(body, "behaviorlib_active_behaviors", wait_labels);
  ASSERT_TRUE(active) << body;
  EXPECT_EQ(*active, 0);
}

// Runs `argv` to completion (bounded); returns the raw wait status, or -1 if
// it had to be killed. Its stderr goes to `stderr_text`.
int runToExit(const std::vector<std::string>& args, milliseconds timeout,
              std::string* stderr_text) {
  char path[] = "/tmp/behaviorlib-stderr-XXXXXX";
  const int fd = mkstemp(path);
  if (fd < 0) return -1;
  std::vector<std::string> copy = args;
  std::vector<char*> argv;
  for (auto& a : copy) argv.push_back(a.data());
  argv.push_back(nullptr);
  const pid_t pid = fork();
  if (pid < 0) {
    close(fd);
    unlink(path);
    return -1;
  }
  if (pid == 0) {
    dup2(fd, STDERR_FILENO);
    execv(argv[0], argv.data());
    _exit(127);
  }
  close(fd);
  const auto deadline = Clock::now() + timeout;
  int status = 0;
  int result = -1;
  while (true) {
    const pid_t r = waitpid(pid, &status, WNOHANG);
    if (r == pid) {
      result = status;
      break;
    }
    if (r < 0) break;
    if (Clock::now() > deadline) {
      ::kill(pid, SIGKILL);
      waitpid(pid, &status, 0);
      break;
    }
    std::this_thread::sleep_for(milliseconds(10));
  }
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  *stderr_text = text.str();
  unlink(path);
  return result;
}

TEST_F(BehaviorSystemTest, SecondProcessOnAPortInUseExitsWithAnError) {
  std::string err;
  std::vector<std::string> command = systemUnderTest().command;
  command.insert(command.end(), {"--listen", system_->address(), "--metrics-listen", "127.0.0.1:0",
                                 "--robot-id", kRobot});
  const int status = runToExit(command, seconds(10), &err);
  ASSERT_NE(status, -1) << "the second process did not exit by itself";
  ASSERT_TRUE(WIFEXITED(status)) << "killed by signal " << WTERMSIG(status) << "\n" << err;
  EXPECT_NE(WEXITSTATUS(status), 0) << err;
  EXPECT_NE(err.find(system_->address()), std::string::npos) << err;

  // The first process is unaffected.
  auto list = client_->listBehaviors();
  EXPECT_TRUE(list.status.ok()) << describe(list.status);
  auto a = client_->activate(0.05);
  EXPECT_TRUE(a.status.ok()) << describe(a.status);
}

// ---------------------------------------------------------------------------
// The contract's termination causes, refusals and supervision, provoked
// through CONTRACT_PROBE (contract_behaviors, in C++ or in Python).

class LifecycleContractTest : public BehaviorSystemTest {
 protected:
  // Activates CONTRACT_PROBE with `json` and returns its finished event.
  std::optional<v1::BehaviorEvent> probe(const std::string& json,
                                         milliseconds timeout = kEventTimeout) {
    EventWatcher watcher(system_->address());
    if (!watcher.start()) return std::nullopt;
    auto r = client_->activateBehavior("CONTRACT_PROBE", json);
    EXPECT_TRUE(r.status.ok()) << json << ": " << describe(r.status);
    if (!r.status.ok()) return std::nullopt;
    return watcher.waitFinished(r.response.activation_id(), timeout);
  }
};

TEST_F(LifecycleContractTest, EachMonitoringFunctionEndsWithItsCauseAndMessage) {
  struct Case {
    const char* parameter;
    v1::TerminationCause cause;
    const char* message;
  };
  for (const Case& c : {
           Case{"fail_processes", v1::TERMINATION_CAUSE_PROCESS_FAILURE,
                "the probe's process failed"},
           Case{"change_situation", v1::TERMINATION_CAUSE_SITUATION_CHANGE,
                "the probe's situation changed"},
           Case{"achieve_goal", v1::TERMINATION_CAUSE_GOAL_ACHIEVED, "the probe's goal achieved"},
           Case{"wrong_progress", v1::TERMINATION_CAUSE_WRONG_PROGRESS,
                "the probe made no progress"},
       }) {
    const std::string json = std::string(R"({"after_s": 0.05, ")") + c.parameter + R"(": true})";
    auto finished = probe(json);
    ASSERT_TRUE(finished) << json << ": no finished event";
    EXPECT_EQ(finished->finished().cause(), c.cause) << finished->ShortDebugString();
    EXPECT_EQ(finished->finished().message(), c.message) << finished->ShortDebugString();
    EXPECT_GE(toSeconds(finished->finished().active_duration()), 0.05);
    EXPECT_TRUE(finished->finished().parameters().fields().at(c.parameter).bool_value());
  }
}

TEST_F(LifecycleContractTest, TheMonitoringOrderDecidesWhenSeveralFunctionsWouldEnd) {
  // checkProcesses, checkSituation, checkGoal, checkProgress: the first that
  // ends the activation wins, whatever the others say at the same tick.
  auto finished = probe(
      R"({"fail_processes": true, "change_situation": true, "achieve_goal": true,
          "wrong_progress": true})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  finished = probe(R"({"change_situation": true, "achieve_goal": true, "wrong_progress": true})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE);
  finished = probe(R"({"achieve_goal": true, "wrong_progress": true})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(LifecycleContractTest, TheMaximumActiveTimeEndsWithTimeOut) {
  auto finished = probe(R"({"time_out_s": 0.3})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT)
      << finished->ShortDebugString();
  EXPECT_EQ(finished->finished().message(), "the probe's time_out_s of active time passed");
  EXPECT_GE(toSeconds(finished->finished().active_duration()), 0.3);
}

TEST_F(LifecycleContractTest, AnExceptionIsProcessFailureNamingItAndTheSystemGoesOn) {
  auto finished = probe(R"({"throw_in_execute": true})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  const std::string& message = finished->finished().message();
  EXPECT_NE(message.find("threw"), std::string::npos) << message;
  EXPECT_NE(message.find("the probe throws"), std::string::npos) << message;
  EXPECT_TRUE(system_->running());
  finished = probe(R"({"achieve_goal": true})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(LifecycleContractTest, TheWatchdogEndsAStuckFunctionAndActivationsResumeAfterIt) {
  // onExecute blocks 2.5 s; the watchdog (1 s) ends the activation while it
  // does, and new activations are refused until the call returns.
  const auto t0 = Clock::now();
  auto finished = probe(R"({"block_s": 2.5})");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(finished->finished().message().find("watchdog"), std::string::npos)
      << finished->finished().message();
  EXPECT_GE(elapsedSeconds(t0), 1.0);
  Reply<v1::ActivateResponse> again;
  const auto deadline = Clock::now() + seconds(10);
  do {
    again = client_->activateBehavior("CONTRACT_PROBE", R"({"achieve_goal": true})");
    if (again.status.ok()) break;
    EXPECT_EQ(again.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
        << describe(again.status);
    std::this_thread::sleep_for(milliseconds(50));
  } while (Clock::now() < deadline);
  ASSERT_TRUE(again.status.ok()) << describe(again.status);
  EXPECT_GE(elapsedSeconds(t0), 2.5) << "accepted while the stuck call still ran";
  EXPECT_TRUE(system_->running());
}

TEST_F(LifecycleContractTest, ARefusalInOnActivateIsItsStatusAndNothingStarts) {
  EventWatcher watcher(system_->address());
  ASSERT_TRUE(watcher.start());
  auto r = client_->activateBehavior("CONTRACT_PROBE", R"({"refuse_activation": "not today"})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("not today"), std::string::npos)
      << r.status.error_message();
  EXPECT_FALSE(watcher.nextEvent(milliseconds(300))) << "a refused activation emits nothing";
  // Out of range and unknown: the parameter named.
  r = client_->activateBehavior("CONTRACT_PROBE", R"({"block_s": 11})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("block_s"), std::string::npos)
      << r.status.error_message();
  r = client_->activateBehavior("CONTRACT_PROBE", R"({"after_s": 0, "fail_processes": 1})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("fail_processes"), std::string::npos)
      << r.status.error_message();
}

// The words of a description: those of a C++ system come from the descriptor
// sets it embeds, the shipped protos' only; a behavior declared outside them
// (CONTRACT_PROBE, an out-of-tree system's) is described without them.
void clearDocumentation(v1::BehaviorDescription* description) {
  description->clear_description();
  for (auto& parameter : *description->mutable_parameters()) parameter.clear_description();
}

TEST_F(LifecycleContractTest, DescribesItsBehaviorsAsTheCppSystemDoes) {
  // The reference: the C++ contract system (the same process when it is the
  // one under test). Every description, byte for byte: WAIT's with its words,
  // CONTRACT_PROBE's without them.
  support::ServerProcess reference(kContractSystemBinary, {"--robot-id", kRobot});
  ASSERT_TRUE(reference.start()) << reference.error();
  auto ours = client_->listBehaviors();
  auto theirs = SystemClient(reference.address()).listBehaviors();
  ASSERT_TRUE(ours.status.ok()) << describe(ours.status);
  ASSERT_TRUE(theirs.status.ok()) << describe(theirs.status);
  ASSERT_EQ(ours.response.behaviors_size(), 2);
  ASSERT_EQ(theirs.response.behaviors_size(), 2);
  ASSERT_EQ(ours.response.behaviors(0).name(), "CONTRACT_PROBE");
  clearDocumentation(ours.response.mutable_behaviors(0));
  clearDocumentation(theirs.response.mutable_behaviors(0));
  EXPECT_FALSE(ours.response.behaviors(1).description().empty());
  for (int i = 0; i < 2; ++i) {
    EXPECT_EQ(ours.response.behaviors(i).SerializeAsString(),
              theirs.response.behaviors(i).SerializeAsString())
        << ours.response.behaviors(i).DebugString() << "\nvs the C++ system's\n"
        << theirs.response.behaviors(i).DebugString();
  }
  EXPECT_EQ(reference.terminate(), 0);
}

TEST_F(LifecycleContractTest, AKilledSystemIsProcessFailureAtTheCoordinator) {
  // SIGKILL: no event from the system, no unregistration; the coordinator's
  // supervision ends the activation it knew (kill -9 as PROCESS_FAILURE).
  support::ServerProcess coordinator(kCoordinatorBinary, {});
  ASSERT_TRUE(coordinator.start()) << coordinator.error();
  system_ = systemProcess({"--robot-id", kRobot, "--coordinator", coordinator.address()});
  ASSERT_TRUE(system_->start()) << system_->error();
  coordinator_test::CoordinatorClient fleet(coordinator.address());
  ASSERT_TRUE(fleet.waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  coordinator_test::FleetWatcher watcher(coordinator.address());
  ASSERT_TRUE(watcher.start());
  auto activated = fleet.activate(kRobot, "WAIT", R"({"duration_s": 60})");
  ASSERT_TRUE(activated.status.ok()) << describe(activated.status);
  const std::string id = activated.response.activation().activation_id();
  ASSERT_TRUE(watcher.waitActivated(id));
  system_->kill();
  auto finished = watcher.waitFinished(id, seconds(10));
  ASSERT_TRUE(finished) << "no finished event after the kill";
  EXPECT_EQ(finished->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_TRUE(finished->synthesized());
  EXPECT_EQ(finished->behavior_event().system(), systemName());
  EXPECT_EQ(coordinator.terminate(), 0);
}

// ---------------------------------------------------------------------------
// Simulated time from the channel broker's `clock` topic.

TEST(BehaviorSystemSimClockTest, WaitFollowsSimulatedTimeFromTheChannel) {
  support::ServerProcess broker(kBrokerBinary, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  auto process =
      systemProcess({"--robot-id", kRobot, "--channel", broker.address(), "--clock", "sim"});
  support::ServerProcess& system = *process;
  ASSERT_TRUE(system.start()) << system.error();
  SystemClient client(system.address());

  // No simulated time yet: activation is refused, naming the clock.
  auto refused = client.activate(2);
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(refused.status);
  EXPECT_NE(refused.status.error_message().find("clock"), std::string::npos)
      << refused.status.error_message();

  // A simulator running 10x faster than wall time: +100 ms every 10 ms.
  constexpr int64_t kSimStartS = 1000;
  std::atomic<bool> stop{false};
  std::atomic<int64_t> published{0};
  std::atomic<int64_t> failures{0};
  std::thread simulator([&] {
    behaviorlib::channel::ChannelClient channel(broker.address());
    int64_t sim_ns = kSimStartS * 1'000'000'000;
    uint64_t seq = 0;
    auto next = Clock::now();
    while (!stop.load()) {
      v1::Clock sample;
      const auto stamp = google::protobuf::util::TimeUtil::NanosecondsToTimestamp(sim_ns);
      *sample.mutable_time() = stamp;
      *sample.mutable_header()->mutable_stamp() = stamp;
      sample.mutable_header()->set_seq(++seq);
      sample.set_time_scale(10);
      if (channel.publish("clock", sample).ok()) {
        ++published;
      } else {
        ++failures;
      }
      sim_ns += 100'000'000;
      next += milliseconds(10);
      std::this_thread::sleep_until(next);
    }
  });
  struct Stop {
    std::atomic<bool>& stop;
    std::thread& thread;
    ~Stop() {
      stop = true;
      if (thread.joinable()) thread.join();
    }
  } stopper{stop, simulator};

  // Once the first sample reached the process, activation is accepted.
  EventWatcher watcher(system.address());
  ASSERT_TRUE(watcher.start());
  Reply<v1::ActivateResponse> activated;
  Clock::time_point t0;
  const auto deadline = Clock::now() + seconds(10);
  do {
    t0 = Clock::now();
    activated = client.activate(2);
    if (activated.status.error_code() != grpc::StatusCode::FAILED_PRECONDITION) break;
    std::this_thread::sleep_for(milliseconds(20));
  } while (Clock::now() < deadline);
  ASSERT_TRUE(activated.status.ok()) << describe(activated.status) << " (published "
                                     << published.load() << ", failed " << failures.load() << ")";
  // The activation time is simulated time, not host time.
  const double activation_time = toSeconds(activated.response.activation_time());
  EXPECT_GE(activation_time, kSimStartS);
  EXPECT_LT(activation_time, kSimStartS + 3600);

  auto finished = watcher.waitFinished(activated.response.activation_id(), seconds(5));
  const double wall = elapsedSeconds(t0);
  ASSERT_TRUE(finished) << "WAIT{2} did not finish within 5 s of wall time";
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  // 2 simulated seconds at 10x: ~0.2 s of wall time (far less than 2 s).
  EXPECT_GE(wall, 0.15);
  EXPECT_LT(wall, 1.0);
  const double active = toSeconds(finished->finished().active_duration());
  EXPECT_GE(active, 2.0);
  EXPECT_LT(active, 2.5);
  const double event_time = toSeconds(finished->time());
  // Both read the simulated clock, which moves in 100 ms steps.
  EXPECT_NEAR(event_time - activation_time, active, 0.15);
  EXPECT_EQ(failures.load(), 0);

  EXPECT_EQ(system.terminate(), 0);
  stop = true;
  if (simulator.joinable()) simulator.join();
  EXPECT_EQ(broker.terminate(), 0);
}

// ---------------------------------------------------------------------------
// The deterministic mode (decision 18): the simulator steps itself in quanta
// granted to the systems that follow its time (--follow-time), and waits for
// a busy one.

// The newest simulated time on the channel's clock topic, in seconds (-1
// when there is none yet): the sample's own time, not extrapolated.
double latestClockSeconds(v1::DataChannel::Stub& data) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
  v1::GetLatestRequest request;
  request.set_topic("clock");
  v1::GetLatestResponse response;
  v1::Clock clock;
  if (!data.GetLatest(&context, request, &response).ok() ||
      !response.sample().sample().UnpackTo(&clock)) {
    return -1;
  }
  return toSeconds(clock.time());
}

TEST(BehaviorSystemDeterministicTest, AWaitRunsItsSimulatedTimeAndAFrozenBusySystemStopsTime) {
  support::ServerProcess broker(kBrokerBinary, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  support::ServerProcess simulator(
      kSimulatorBinary, support::deterministicSimulatorArgs(
                            {"--channel", broker.address(), "--follower-timeout-s", "600"}, 1));
  ASSERT_TRUE(simulator.start()) << simulator.error();
  auto process = systemProcess(support::followTimeArgs(
      {"--robot-id", kRobot, "--channel", broker.address(), "--clock", "sim"},
      simulator.address()));
  support::ServerProcess& system = *process;
  ASSERT_TRUE(system.start(seconds(20))) << system.error();
  auto data = v1::DataChannel::NewStub(
      grpc::CreateChannel(broker.address(), grpc::InsecureChannelCredentials()));

  // Time starts once the system joined.
  double t = -1;
  for (int attempt = 0; attempt < 500 && t < 0.5; ++attempt) {
    std::this_thread::sleep_for(milliseconds(20));
    t = latestClockSeconds(*data);
  }
  ASSERT_GE(t, 0.5) << "time did not start with the system following it";

  // A WAIT of 2 s runs 2 s of simulated time and ends within one tick (10 ms)
  // of it, however loaded the machine is.
  SystemClient client(system.address());
  EventWatcher watcher(system.address());
  ASSERT_TRUE(watcher.start());
  auto activated = client.activate(2);
  ASSERT_TRUE(activated.status.ok()) << describe(activated.status);
  auto finished = watcher.waitFinished(activated.response.activation_id(), seconds(60));
  ASSERT_TRUE(finished) << "WAIT{2} did not finish";
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  const double active = toSeconds(finished->finished().active_duration());
  EXPECT_GE(active, 2.0);
  EXPECT_LE(active, 2.0 + 0.0101) << "one tick at most past its end";
  EXPECT_NEAR(toSeconds(finished->time()) - toSeconds(activated.response.activation_time()), active,
              1e-6)
      << "nothing paused it: the event's time is the activation's plus its active time";

  // Busy (a long WAIT active) and frozen: time stands, within the grant in
  // flight. Thawed, it goes on.
  auto busy = client.activate(3600);
  ASSERT_TRUE(busy.status.ok()) << describe(busy.status);
  ASSERT_TRUE(system.freeze()) << system.error();
  std::this_thread::sleep_for(milliseconds(200));
  const double frozen = latestClockSeconds(*data);
  std::this_thread::sleep_for(milliseconds(700));
  EXPECT_LE(latestClockSeconds(*data) - frozen, 0.051) << "time went on without the busy system";
  ASSERT_TRUE(system.thaw()) << system.error();
  double after = frozen;
  for (int attempt = 0; attempt < 500 && after < frozen + 0.5; ++attempt) {
    std::this_thread::sleep_for(milliseconds(20));
    after = latestClockSeconds(*data);
  }
  EXPECT_GE(after, frozen + 0.5) << "time did not go on once the system thawed";
  ASSERT_TRUE(client.deactivate(busy.response.activation_id()).status.ok());

  EXPECT_EQ(system.terminate(), 0);
  EXPECT_EQ(simulator.terminate(), 0);
  EXPECT_EQ(broker.terminate(), 0);
}

}  // namespace
