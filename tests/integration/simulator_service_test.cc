// The simulator binary with its real dynamics, on free loopback ports, driven
// over gRPC as a motion controller would, with state and time checked on the
// real data channel broker.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <csignal>
#include <fstream>
#include <map>
#include <optional>
#include <set>
#include <thread>
#include <vector>

#include "behaviorlib/error_details.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.grpc.pb.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

std::unique_ptr<grpc::ClientContext> deadline(seconds s = seconds(10)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + s);
  return context;
}

// Activates WAIT{duration_s} on the behavior system at `address` (retried
// for 1 s while it has no simulated time yet) and returns its finished
// event; nullopt, with `error`, when refused or the event stream ended first.
std::optional<v1::BehaviorEvent> runWait(const std::string& address, double duration_s,
                                         std::string* error) {
  auto stub =
      v1::BehaviorSystem::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  auto watch_context = deadline(seconds(30));
  auto reader = stub->WatchEvents(watch_context.get(), v1::WatchEventsRequest());
  v1::WatchEventsResponse message;
  if (!reader->Read(&message)) {  // the start message
    *error = "no event stream";
    return std::nullopt;
  }
  v1::ActivateBehaviorRequest activate;
  activate.set_behavior("WAIT");
  (*activate.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(duration_s);
  v1::ActivateResponse activated;
  grpc::Status status;
  for (int attempt = 0; attempt < 50; ++attempt) {  // until the sim clock reached the system
    status = stub->ActivateBehavior(deadline().get(), activate, &activated);
    if (status.ok()) break;
    std::this_thread::sleep_for(milliseconds(20));
  }
  if (!status.ok()) {
    *error = status.error_message();
    return std::nullopt;
  }
  std::optional<v1::BehaviorEvent> finished;
  while (!finished && reader->Read(&message)) {
    // Ours only: an earlier activation's end may still be on its way.
    if (message.has_event() && message.event().has_finished() &&
        message.event().activation_id() == activated.activation_id()) {
      finished = message.event();
    }
  }
  watch_context->TryCancel();
  reader->Finish();
  if (!finished) *error = "the event stream ended before WAIT finished";
  return finished;
}

class SimulatorServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        std::vector<std::string>{"--channel", broker_.address(), "--vehicles", "drone1,drone2",
                                 "--time-scale", "10"});
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    auto channel = grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials());
    flight_ = v1::FlightController::NewStub(channel);
    sim_ = v1::Simulator::NewStub(channel);
    data_ = v1::DataChannel::NewStub(
        grpc::CreateChannel(broker_.address(), grpc::InsecureChannelCredentials()));
  }

  std::string lease(const std::string& holder = "test-controller", int ttl_ms = 500) {
    v1::AcquireLeaseRequest request;
    request.set_robot_id("drone1");
    request.set_holder(holder);
    *request.mutable_ttl() = TimeUtil::MillisecondsToDuration(ttl_ms);
    v1::AcquireLeaseResponse response;
    auto status = flight_->AcquireLease(deadline().get(), request, &response);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return response.lease_id();
  }
  grpc::Status action(v1::FlightAction a, const std::string& lease_id, double altitude = 0) {
    v1::ExecuteFlightActionRequest request;
    request.set_robot_id("drone1");
    request.set_lease_id(lease_id);
    request.set_action(a);
    request.set_takeoff_altitude_m(altitude);
    v1::ExecuteFlightActionResponse response;
    return flight_->ExecuteFlightAction(deadline().get(), request, &response);
  }
  // Ground truth of drone1 from the broker.
  v1::PoseStamped pose() {
    v1::GetLatestRequest request;
    request.set_topic("robots/drone1/ground_truth/pose");
    v1::GetLatestResponse response;
    v1::PoseStamped pose;
    if (data_->GetLatest(deadline().get(), request, &response).ok()) {
      response.sample().sample().UnpackTo(&pose);
    }
    return pose;
  }
  // Waits (wall time) for drone1's flight state (and failsafe flag if asked);
  // FLIGHT_STATE_UNSPECIFIED takes the current status, whatever it is.
  bool waitForState(v1::FlightState wanted, seconds timeout, bool want_failsafe = false) {
    auto context = deadline(timeout);
    v1::WatchFlightStateRequest request;
    request.set_robot_id("drone1");
    auto reader = flight_->WatchFlightState(context.get(), request);
    v1::WatchFlightStateResponse message;
    while (reader->Read(&message)) {
      last_status_ = message.status();
      if ((wanted == v1::FLIGHT_STATE_UNSPECIFIED || message.status().state() == wanted) &&
          (!want_failsafe || message.status().failsafe_active())) {
        context->TryCancel();
        reader->Finish();
        return true;
      }
    }
    reader->Finish();
    return false;
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<v1::DataChannel::Stub> data_;
  v1::FlightStatus last_status_;
};

