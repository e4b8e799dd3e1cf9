// The flight behaviors of basic_quadrotor_behaviors (TAKE_OFF, LAND,
// HOVER_WITH_FLIGHT_ACTION_CONTROL, SELF_LOCALIZE_WITH_GROUND_TRUTH) flown
// against the real simulator: the channel broker, the simulator at 10x and
// the behavior system (--clock sim --channel --flight-controller, the shipped
// --config) on free loopback ports, driven over gRPC. Results are checked on
// the simulator's own ground truth and flight state.

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.grpc.pb.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/deterministic.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;
using WallClock = std::chrono::steady_clock;

constexpr char kRobot[] = "drone1";

std::unique_ptr<grpc::ClientContext> deadline(milliseconds timeout = seconds(5)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + timeout);
  return context;
}

std::string describe(const grpc::Status& s) {
  return std::to_string(static_cast<int>(s.error_code())) + " " + s.error_message();
}

// BehaviorSystem.WatchEvents on a reader thread; the test pops events with
// bounded waits.
class EventWatcher {
 public:
  explicit EventWatcher(const std::string& address)
      : stub_(v1::BehaviorSystem::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(60));
    reader_ = stub_->WatchEvents(&context_, v1::WatchEventsRequest());
    thread_ = std::thread([this] {
      v1::WatchEventsResponse message;
      while (reader_->Read(&message)) {
        if (!message.has_event()) continue;
        std::lock_guard lock(mutex_);
        events_.push_back(message.event());
        cv_.notify_all();
      }
      reader_->Finish();
    });
  }
  ~EventWatcher() {
    context_.TryCancel();
    thread_.join();
  }

  // The finished event of `behavior`, or nullopt after `timeout` (wall).
  std::optional<v1::BehaviorEvent> finished(const std::string& behavior,
                                            milliseconds timeout = seconds(20)) {
    std::unique_lock lock(mutex_);
    std::optional<v1::BehaviorEvent> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const auto& e : events_) {
        if (e.behavior() == behavior && e.has_finished()) {
          found = e;
          return true;
        }
      }
      return false;
    });
    return found;
  }

 private:
  std::unique_ptr<v1::BehaviorSystem::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchEventsResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<v1::BehaviorEvent> events_;
};

class FlightBehaviorsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH, support::deterministicSimulatorArgs(
                                        {"--channel", broker_.address(), "--vehicles", kRobot}, 1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    system_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH,
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--flight-controller", simulator_->address(), "--config",
                                 BEHAVIORLIB_BASIC_CONFIG_PATH},
                                simulator_->address()));
    ASSERT_TRUE(system_->start()) << system_->error();
    auto channel = grpc::CreateChannel(system_->address(), grpc::InsecureChannelCredentials());
    behaviors_ = v1::BehaviorSystem::NewStub(channel);
    take_off_ = v1::TakeOff::NewStub(channel);
    flight_ = v1::FlightController::NewStub(
        grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
    data_ = v1::DataChannel::NewStub(
        grpc::CreateChannel(broker_.address(), grpc::InsecureChannelCredentials()));
    events_ = std::make_unique<EventWatcher>(system_->address());
  }

  void TearDown() override {
    events_.reset();
    // SIGKILL: an orderly SIGTERM exit is checked once, in the hover test
    // (it takes a few seconds of gRPC shutdown per process).
    if (system_ && system_->running()) system_->kill();
  }

  // Activates a behavior through the generic API; retried while the
  // behavior system has no simulated time yet (the simulator just started).
  grpc::Status activate(const std::string& behavior, const std::string& json,
                        v1::ActivateResponse* response) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    EXPECT_TRUE(
        google::protobuf::util::JsonStringToMessage(json, request.mutable_parameters()).ok());
    grpc::Status status;
    for (int attempt = 0; attempt < 100; ++attempt) {
      status = behaviors_->ActivateBehavior(deadline().get(), request, response);
      if (status.ok() || status.error_message().find("no time yet") == std::string::npos) break;
      std::this_thread::sleep_for(milliseconds(20));
    }
    return status;
  }

  v1::CheckSituationResponse checkSituation(const std::string& behavior) {
    v1::CheckBehaviorSituationRequest request;
    request.set_behavior(behavior);
    v1::CheckSituationResponse response;
    auto status = behaviors_->CheckBehaviorSituation(deadline().get(), request, &response);
    EXPECT_TRUE(status.ok()) << describe(status);
    return response;
  }

  grpc::Status deactivate(const std::string& behavior) {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior);
    v1::DeactivateResponse response;
    return behaviors_->DeactivateBehavior(deadline().get(), request, &response);
  }

  // The newest sample on a topic, unpacked; nullopt when there is none.
  template <class T>
  std::optional<T> latest(const std::string& topic) {
    v1::GetLatestRequest request;
    request.set_topic(topic);
    v1::GetLatestResponse response;
    T message;
    if (!data_->GetLatest(deadline().get(), request, &response).ok() ||
        !response.sample().sample().UnpackTo(&message)) {
      return std::nullopt;
    }
    return message;
  }

  // drone1's flight status as the simulator reports it.
  v1::FlightStatus flightStatus() {
    auto context = deadline();
    v1::WatchFlightStateRequest request;
    request.set_robot_id(kRobot);
    auto reader = flight_->WatchFlightState(context.get(), request);
    v1::WatchFlightStateResponse message;
    EXPECT_TRUE(reader->Read(&message));
    context->TryCancel();
    reader->Finish();
    return message.status();
  }

  // Starts SELF_LOCALIZE_WITH_GROUND_TRUTH and waits for its first pose and
  // velocity estimates (two topics: either may come first).
  void localize() {
    v1::ActivateResponse activated;
    auto status = activate("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}", &activated);
    ASSERT_TRUE(status.ok()) << describe(status);
    const auto estimated = [this] {
      return latest<v1::PoseStamped>("robots/drone1/self_localization/pose") &&
             latest<v1::TwistStamped>("robots/drone1/self_localization/twist");
    };
    // A bound for a stuck stack, not a timing: generous for a loaded machine.
    const auto until = WallClock::now() + seconds(30);
    while (!estimated() && WallClock::now() < until) {
      std::this_thread::sleep_for(milliseconds(10));
    }
    ASSERT_TRUE(estimated());
  }

  // Publishes drone1's pose and velocity estimates as an estimator would: at
  // its ground truth, stamped as the ground truth, the pose stating
  // `stddev_m` of horizontal standard deviation.
  void publishEstimate(double stddev_m) {
    auto pose = latest<v1::PoseStamped>("robots/drone1/ground_truth/pose");
    auto twist = latest<v1::TwistStamped>("robots/drone1/ground_truth/twist");
    ASSERT_TRUE(pose && twist);
    pose->set_horizontal_stddev_m(stddev_m);
    v1::PublishRequest request;
    request.set_topic("robots/drone1/self_localization/pose");
    request.mutable_sample()->PackFrom(*pose);
    request.set_sync(true);
    v1::PublishRequest* velocity = request.add_more();
    velocity->set_topic("robots/drone1/self_localization/twist");
    velocity->mutable_sample()->PackFrom(*twist);
    auto context = deadline();
    v1::PublishResponse response;
    auto writer = data_->Publish(context.get(), &response);
    ASSERT_TRUE(writer->Write(request));
    writer->WritesDone();
    ASSERT_TRUE(writer->Finish().ok());
  }

  // Takes off to `altitude_m` with the typed API and waits for the end.
  v1::BehaviorEvent takeOff(double altitude_m) {
    v1::TakeOffActivateRequest request;
    request.mutable_parameters()->set_altitude_m(altitude_m);
    v1::ActivateResponse activated;
    auto status = take_off_->Activate(deadline().get(), request, &activated);
    EXPECT_TRUE(status.ok()) << describe(status);
    auto finished = events_->finished("TAKE_OFF");
    EXPECT_TRUE(finished) << "TAKE_OFF did not finish";
    return finished.value_or(v1::BehaviorEvent());
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> system_;
  std::unique_ptr<v1::BehaviorSystem::Stub> behaviors_;
  std::unique_ptr<v1::TakeOff::Stub> take_off_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<v1::DataChannel::Stub> data_;
  std::unique_ptr<EventWatcher> events_;
};

