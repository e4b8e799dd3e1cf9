// swarm_interaction with two vehicles: the channel broker, the simulator
// (drone1 and drone2, 5x, fixed seed), basic_quadrotor_behaviors and
// swarm_interaction for each robot, and the coordinator's belief memory.
// Each vehicle learns where the other one is (its beliefs match the
// simulator's ground truth), an estimate looser than INFORM_POSITION_TO_ROBOTS'
// bound is not shared, a message of INFORM_ROBOTS reaches the robot it
// is for and no other, a malformed message is counted and skipped, and a
// silent swarm ends PAY_ATTENTION_TO_ROBOT_MESSAGES with PROCESS_FAILURE.

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Core>
#include <chrono>
#include <filesystem>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "motion_test_support.h"
#include "support/deterministic.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using motion_test::deadline;
using motion_test::FlightStack;
using motion_test::SystemClient;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr char kDrone1[] = "drone1";
constexpr char kDrone2[] = "drone2";
/// How far a position in belief memory may be from the ground truth: the
/// vehicles hover; the belief is at most a few publications old.
constexpr double kPositionBoundM = 0.3;

double number(const google::protobuf::Value& v, const std::string& name) {
  const auto& fields = v.struct_value().fields();
  return fields.contains(name) ? fields.at(name).number_value() : 0.0;  // JSON omits zeros
}

const google::protobuf::Value& field(const google::protobuf::Value& v, const std::string& name) {
  static const google::protobuf::Value kNone;
  const auto& fields = v.struct_value().fields();
  return fields.contains(name) ? fields.at(name) : kNone;
}

class SwarmInteractionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/swarm_interaction_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    state_dir_ = dir;
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs(
            {"--channel", broker_.address(), "--vehicles", std::string(kDrone1) + "," + kDrone2,
             "--seed", motion_test::kSeed},
            1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    coordinator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_COORDINATOR_PATH, std::vector<std::string>{"--state-dir", state_dir_});
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    beliefs_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
    channel_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
    for (const char* robot : {kDrone1, kDrone2}) {
      Robot& r = robots_[robot];
      r.basic = startSystem(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, robot,
                            {"--flight-controller", simulator_->address(), "--config",
                             BEHAVIORLIB_BASIC_CONFIG_PATH});
      r.swarm = startSystem(BEHAVIORLIB_SWARM_INTERACTION_PATH, robot,
                            {"--coordinator", coordinator_->address()});
      ASSERT_TRUE(r.basic && r.swarm);
      r.basic_client = std::make_unique<SystemClient>(r.basic->address());
      r.swarm_client = std::make_unique<SystemClient>(r.swarm->address());
    }
  }
  void TearDown() override {
    for (auto& [name, r] : robots_) {
      r.basic_client.reset();
      r.swarm_client.reset();
      if (r.swarm) {
        EXPECT_EQ(r.swarm->terminate(), 0) << name << ": swarm_interaction exit";
      }
      if (r.basic && r.basic->running()) r.basic->kill();
    }
    channel_.reset();
    coordinator_.reset();
    std::filesystem::remove_all(state_dir_);
  }

  std::unique_ptr<support::ServerProcess> startSystem(const std::string& binary,
                                                      const std::string& robot,
                                                      std::vector<std::string> extra) {
    std::vector<std::string> args = support::followTimeArgs(
        {"--robot-id", robot, "--channel", broker_.address(), "--clock", "sim"},
        simulator_->address());
    args.insert(args.end(), extra.begin(), extra.end());
    auto process = std::make_unique<support::ServerProcess>(binary, args);
    if (!process->start()) {
      ADD_FAILURE() << binary << " (" << robot << "): " << process->error();
      return nullptr;
    }
    return process;
  }

  std::optional<v1::Belief> read(const std::string& key) {
    v1::ReadBeliefRequest request;
    request.set_key(key);
    v1::ReadBeliefResponse response;
    if (!beliefs_->ReadBelief(deadline().get(), request, &response).ok()) return std::nullopt;
    return response.belief();
  }

  std::optional<Eigen::Vector3d> truth(const std::string& robot) {
    auto latest = channel_->getLatest("robots/" + robot + "/ground_truth/pose");
    v1::PoseStamped pose;
    if (!latest.ok() || !latest->sample().UnpackTo(&pose)) return std::nullopt;
    const auto& p = pose.pose().position_m();
    return Eigen::Vector3d(p.x(), p.y(), p.z());
  }

  std::optional<Eigen::Vector3d> believedPosition(const std::string& robot,
                                                  const std::string& other) {
    auto belief = read(robot + "/swarm/" + other + "/position");
    if (!belief) return std::nullopt;
    const auto& p = field(field(belief->value(), "pose"), "position_m");
    return Eigen::Vector3d(number(p, "x"), number(p, "y"), number(p, "z"));
  }

  // Publishes `robot`'s pose estimate as an estimator would: at its ground
  // truth, stamped with the ground truth's (simulated) stamp, stating
  // `stddev_m` of horizontal standard deviation. False when there is no
  // ground truth yet.
  bool publishEstimate(const std::string& robot, double stddev_m) {
    auto latest = channel_->getLatest("robots/" + robot + "/ground_truth/pose");
    v1::PoseStamped pose;
    if (!latest.ok() || !latest->sample().UnpackTo(&pose)) return false;
    pose.set_horizontal_stddev_m(stddev_m);
    return channel_->publish("robots/" + robot + "/self_localization/pose", pose).ok() &&
           channel_->flush().ok();
  }

  // Localizes `robot` on the ground truth and takes it off to `altitude_m`.
  void takeOff(const std::string& robot, double altitude_m) {
    SystemClient& basic = *robots_[robot].basic_client;
    ASSERT_FALSE(basic.start("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}").empty());
    ASSERT_TRUE(FlightStack::waitFor([&] { return basic.checkSituation("TAKE_OFF").feasible(); },
                                     seconds(10)))
        << basic.checkSituation("TAKE_OFF").ShortDebugString();
    const std::string id =
        basic.start("TAKE_OFF", "{\"altitude_m\": " + std::to_string(altitude_m) + "}");
    ASSERT_FALSE(id.empty());
    const auto finished = basic.finished(id, seconds(30));
    ASSERT_TRUE(finished) << robot << ": TAKE_OFF did not finish";
    ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << finished->ShortDebugString();
  }

  struct Robot {
    std::unique_ptr<support::ServerProcess> basic, swarm;
    std::unique_ptr<SystemClient> basic_client, swarm_client;
  };

  std::string state_dir_;
  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_, coordinator_;
  std::unique_ptr<v1::Coordinator::Stub> beliefs_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> channel_;
  std::map<std::string, Robot> robots_;
};