TEST_F(SimulatorServiceTest, TakeOffWithTheRealDynamicsHoversAtTheTargetAltitude) {
  ASSERT_TRUE(waitForState(v1::FLIGHT_STATE_LANDED, seconds(5)));
  const std::string id = lease("test-controller", 5000);
  // On the ground, LAND and setpoints are refused with the flight state.
  const grpc::Status land = action(v1::FLIGHT_ACTION_LAND, id, 0.0);
  EXPECT_EQ(land.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  const auto conflict = behaviorlib::errors::errorInfo(land);
  ASSERT_TRUE(conflict.has_value());
  EXPECT_EQ(conflict->reason(), "FLIGHT_STATE_CONFLICT");
  EXPECT_EQ(conflict->metadata().at("flight_state"), "FLIGHT_STATE_LANDED");
  EXPECT_EQ(conflict->metadata().at("robot"), "drone1");
  ASSERT_TRUE(action(v1::FLIGHT_ACTION_TAKE_OFF, id, 2.0).ok());
  ASSERT_TRUE(waitForState(v1::FLIGHT_STATE_HOVERING, seconds(10)));
  std::this_thread::sleep_for(milliseconds(500));  // 5 s simulated: settle
  const auto p = pose();
  EXPECT_NEAR(p.pose().position_m().z(), 2.0, 0.25);
  EXPECT_NEAR(p.pose().position_m().x(), 0.0, 0.25);
  EXPECT_EQ(p.header().robot_id(), "drone1");
  EXPECT_EQ(p.header().frame_id(), "world");
}

TEST_F(SimulatorServiceTest, LeaseRefusesOthersAndItsLossHoversThenLands) {
  const std::string id = lease("controller", 10000);
  ASSERT_TRUE(action(v1::FLIGHT_ACTION_TAKE_OFF, id, 1.5).ok());
  ASSERT_TRUE(waitForState(v1::FLIGHT_STATE_HOVERING, seconds(10)));
  // Simulated time stands still (lock-step) while the leases are checked: at
  // 10x, the leases' 10 s and 200 ms are 1 s and 20 ms of wall time, less
  // than a busy machine may take between two calls.
  v1::SetTimeScaleRequest freeze;
  freeze.set_lock_step(true);
  v1::SetTimeScaleResponse scale;
  ASSERT_TRUE(sim_->SetTimeScale(deadline().get(), freeze, &scale).ok());

  v1::AcquireLeaseRequest intruder;
  intruder.set_robot_id("drone1");
  intruder.set_holder("intruder");
  v1::AcquireLeaseResponse ignored;
  auto refused = flight_->AcquireLease(deadline().get(), intruder, &ignored);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(refused.error_message().find("controller"), std::string::npos);

  v1::SetpointRequest setpoint;
  setpoint.set_robot_id("drone1");
  setpoint.set_lease_id("forged");
  setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(1.0);
  v1::SendSetpointResponse response;
  EXPECT_EQ(flight_->SendSetpoint(deadline().get(), setpoint, &response).error_code(),
            grpc::StatusCode::FAILED_PRECONDITION);
  setpoint.set_lease_id(id);
  setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(std::nan(""));
  const grpc::Status not_finite = flight_->SendSetpoint(deadline().get(), setpoint, &response);
  EXPECT_EQ(not_finite.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  // No finer reason was given: INVALID_ARGUMENT says a request field is wrong.
  EXPECT_EQ(behaviorlib::errors::errorInfo(not_finite).value_or(google::rpc::ErrorInfo()).reason(),
            "INVALID_REQUEST");
  setpoint.set_robot_id("drone9");
  EXPECT_EQ(flight_->SendSetpoint(deadline().get(), setpoint, &response).error_code(),
            grpc::StatusCode::NOT_FOUND);

  // A short lease, one setpoint, then silence: hover (failsafe), then land.
  const std::string short_lease = lease("controller", 200);
  setpoint.set_robot_id("drone1");
  setpoint.set_lease_id(short_lease);
  setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(0.5);
  ASSERT_TRUE(flight_->SendSetpoint(deadline().get(), setpoint, &response).ok());
  EXPECT_EQ(response.state(), v1::FLIGHT_STATE_FLYING);
  // Silence, stepped 100 ms at a time: the failsafe hovers, then lands.
  std::vector<v1::FlightState> seen;
  bool failsafe_hover = false;
  v1::StepRequest step;
  *step.mutable_duration() = TimeUtil::MillisecondsToDuration(100);
  v1::StepResponse stepped;
  for (int i = 0; i < 300 && (seen.empty() || seen.back() != v1::FLIGHT_STATE_LANDED); ++i) {
    ASSERT_TRUE(sim_->Step(deadline().get(), step, &stepped).ok());
    ASSERT_TRUE(waitForState(v1::FLIGHT_STATE_UNSPECIFIED, seconds(5)));  // the current status
    if (seen.empty() || seen.back() != last_status_.state()) seen.push_back(last_status_.state());
    failsafe_hover |=
        last_status_.state() == v1::FLIGHT_STATE_HOVERING && last_status_.failsafe_active();
  }
  EXPECT_TRUE(failsafe_hover);
  const std::vector<v1::FlightState> expected = {v1::FLIGHT_STATE_FLYING, v1::FLIGHT_STATE_HOVERING,
                                                 v1::FLIGHT_STATE_LANDING, v1::FLIGHT_STATE_LANDED};
  EXPECT_EQ(seen, expected);
  EXPECT_NEAR(pose().pose().position_m().z(), 0.0, 0.05);
}

TEST_F(SimulatorServiceTest, LockStepAdvancesExactlyAndFaultInjectionIsOffByDefault) {
  v1::SetTimeScaleRequest lock;
  lock.set_lock_step(true);
  v1::SetTimeScaleResponse scale;
  ASSERT_TRUE(sim_->SetTimeScale(deadline().get(), lock, &scale).ok());
  EXPECT_TRUE(scale.lock_step());
  v1::StepRequest step;
  *step.mutable_duration() = TimeUtil::MillisecondsToDuration(10);
  v1::StepResponse before, after;
  ASSERT_TRUE(sim_->Step(deadline().get(), step, &before).ok());
  *step.mutable_duration() = TimeUtil::SecondsToDuration(2);
  ASSERT_TRUE(sim_->Step(deadline().get(), step, &after).ok());
  EXPECT_EQ(TimeUtil::DurationToMilliseconds(after.time() - before.time()), 2000);

  v1::SetTimeScaleRequest bad;
  bad.set_time_scale(1e6);
  EXPECT_EQ(sim_->SetTimeScale(deadline().get(), bad, &scale).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);

  v1::InjectFailureRequest failure;
  failure.set_robot_id("drone1");
  failure.set_component(v1::FAILURE_COMPONENT_GPS);
  failure.set_type(v1::FAILURE_TYPE_OFF);
  v1::InjectFailureResponse injected;
  const grpc::Status disabled = sim_->InjectFailure(deadline().get(), failure, &injected);
  EXPECT_EQ(disabled.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_EQ(behaviorlib::errors::errorInfo(disabled).value_or(google::rpc::ErrorInfo()).reason(),
            "FEATURE_NOT_ENABLED");
}

TEST_F(SimulatorServiceTest, SimulatedTimeDrivesABehaviorSystemThroughTheChannel) {
  v1::GetLatestRequest request;
  request.set_topic("clock");
  v1::GetLatestResponse response;
  bool published = false;
  for (int attempt = 0; attempt < 100 && !published; ++attempt) {  // first samples in flight
    published = data_->GetLatest(deadline().get(), request, &response).ok();
    if (!published) std::this_thread::sleep_for(milliseconds(20));
  }
  ASSERT_TRUE(published) << "no sample on 'clock'";
  v1::Clock clock;
  ASSERT_TRUE(response.sample().sample().UnpackTo(&clock));
  EXPECT_DOUBLE_EQ(clock.time_scale(), 10.0);

  support::ServerProcess system(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH,
                                {"--channel", broker_.address(), "--clock", "sim"});
  ASSERT_TRUE(system.start()) << system.error();
  // WAIT 3 s of simulated time at 10x: about 0.3 s of wall time.
  const auto wall_start = std::chrono::steady_clock::now();
  std::string error;
  const auto finished = runWait(system.address(), 3.0, &error);
  const double wall_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - wall_start).count();
  ASSERT_TRUE(finished) << error;
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  const double active_s =
      TimeUtil::DurationToMilliseconds(finished->finished().active_duration()) / 1e3;
  EXPECT_NEAR(active_s, 3.0, 0.1) << "active time is simulated time";
  EXPECT_LT(wall_s, 2.5) << "3 simulated seconds at 10x";
  EXPECT_EQ(system.terminate(), 0);
}

// The latest Clock sample on the topic (nullopt when none).
std::optional<v1::Clock> latestClock(v1::DataChannel::Stub& data) {
  v1::GetLatestRequest request;
  request.set_topic("clock");
  v1::GetLatestResponse response;
  v1::Clock clock;
  if (!data.GetLatest(deadline().get(), request, &response).ok() ||
      !response.sample().sample().UnpackTo(&clock)) {
    return std::nullopt;
  }
  return clock;
}

// Simulated time on the channel's clock topic (seconds; -1 when none yet):
// its line extrapolated to now, as types.proto's Clock says.
double clockSeconds(v1::DataChannel::Stub& data) {
  const auto clock = latestClock(data);
  if (!clock) return -1;
  const double wall_now_s =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  const double since_s = wall_now_s - TimeUtil::TimestampToNanoseconds(clock->wall_time()) / 1e9;
  return TimeUtil::TimestampToMilliseconds(clock->time()) / 1e3 +
         (clock->has_wall_time() ? since_s * clock->time_scale() : 0.0);
}

// The number of samples the broker took on `topic` so far (0 if unknown).
uint64_t publishedCount(v1::DataChannel::Stub& data, const std::string& topic) {
  v1::ListTopicsRequest request;
  request.set_prefix(topic);
  v1::ListTopicsResponse response;
  if (!data.ListTopics(deadline().get(), request, &response).ok()) return 0;
  for (const auto& info : response.topics()) {
    if (info.name() == topic) return info.published_count();
  }
  return 0;
}

// Samples arriving on `topic` within `window` of wall time.
int samplesWithin(v1::DataChannel::Stub& data, const std::string& topic,
                  std::chrono::milliseconds window) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + window);
  v1::SubscribeRequest request;
  request.set_topic(topic);
  request.set_mode(v1::DELIVERY_MODE_QUEUE);
  request.set_queue_size(10000);
  auto reader = data.Subscribe(&context, request);
  v1::SubscribeResponse response;
  int samples = 0;
  while (reader->Read(&response)) ++samples;
  return samples;
}