TEST_F(FlightBehaviorsTest, SelfLocalizationPublishesTheGroundTruthAsTheEstimate) {
  ASSERT_NO_FATAL_FAILURE(localize());
  std::this_thread::sleep_for(milliseconds(100));  // about 1 s of simulated time
  auto truth = latest<v1::PoseStamped>("robots/drone1/ground_truth/pose");
  auto estimate = latest<v1::PoseStamped>("robots/drone1/self_localization/pose");
  auto twist = latest<v1::TwistStamped>("robots/drone1/self_localization/twist");
  ASSERT_TRUE(truth && estimate && twist);
  EXPECT_EQ(estimate->header().robot_id(), kRobot);
  EXPECT_EQ(estimate->header().frame_id(), "world");
  EXPECT_GT(estimate->header().seq(), 10u) << "one estimate per ground-truth sample";
  EXPECT_GT(twist->header().seq(), 10u);
  // The estimate follows the truth: at most a few samples behind.
  const auto lag = TimeUtil::TimestampToMilliseconds(truth->header().stamp()) -
                   TimeUtil::TimestampToMilliseconds(estimate->header().stamp());
  EXPECT_LE(std::abs(lag), 100) << "estimate lags the ground truth by " << lag << " ms";
  EXPECT_NEAR(estimate->pose().position_m().x(), truth->pose().position_m().x(), 1e-6);
  EXPECT_NEAR(estimate->pose().position_m().z(), truth->pose().position_m().z(), 1e-6);

  // Deactivated, it stops publishing.
  ASSERT_TRUE(deactivate("SELF_LOCALIZE_WITH_GROUND_TRUTH").ok());
  auto finished = events_->finished("SELF_LOCALIZE_WITH_GROUND_TRUTH");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  // (Samples already written to the publish stream may still arrive.)
  std::this_thread::sleep_for(milliseconds(100));
  const auto last = latest<v1::PoseStamped>("robots/drone1/self_localization/pose");
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_EQ(latest<v1::PoseStamped>("robots/drone1/self_localization/pose")->header().seq(),
            last->header().seq());
}