TEST_F(SwarmInteractionTest, EachVehicleLearnsTheOthersPositionAndMessagesReachTheirRobot) {
  ASSERT_NO_FATAL_FAILURE(takeOff(kDrone1, 1.0));
  ASSERT_NO_FATAL_FAILURE(takeOff(kDrone2, 1.5));

  std::map<std::string, std::string> attention;
  for (const char* robot : {kDrone1, kDrone2}) {
    SystemClient& swarm = *robots_[robot].swarm_client;
    attention[robot] = swarm.start("PAY_ATTENTION_TO_ROBOT_MESSAGES", R"({"max_silence_s": 3})");
    ASSERT_FALSE(attention[robot].empty());
    ASSERT_FALSE(swarm.start("INFORM_POSITION_TO_ROBOTS", R"({"rate_hz": 5})").empty());
  }

  // Each vehicle's belief about the other matches the simulator.
  for (const auto& [robot, other] : {std::pair{kDrone1, kDrone2}, std::pair{kDrone2, kDrone1}}) {
    double error_m = -1;
    const bool close = FlightStack::waitFor(
        [&] {
          const auto believed = believedPosition(robot, other);
          const auto actual = truth(other);
          if (!believed || !actual) return false;
          error_m = (*believed - *actual).norm();
          return error_m <= kPositionBoundM;
        },
        seconds(20));
    EXPECT_TRUE(close) << robot << " about " << other << ": error " << error_m << " m";
  }
  // drone2 is 2 m east of drone1 and 0.5 m higher.
  const auto d2 = believedPosition(kDrone1, kDrone2);
  ASSERT_TRUE(d2);
  EXPECT_NEAR(d2->x(), 2.0, kPositionBoundM);
  EXPECT_NEAR(d2->z(), 1.5, kPositionBoundM);
  EXPECT_FALSE(read(std::string(kDrone1) + "/swarm/" + kDrone1 + "/position"))
      << "a robot must not record itself";

  // A message for drone2 only.
  const std::string inform = robots_[kDrone1].swarm_client->start(
      "INFORM_ROBOTS",
      R"({"robot_ids": ["drone2"], "text": "hello drone2", "payload_json": "{\"room\": 3}"})");
  ASSERT_FALSE(inform.empty());
  const auto sent = robots_[kDrone1].swarm_client->finished(inform, seconds(10));
  ASSERT_TRUE(sent);
  EXPECT_EQ(sent->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << sent->ShortDebugString();
  std::optional<v1::Belief> received;
  ASSERT_TRUE(FlightStack::waitFor(
      [&] { return (received = read(std::string(kDrone2) + "/swarm/messages/1")).has_value(); },
      seconds(10)))
      << "the message did not reach drone2's belief memory";
  EXPECT_EQ(field(received->value(), "from").string_value(), kDrone1);
  EXPECT_EQ(field(received->value(), "text").string_value(), "hello drone2");
  EXPECT_EQ(number(field(received->value(), "payload"), "room"), 3.0);
  // The count is written after the message.
  EXPECT_TRUE(FlightStack::waitFor([&] {
    auto count = read(std::string(kDrone2) + "/swarm/message_count");
    return count && count->value().number_value() == 1.0;
  })) << "drone2's swarm/message_count is not 1";
  EXPECT_FALSE(read(std::string(kDrone1) + "/swarm/messages/1"))
      << "drone1 recorded a message not for it";

  // A malformed message (no sender) is counted and skipped; listening goes on.
  v1::SwarmMessage anonymous;
  anonymous.set_text("who am I?");
  ASSERT_TRUE(channel_->publish("robots/swarm/messages", anonymous).ok());
  ASSERT_TRUE(channel_->flush().ok());
  for (const char* robot : {kDrone1, kDrone2}) {
    EXPECT_TRUE(FlightStack::waitFor(
        [&] {
          const auto count = read(std::string(robot) + "/swarm/malformed_count");
          return count && count->value().number_value() >= 1.0;
        },
        seconds(10)))
        << robot << " did not count the malformed message";
  }
  EXPECT_FALSE(read(std::string(kDrone2) + "/swarm/messages/2"));
  for (const char* robot : {kDrone1, kDrone2}) {
    EXPECT_FALSE(robots_[robot].swarm_client->finished(attention[robot], milliseconds(0)))
        << robot << ": PAY_ATTENTION_TO_ROBOT_MESSAGES ended";
  }

  // drone2 falls silent: drone1's channel is stale after max_silence_s.
  ASSERT_TRUE(robots_[kDrone2].swarm_client->deactivate("INFORM_POSITION_TO_ROBOTS").ok());
  const auto stale = robots_[kDrone1].swarm_client->finished(attention[kDrone1], seconds(20));
  ASSERT_TRUE(stale) << "drone1 did not notice the silence";
  EXPECT_EQ(stale->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << stale->ShortDebugString();
  EXPECT_NE(stale->finished().message().find("stale"), std::string::npos)
      << stale->finished().message();
}

TEST_F(SwarmInteractionTest, AnEstimateLooserThanTheBoundIsNotSharedUntilItTightens) {
  ASSERT_FALSE(
      robots_[kDrone2]
          .swarm_client->start("PAY_ATTENTION_TO_ROBOT_MESSAGES", R"({"max_silence_s": 60})")
          .empty());
  // drone1's estimator still converging: it states 1 m.
  ASSERT_TRUE(FlightStack::waitFor([&] { return publishEstimate(kDrone1, 1.0); }));
  ASSERT_FALSE(
      robots_[kDrone1]
          .swarm_client
          ->start("INFORM_POSITION_TO_ROBOTS", R"({"rate_hz": 10, "max_horizontal_stddev_m": 0.5})")
          .empty());
  const std::string key = std::string(kDrone2) + "/swarm/" + kDrone1 + "/position";
  // Two seconds of wall time at 10 Hz, every estimate stating 1 m: none is
  // shared.
  EXPECT_FALSE(FlightStack::waitFor(
      [&] {
        publishEstimate(kDrone1, 1.0);
        return read(key).has_value();
      },
      seconds(2)))
      << "an estimate stating 1 m was shared past the 0.5 m bound";
  // Tighter than the bound: shared, with what it states.
  std::optional<v1::Belief> belief;
  ASSERT_TRUE(FlightStack::waitFor(
      [&] {
        publishEstimate(kDrone1, 0.2);
        return (belief = read(key)).has_value();
      },
      seconds(10)))
      << "an estimate stating 0.2 m was not shared";
  EXPECT_DOUBLE_EQ(number(belief->value(), "horizontal_stddev_m"), 0.2)
      << belief->ShortDebugString();
}

TEST_F(SwarmInteractionTest, BadParametersAndMissingEstimatesAreRefusedWithAReason) {
  SystemClient& swarm = *robots_[kDrone1].swarm_client;
  v1::ActivateResponse response;
  grpc::Status status = swarm.activate("INFORM_ROBOTS", R"({"robot_ids": ["drone2"]})", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("text"), std::string::npos) << status.error_message();
  status = swarm.activate("INFORM_ROBOTS", R"({"text": "x", "payload_json": "{oops"})", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("payload_json"), std::string::npos);
  // No self-localization yet: nothing to inform about.
  const auto situation = swarm.checkSituation("INFORM_POSITION_TO_ROBOTS");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("self_localization/pose"), std::string::npos)
      << situation.ShortDebugString();
}

}  // namespace