TEST_F(SimulatorServiceTest, VehicleTopicsArePublishedOnlyWhileWanted) {
  const std::string imu = "robots/drone1/imu";
  for (int attempt = 0; attempt < 100 && publishedCount(*data_, imu) == 0; ++attempt) {
    std::this_thread::sleep_for(milliseconds(50));
  }
  ASSERT_GT(publishedCount(*data_, imu), 0u) << "the topic's first sample makes it known";
  const uint64_t before = publishedCount(*data_, imu);
  std::this_thread::sleep_for(milliseconds(500));  // 5 s simulated: 1000 IMU samples at 200 Hz
  EXPECT_LT(publishedCount(*data_, imu) - before, 20u) << "nobody subscribes: (almost) none";
  // A subscriber gets the stream at once, at its rate (1 s at 10x: 2000
  // samples; the bound leaves room for a loaded machine).
  EXPECT_GT(samplesWithin(*data_, imu, milliseconds(1000)), 200);
  // The subscriber gone (its leaving reaches the simulator in a moment),
  // the topic stops again.
  std::this_thread::sleep_for(milliseconds(500));
  const uint64_t after = publishedCount(*data_, imu);
  std::this_thread::sleep_for(milliseconds(1000));  // 10 s simulated: 2000 IMU samples
  ASSERT_LT(publishedCount(*data_, imu) - after, 20u);
  // A GetLatest gets a fresh sample although nobody subscribes.
  v1::GetLatestRequest request;
  request.set_topic("robots/drone1/ground_truth/pose");
  v1::GetLatestResponse response;
  ASSERT_TRUE(data_->GetLatest(deadline().get(), request, &response).ok());
  v1::PoseStamped pose;
  ASSERT_TRUE(response.sample().sample().UnpackTo(&pose));
  EXPECT_NEAR(TimeUtil::TimestampToMilliseconds(pose.header().stamp()) / 1e3, clockSeconds(*data_),
              1.0)
      << "the pose is current (within 1 s simulated of the clock)";
}