TEST_F(FlightBehaviorsTest, TakeOffReachesTheAltitudeRefusesASecondTakeOffAndLands) {
  ASSERT_NO_FATAL_FAILURE(localize());
  const auto event = takeOff(1.5);
  ASSERT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << event.ShortDebugString();
  const auto truth = latest<v1::PoseStamped>("robots/drone1/ground_truth/pose");
  ASSERT_TRUE(truth);
  EXPECT_NEAR(truth->pose().position_m().z(), 1.5, 0.1) << "simulator's ground truth";
  std::printf("TAKE_OFF 1.5 m: ground truth %.4f m after %.2f s of simulated time (%s)\n",
              truth->pose().position_m().z(),
              TimeUtil::DurationToMilliseconds(event.finished().active_duration()) / 1e3,
              event.finished().message().c_str());
  const auto status = flightStatus();
  EXPECT_EQ(status.state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_EQ(status.lease_holder(), "") << "TAKE_OFF released the lease";

  // Flying: a second TAKE_OFF is refused by checkSituation, with the reason.
  auto situation = checkSituation("TAKE_OFF");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("LANDED"), std::string::npos) << situation.reasons(0);
  v1::ActivateResponse activated;
  auto refused = activate("TAKE_OFF", R"({"altitude_m": 2})", &activated);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(refused);
  EXPECT_NE(refused.error_message().find("HOVERING"), std::string::npos) << describe(refused);

  // LAND, before which LAND's situation is feasible.
  const auto land_situation = checkSituation("LAND");
  EXPECT_TRUE(land_situation.feasible()) << land_situation.ShortDebugString();
  auto landing = activate("LAND", "{}", &activated);
  ASSERT_TRUE(landing.ok()) << describe(landing);
  const auto landed = events_->finished("LAND");
  ASSERT_TRUE(landed);
  EXPECT_EQ(landed->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << landed->ShortDebugString();
  std::printf("LAND: %.2f s of simulated time (%s)\n",
              TimeUtil::DurationToMilliseconds(landed->finished().active_duration()) / 1e3,
              landed->finished().message().c_str());
  EXPECT_EQ(flightStatus().state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_NEAR(latest<v1::PoseStamped>("robots/drone1/ground_truth/pose")->pose().position_m().z(),
              0.0, 0.05);
  // Landed: LAND is now infeasible, TAKE_OFF feasible again.
  EXPECT_FALSE(checkSituation("LAND").feasible());
  EXPECT_TRUE(checkSituation("TAKE_OFF").feasible());
}

TEST_F(FlightBehaviorsTest, TakeOffWaitsForAnEstimateThatHasConverged) {
  // An EKF just started: it states 1.2 m. TAKE_OFF is refused, with the reason.
  const auto until = WallClock::now() + seconds(30);  // a bound for a stuck stack
  while ((!latest<v1::PoseStamped>("robots/drone1/ground_truth/pose") ||
          !latest<v1::TwistStamped>("robots/drone1/ground_truth/twist")) &&
         WallClock::now() < until) {
    std::this_thread::sleep_for(milliseconds(10));
  }
  ASSERT_NO_FATAL_FAILURE(publishEstimate(1.2));
  auto situation = checkSituation("TAKE_OFF");
  EXPECT_FALSE(situation.feasible()) << situation.ShortDebugString();
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("1.20 m, above max_pose_stddev_m 0.30 m"), std::string::npos)
      << situation.reasons(0);
  ASSERT_GT(situation.reason_codes_size(), 0);
  EXPECT_EQ(situation.reason_codes(0), v1::SITUATION_REASON_INPUT_INVALID);
  v1::ActivateResponse activated;
  auto refused = activate("TAKE_OFF", R"({"altitude_m": 1})", &activated);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(refused);
  EXPECT_EQ(flightStatus().state(), v1::FLIGHT_STATE_LANDED) << "nothing moved";
  // Converged: 0.1 m. TAKE_OFF may go.
  ASSERT_NO_FATAL_FAILURE(publishEstimate(0.1));
  situation = checkSituation("TAKE_OFF");
  EXPECT_TRUE(situation.feasible()) << situation.ShortDebugString();
}

TEST_F(FlightBehaviorsTest, HoverHoldsTheLeaseUntilDeactivatedAndLeavesTheVehicleHovering) {
  ASSERT_NO_FATAL_FAILURE(localize());
  ASSERT_EQ(takeOff(1.0).finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  v1::ActivateResponse activated;
  auto status = activate("HOVER_WITH_FLIGHT_ACTION_CONTROL", R"({"max_drift_m": 0.3})", &activated);
  ASSERT_TRUE(status.ok()) << describe(status);
  std::this_thread::sleep_for(milliseconds(500));  // about 5 s simulated
  EXPECT_EQ(flightStatus().lease_holder(), "drone1/HOVER_WITH_FLIGHT_ACTION_CONTROL")
      << "the lease is renewed beyond its 2 s ttl; "
      << events_->finished("HOVER_WITH_FLIGHT_ACTION_CONTROL", milliseconds(0))
             .value_or(v1::BehaviorEvent())
             .ShortDebugString();
  ASSERT_TRUE(deactivate("HOVER_WITH_FLIGHT_ACTION_CONTROL").ok());
  auto finished = events_->finished("HOVER_WITH_FLIGHT_ACTION_CONTROL");
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED)
      << finished->ShortDebugString();
  const auto after = flightStatus();
  EXPECT_EQ(after.state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_EQ(after.lease_holder(), "");
  EXPECT_NEAR(latest<v1::PoseStamped>("robots/drone1/ground_truth/pose")->pose().position_m().z(),
              1.0, 0.1);

  // SIGTERM while hovering: HOVER ends INTERRUPTED, releases the lease, and
  // the process exits 0.
  status = activate("HOVER_WITH_FLIGHT_ACTION_CONTROL", "{}", &activated);
  ASSERT_TRUE(status.ok()) << describe(status);
  ASSERT_EQ(flightStatus().lease_holder(), "drone1/HOVER_WITH_FLIGHT_ACTION_CONTROL");
  EXPECT_EQ(system_->terminate(), 0);
  EXPECT_EQ(flightStatus().lease_holder(), "");
  EXPECT_EQ(flightStatus().state(), v1::FLIGHT_STATE_HOVERING);
}

TEST_F(FlightBehaviorsTest, KillingTheSimulatorDuringTakeOffIsAProcessFailure) {
  ASSERT_NO_FATAL_FAILURE(localize());
  v1::ActivateResponse activated;
  auto status = activate("TAKE_OFF", R"({"altitude_m": 20})", &activated);
  ASSERT_TRUE(status.ok()) << describe(status);
  std::this_thread::sleep_for(milliseconds(100));  // climbing
  simulator_->kill();
  auto finished = events_->finished("TAKE_OFF", seconds(10));
  ASSERT_TRUE(finished) << "no PROCESS_FAILURE after the simulator died";
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished->ShortDebugString();
  EXPECT_FALSE(finished->finished().message().empty());
  std::printf("simulator killed: TAKE_OFF %s\n", finished->finished().message().c_str());
  // The localization notices it too, and the process keeps serving.
  auto localization = events_->finished("SELF_LOCALIZE_WITH_GROUND_TRUTH", seconds(10));
  ASSERT_TRUE(localization);
  EXPECT_EQ(localization->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(localization->finished().message().find("ground truth"), std::string::npos)
      << localization->finished().message();
  auto situation = checkSituation("TAKE_OFF");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find(simulator_->address()), std::string::npos)
      << situation.reasons(0);
}

TEST_F(FlightBehaviorsTest, OutOfRangeParametersAreInvalidArgumentNamingThemBeforeAnythingMoves) {
  v1::TakeOffActivateRequest request;
  request.mutable_parameters()->set_altitude_m(500);
  v1::ActivateResponse activated;
  auto status = take_off_->Activate(deadline().get(), request, &activated);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("altitude_m"), std::string::npos) << describe(status);
  status = activate("HOVER_WITH_FLIGHT_ACTION_CONTROL", R"({"max_drift_m": -1})", &activated);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("max_drift_m"), std::string::npos) << describe(status);
  status = activate("TAKE_OFF", R"({"altitude": 2})", &activated);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("altitude"), std::string::npos) << describe(status);
  // Nothing moved.
  std::this_thread::sleep_for(milliseconds(100));
  const auto s = flightStatus();
  EXPECT_EQ(s.state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_EQ(s.lease_holder(), "");
}