// Polls `condition` (wall time) until true or 10 s.
template <class F>
bool eventuallyTrue(F condition) {
  const auto deadline = std::chrono::steady_clock::now() + seconds(10);
  while (!condition()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(milliseconds(20));
  }
  return true;
}

TEST_F(SimulatorServiceTest, AVehicleTopicReadAtARateIsPublishedAtThatRate) {
  const std::string imu = "robots/drone1/imu";
  ASSERT_TRUE(eventuallyTrue([&] { return publishedCount(*data_, imu) > 0; }));
  // A reader at 5 samples a second of wall time: the simulator publishes
  // the IMU (200 Hz simulated, 2000 a wall second at 10x) about that often.
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + seconds(30));
  v1::SubscribeRequest request;
  request.set_topic(imu);
  request.set_max_rate_hz(5);
  auto reader = data_->Subscribe(&context, request);
  std::atomic<int> received{0};
  std::thread reading([&] {
    v1::SubscribeResponse response;
    while (reader->Read(&response)) ++received;
  });
  // The rate reaches the simulator with the broker's interest (a round
  // trip); by the third sample (400 ms on) it has.
  ASSERT_TRUE(eventuallyTrue([&] { return received.load() >= 3; }));
  const auto start = std::chrono::steady_clock::now();
  const uint64_t before = publishedCount(*data_, imu);
  std::this_thread::sleep_for(milliseconds(1500));
  const uint64_t published = publishedCount(*data_, imu) - before;
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  // At most one sample every 200 ms (and one that was held at the start).
  EXPECT_LE(static_cast<double>(published), elapsed_s * 5 + 2) << "published " << published;
  // Someone who wants every sample gets every sample (1 s at 10x: 2000;
  // the bound leaves room for a loaded machine).
  EXPECT_GT(samplesWithin(*data_, imu, milliseconds(1000)), 200);
  context.TryCancel();
  reading.join();
  reader->Finish();
}