// Without a simulator (nothing at the flight controller's address, no
// simulated time) the process serves and says why nothing can fly.
TEST(FlightBehaviorsWithoutSimulatorTest, TheSystemServesAndCheckSituationSaysWhy) {
  support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  // A port nothing listens on: the broker's metrics port is HTTP, so take a
  // closed one by starting and stopping a second broker.
  support::ServerProcess gone(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  ASSERT_TRUE(gone.start()) << gone.error();
  const std::string nowhere = gone.address();
  gone.kill();
  support::ServerProcess system(
      BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH,
      {"--robot-id", kRobot, "--channel", broker.address(), "--clock", "sim", "--flight-controller",
       nowhere, "--config", BEHAVIORLIB_BASIC_CONFIG_PATH});
  ASSERT_TRUE(system.start()) << system.error();
  auto stub = v1::BehaviorSystem::NewStub(
      grpc::CreateChannel(system.address(), grpc::InsecureChannelCredentials()));
  for (const char* behavior : {"TAKE_OFF", "LAND", "HOVER_WITH_FLIGHT_ACTION_CONTROL"}) {
    v1::CheckBehaviorSituationRequest request;
    request.set_behavior(behavior);
    v1::CheckSituationResponse response;
    auto status = stub->CheckBehaviorSituation(deadline().get(), request, &response);
    ASSERT_TRUE(status.ok()) << describe(status);
    EXPECT_FALSE(response.feasible()) << behavior;
    ASSERT_GT(response.reasons_size(), 0) << behavior;
    EXPECT_NE(response.reasons(0).find(nowhere), std::string::npos)
        << behavior << ": " << response.reasons(0);
  }
  v1::CheckBehaviorSituationRequest request;
  request.set_behavior("SELF_LOCALIZE_WITH_GROUND_TRUTH");
  v1::CheckSituationResponse response;
  ASSERT_TRUE(stub->CheckBehaviorSituation(deadline().get(), request, &response).ok());
  EXPECT_FALSE(response.feasible());
  ASSERT_GT(response.reasons_size(), 0);
  EXPECT_NE(response.reasons(0).find("ground truth"), std::string::npos) << response.reasons(0);

  v1::ActivateBehaviorRequest activate;
  activate.set_behavior("TAKE_OFF");
  v1::ActivateResponse activated;
  auto status = stub->ActivateBehavior(deadline().get(), activate, &activated);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(status);
  // Still serving.
  v1::ListBehaviorsResponse listing;
  EXPECT_TRUE(stub->ListBehaviors(deadline().get(), v1::ListBehaviorsRequest(), &listing).ok());
  EXPECT_EQ(listing.behaviors_size(), 7);
}

}  // namespace