TEST_F(SimulatorServiceTest, ClockTopicCarriesThePaceLineNotEveryTick) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + seconds(2));
  v1::SubscribeRequest request;
  request.set_topic("clock");
  request.set_mode(v1::DELIVERY_MODE_QUEUE);
  request.set_queue_size(10000);
  auto reader = data_->Subscribe(&context, request);
  v1::SubscribeResponse response;
  int samples = 0;
  v1::Clock last;
  while (reader->Read(&response)) {
    ++samples;
    ASSERT_TRUE(response.sample().UnpackTo(&last));
  }
  // 2 s of wall time at 10x: a sample per 5 ms of simulated time would be
  // 4000; the line comes once a wall second, and at most 50 times a second
  // when the physics slips behind it.
  EXPECT_GE(samples, 1);
  EXPECT_LT(samples, 120);
  EXPECT_DOUBLE_EQ(last.time_scale(), 10.0);
  EXPECT_TRUE(last.has_wall_time());
  EXPECT_NE(last.epoch(), 0u);
}

TEST_F(SimulatorServiceTest, ResetLoadsWorldsAndReportsBadWorldFiles) {
  // The simulator's first clock sample may still be on its way.
  std::optional<v1::Clock> epoch_before;
  for (int attempt = 0; attempt < 250 && !epoch_before; ++attempt) {
    epoch_before = latestClock(*data_);
    if (!epoch_before) std::this_thread::sleep_for(milliseconds(20));
  }
  ASSERT_TRUE(epoch_before);
  std::this_thread::sleep_for(milliseconds(300));  // about 3 s of simulated time
  const double before_reset = clockSeconds(*data_);
  ASSERT_GT(before_reset, 1.0);
  v1::ResetRequest reset;
  reset.set_world("rooms");
  v1::ResetResponse response;
  auto status = sim_->Reset(deadline().get(), reset, &response);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(std::vector<std::string>(response.robot_ids().begin(), response.robot_ids().end()),
            (std::vector<std::string>{"drone1", "drone2"}));
  EXPECT_LT(TimeUtil::TimestampToMilliseconds(response.time()), 100) << "time restarts";
  bool restarted = false;  // the clock topic follows at once, not after catching up
  for (int attempt = 0; attempt < 50 && !restarted; ++attempt) {
    const double now = clockSeconds(*data_);
    restarted = now >= 0 && now < before_reset / 2;
    if (!restarted) std::this_thread::sleep_for(milliseconds(2));
  }
  EXPECT_TRUE(restarted);
  const auto after = latestClock(*data_);
  ASSERT_TRUE(after);
  EXPECT_NE(after->epoch(), epoch_before->epoch()) << "time restarted: a new epoch";
  // drone1 starts where the world file puts it.
  std::this_thread::sleep_for(milliseconds(100));
  bool at_start = false;
  for (int attempt = 0; attempt < 50 && !at_start; ++attempt) {
    const auto p = pose();
    at_start = std::abs(p.pose().position_m().x() - 2.0) < 0.01 &&
               std::abs(p.pose().position_m().y() - 2.0) < 0.01;
    if (!at_start) std::this_thread::sleep_for(milliseconds(20));
  }
  EXPECT_TRUE(at_start);

  const std::string bad = ::testing::TempDir() + "/bad_world.yaml";
  {
    std::ofstream out(bad);
    out << "name: bad\nboxes:\n  - name: crate\n    center_m: [0, 0, 1]\n    size_m: [1, -1, 1]\n";
  }
  // A request names worlds inside --worlds-dir only (a bad world's file and
  // line are world_file_test's): a file elsewhere, a way out through "..",
  // and a device are refused naming the directory, before anything is read.
  for (const std::string& outside :
       {bad, std::string("../worlds/rooms.yaml"), std::string("/dev/zero")}) {
    reset.set_world(outside);
    status = sim_->Reset(deadline().get(), reset, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::PERMISSION_DENIED) << outside;
    EXPECT_NE(status.error_message().find("worlds must be inside"), std::string::npos)
        << status.error_message();
  }
  reset.set_world("no_such_world");
  EXPECT_EQ(sim_->Reset(deadline().get(), reset, &response).error_code(),
            grpc::StatusCode::NOT_FOUND);
  // A failed reset leaves the running world alone.
  v1::WatchFlightStateRequest watch;
  watch.set_robot_id("drone2");
  auto context = deadline(seconds(5));
  auto reader = flight_->WatchFlightState(context.get(), watch);
  v1::WatchFlightStateResponse message;
  EXPECT_TRUE(reader->Read(&message));
  context->TryCancel();
  reader->Finish();
}

TEST_F(SimulatorServiceTest, SigtermEndsStreamsAndExitsZero) {
  auto context = deadline(seconds(20));
  v1::WatchFlightStateRequest request;
  request.set_robot_id("drone2");
  auto reader = flight_->WatchFlightState(context.get(), request);
  v1::WatchFlightStateResponse message;
  ASSERT_TRUE(reader->Read(&message));
  EXPECT_EQ(message.status().state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_EQ(simulator_->terminate(), 0);
  while (reader->Read(&message)) {
  }
  EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::UNAVAILABLE);
}

// One FollowTime stream as a behavior system runs it: joins, then reports
// every grant (busy), and records the topics each grant names. The awaited
// topics it says in its join (when `awaited` is set), and `change_to` in its
// report of grant `change_at`.
struct GrantLog {
  std::vector<std::set<std::string>> named;  // per grant, the topics named
  std::vector<bool> has_seq;                 // per grant, some number > 0
  int changed_at = -1;                       // the grant whose report changed them
};

GrantLog followGrants(v1::Simulator::Stub& sim, const std::string& participant, int grants,
                      std::optional<std::vector<std::string>> awaited,
                      std::optional<std::vector<std::string>> change_to = std::nullopt,
                      int change_at = -1) {
  GrantLog log;
  auto context = deadline(seconds(60));
  auto stream = sim.FollowTime(context.get());
  v1::FollowTimeRequest join;
  join.set_participant(participant);
  join.set_robot_id("drone1");
  if (awaited) {
    join.mutable_awaited_topics()->mutable_topics()->Add(awaited->begin(), awaited->end());
  }
  if (!stream->Write(join)) return log;
  v1::FollowTimeResponse grant;
  for (int i = 0; i < grants && stream->Read(&grant); ++i) {
    std::set<std::string> named;
    bool any = false;
    for (const auto& [topic, seq] : grant.topic_seqs()) {
      named.insert(topic);
      any = any || seq > 0;
    }
    log.named.push_back(std::move(named));
    log.has_seq.push_back(any);
    v1::FollowTimeRequest report;
    *report.mutable_caught_up_to() = grant.clock().time();
    report.set_idle(false);
    if (change_to && i == change_at) {
      report.mutable_awaited_topics()->mutable_topics()->Add(change_to->begin(), change_to->end());
      log.changed_at = i;
    }
    if (!stream->Write(report)) break;
  }
  stream->WritesDone();
  context->TryCancel();
  stream->Finish();
  return log;
}

// A grant names only the topics its follower's data barrier awaits, as the
// follower said in its join and again when they changed; a follower that
// said nothing (an older one) is named every topic. Without this, every
// grant to each of N vehicles' systems named every vehicle's topics: N^2
// numbers copied and sent each quantum, half the simulator's CPU with 20
// vehicles.
TEST(SimulatorDeterministicTest, AGrantNamesTheTopicsItsFollowerAwaits) {
  support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  support::ServerProcess simulator(
      BEHAVIORLIB_SIMULATOR_PATH,
      {"--channel", broker.address(), "--vehicles", "drone1,drone2", "--time-scale", "max",
       "--min-followers", "2", "--follower-timeout-s", "600"});
  ASSERT_TRUE(simulator.start()) << simulator.error();
  auto data = v1::DataChannel::NewStub(
      grpc::CreateChannel(broker.address(), grpc::InsecureChannelCredentials()));
  auto sim = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials()));
  const std::string pose1 = "robots/drone1/ground_truth/pose";
  const std::string pose2 = "robots/drone2/ground_truth/pose";
  // Subscribers, so that the simulator publishes both vehicles' poses.
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::SubscribeResponse>>> readers;
  for (const auto& topic : {pose1, pose2}) {
    contexts.push_back(deadline(seconds(60)));
    v1::SubscribeRequest request;
    request.set_topic(topic);
    request.set_mode(v1::DELIVERY_MODE_LATEST);
    readers.push_back(data->Subscribe(contexts.back().get(), request));
  }

  constexpr int kGrants = 120;
  constexpr int kChangeAt = 60;
  GrantLog all;
  std::thread older([&] { all = followGrants(*sim, "test/older", kGrants, std::nullopt); });
  const GrantLog awaiting =
      followGrants(*sim, "test/awaiting", kGrants, std::vector<std::string>{pose1},
                   std::vector<std::string>{pose2}, kChangeAt);
  older.join();
  for (auto& context : contexts) context->TryCancel();
  for (auto& reader : readers) reader->Finish();

  ASSERT_EQ(awaiting.named.size(), static_cast<size_t>(kGrants));
  ASSERT_GE(all.named.size(), static_cast<size_t>(kChangeAt));
  // Before the change: drone1's pose only, and numbered once it flowed.
  int numbered = 0;
  for (int i = 0; i < kChangeAt; ++i) {
    for (const auto& topic : awaiting.named[i]) EXPECT_EQ(topic, pose1) << "grant " << i;
    numbered += awaiting.has_seq[i] ? 1 : 0;
  }
  EXPECT_GT(numbered, 0) << "no grant named drone1's pose with a number";
  // The grant after the changing report may have been decided before it
  // arrived; from the one after, drone2's pose only.
  int numbered_after = 0;
  for (int i = kChangeAt + 2; i < kGrants; ++i) {
    for (const auto& topic : awaiting.named[i]) EXPECT_EQ(topic, pose2) << "grant " << i;
    numbered_after += awaiting.named[i].count(pose2);
  }
  EXPECT_GT(numbered_after, 0) << "no grant named drone2's pose after the change";
  // The follower that said nothing is named both vehicles' poses.
  bool both = false;
  for (const auto& named : all.named) both = both || (named.count(pose1) && named.count(pose2));
  EXPECT_TRUE(both) << "the older follower was not named every topic";
}

// Setpoints travel on StreamSetpoints calls of their own, read by other
// threads of the simulator than the follower's reports. A report names how
// many setpoints its follower wrote on each stream (the key in the stream's
// metadata), and the simulator does not step on until it has read them all,
// or their stream ended: a setpoint written before a report is applied in
// the quantum it was meant for (before, about 15 a flight were applied a
// quantum late in the demo). A stream that never comes holds the step for a
// bounded wall time only.
TEST(SimulatorDeterministicTest, AReportedSetpointIsReadBeforeTheNextStep) {
  support::ServerProcess simulator(
      BEHAVIORLIB_SIMULATOR_PATH,
      {"--time-scale", "max", "--min-followers", "1", "--follower-timeout-s", "600"});
  ASSERT_TRUE(simulator.start()) << simulator.error();
  auto channel = grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials());
  auto sim = v1::Simulator::NewStub(channel);
  auto platform = v1::FlightController::NewStub(channel);

  auto context = deadline(seconds(60));
  auto stream = sim->FollowTime(context.get());
  v1::FollowTimeRequest join;
  join.set_participant("test/setpoints");
  join.set_robot_id("drone1");
  ASSERT_TRUE(stream->Write(join));
  const auto report = [&stream](const v1::FollowTimeResponse& grant,
                                std::map<std::string, uint64_t> written) {
    v1::FollowTimeRequest request;
    *request.mutable_caught_up_to() = grant.clock().time();
    request.set_idle(false);
    request.mutable_setpoints_written()->insert(written.begin(), written.end());
    return stream->Write(request);
  };
  const auto nanos = [](const v1::FollowTimeResponse& grant) {
    return TimeUtil::TimestampToNanoseconds(grant.clock().time());
  };
  v1::FollowTimeResponse first;
  ASSERT_TRUE(stream->Read(&first));
  ASSERT_TRUE(report(first, {{"test-stream-1", 1}}));

  // The next grant waits for the setpoint.
  std::atomic<bool> granted{false};
  v1::FollowTimeResponse second;
  std::thread reader([&] { granted = stream->Read(&second); });
  std::this_thread::sleep_for(milliseconds(500));
  EXPECT_FALSE(granted.load()) << "the simulator stepped before the reported setpoint arrived";
  {
    // The setpoint: refused (no lease), which counts as read, and ends the stream.
    grpc::ClientContext setpoints_context;
    setpoints_context.AddMetadata("behaviorlib-setpoint-stream", "test-stream-1");
    v1::StreamSetpointsResponse accepted;
    auto writer = platform->StreamSetpoints(&setpoints_context, &accepted);
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id("drone1");
    setpoint.set_lease_id("no-such-lease");
    setpoint.mutable_position_yaw()->mutable_position_m()->set_z(1.0);
    writer->Write(setpoint);
    writer->WritesDone();
    EXPECT_FALSE(writer->Finish().ok()) << "a setpoint without a lease was accepted";
  }
  reader.join();
  ASSERT_TRUE(granted.load());
  EXPECT_EQ(nanos(second) - nanos(first), 10'000'000) << "one quantum, and only one";

  // A stream that ended is not waited for, whatever its report says.
  ASSERT_TRUE(report(second, {{"test-stream-1", 3}}));
  v1::FollowTimeResponse third;
  ASSERT_TRUE(stream->Read(&third));
  EXPECT_EQ(nanos(third) - nanos(second), 10'000'000);

  // A stream that never comes holds the step for the bounded wait (2 s).
  const auto before = std::chrono::steady_clock::now();
  ASSERT_TRUE(report(third, {{"never-opened", 1}}));
  v1::FollowTimeResponse fourth;
  ASSERT_TRUE(stream->Read(&fourth));
  EXPECT_GE(std::chrono::steady_clock::now() - before, milliseconds(1900));
  EXPECT_EQ(nanos(fourth) - nanos(third), 10'000'000);

  stream->WritesDone();
  context->TryCancel();
  stream->Finish();
  EXPECT_EQ(simulator.terminate(), 0);
}

// The deterministic mode (--time-scale max): time starts once the follower
// joined, advances only as fast as it reports back while a behavior is
// active, stands while it is frozen then (SIGSTOP: a starved process slows
// the simulation instead of missing its deadlines), goes on without it while
// it is idle, an activation of the idle system starts at the simulation's
// time, and a WAIT runs exactly its simulated duration.
TEST(SimulatorDeterministicTest, TimeAdvancesOnlyAsFastAsItsFollowerKeepsUp) {
  support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  support::ServerProcess simulator(BEHAVIORLIB_SIMULATOR_PATH,
                                   {"--channel", broker.address(), "--time-scale", "max",
                                    "--min-followers", "1", "--follower-timeout-s", "600"});
  ASSERT_TRUE(simulator.start()) << simulator.error();
  auto data = v1::DataChannel::NewStub(
      grpc::CreateChannel(broker.address(), grpc::InsecureChannelCredentials()));
  auto sim = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials()));

  // No follower yet: time has not started.
  std::this_thread::sleep_for(milliseconds(300));
  EXPECT_LE(clockSeconds(*data), 0.0);
  // Step and SetTimeScale are refused: the simulator steps itself.
  v1::StepRequest step;
  step.mutable_duration()->set_seconds(1);
  v1::StepResponse stepped;
  const grpc::Status refused = sim->Step(deadline().get(), step, &stepped);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  const auto info = behaviorlib::errors::errorInfo(refused);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->reason(), "FEATURE_NOT_ENABLED");
  EXPECT_EQ(info->metadata().at("feature"), "wall_clock_mode");

  support::ServerProcess system(
      BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH,
      {"--channel", broker.address(), "--clock", "sim", "--follow-time", simulator.address()});
  ASSERT_TRUE(system.start()) << system.error();
  double t = -1;
  for (int attempt = 0; attempt < 200 && t < 1.0; ++attempt) {
    std::this_thread::sleep_for(milliseconds(20));
    t = clockSeconds(*data);
  }
  ASSERT_GE(t, 1.0) << "time did not advance with a follower";

  // An idle follower (no behavior active) is not waited for: frozen, time
  // goes on.
  ASSERT_TRUE(system.freeze()) << system.error();
  const double idle_frozen = clockSeconds(*data);
  std::this_thread::sleep_for(milliseconds(700));
  const double before_activation = clockSeconds(*data);
  EXPECT_GE(before_activation - idle_frozen, 0.5) << "time waited for an idle follower";

  // Its clock now lags the simulation by the time it was frozen. An
  // activation sent while it is frozen, read the moment it thaws, waits for a
  // grant sent after the system said it is busy: it starts at the
  // simulation's time, not at the follower's stale one (which the next grant
  // would have jumped forward under the new activation, by 0.7 s here).
  auto stub = v1::BehaviorSystem::NewStub(
      grpc::CreateChannel(system.address(), grpc::InsecureChannelCredentials()));
  v1::ActivateBehaviorRequest activate;
  activate.set_behavior("WAIT");
  (*activate.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(3600);
  v1::ActivateResponse activated;
  grpc::Status activate_status;
  std::thread activation(
      [&] { activate_status = stub->ActivateBehavior(deadline().get(), activate, &activated); });
  std::this_thread::sleep_for(milliseconds(100));  // the request waits in the socket
  ASSERT_EQ(::kill(system.pid(), SIGCONT), 0);
  activation.join();
  ASSERT_TRUE(activate_status.ok()) << activate_status.error_message();
  EXPECT_GE(TimeUtil::TimestampToNanoseconds(activated.activation_time()) / 1e9, before_activation)
      << "the activation ran at a time the simulation had already passed";

  // A busy one (a long WAIT active) frozen: time stands, within the grant in
  // flight and the clock topic's 50 ms.
  std::this_thread::sleep_for(milliseconds(200));
  ASSERT_TRUE(system.freeze()) << system.error();
  std::this_thread::sleep_for(milliseconds(200));
  const double frozen = clockSeconds(*data);
  std::this_thread::sleep_for(milliseconds(700));
  EXPECT_LE(clockSeconds(*data) - frozen, 0.051) << "time went on without the busy follower";
  ASSERT_EQ(::kill(system.pid(), SIGCONT), 0);
  v1::DeactivateBehaviorRequest deactivate;
  deactivate.set_behavior("WAIT");
  v1::DeactivateResponse deactivated;
  ASSERT_TRUE(stub->DeactivateBehavior(deadline().get(), deactivate, &deactivated).ok());

  // A WAIT of 2 s runs 2 s of simulated time, however long in wall time.
  std::string error;
  const auto finished = runWait(system.address(), 2.0, &error);
  ASSERT_TRUE(finished) << error;
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  const double active_s =
      TimeUtil::DurationToNanoseconds(finished->finished().active_duration()) / 1e9;
  EXPECT_GE(active_s, 2.0);
  EXPECT_LE(active_s, 2.0 + 0.011) << "one quantum at most past its end";
  EXPECT_EQ(system.terminate(), 0);
  EXPECT_EQ(simulator.terminate(), 0);
  EXPECT_EQ(broker.terminate(), 0);
}

}  // namespace
