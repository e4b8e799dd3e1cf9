// operator_interaction against the real coordinator's belief memory:
// REQUEST_OPERATOR_ASSISTANCE answered through WriteBelief and through
// behaviorctl (GOAL_ACHIEVED, the answer copied where the mission reads it),
// unanswered (TIME_OUT, an answer to an earlier request does not count),
// refused without a coordinator; INFORM_OPERATOR leaves its message.

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>

#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "motion_test_support.h"
#include "support/run_command.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using motion_test::deadline;
using motion_test::describe;
using motion_test::FlightStack;
using motion_test::SystemClient;
using std::chrono::milliseconds;
using std::chrono::seconds;

using support::run;

class OperatorInteractionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/operator_interaction_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    state_dir_ = dir;
    coordinator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_COORDINATOR_PATH, std::vector<std::string>{"--state-dir", state_dir_});
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
    system_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_OPERATOR_INTERACTION_PATH,
        std::vector<std::string>{"--robot-id", "drone1", "--coordinator", coordinator_->address()});
    ASSERT_TRUE(system_->start()) << system_->error();
    client_ = std::make_unique<SystemClient>(system_->address());
  }
  void TearDown() override {
    client_.reset();
    if (system_) {
      EXPECT_EQ(system_->terminate(), 0);
    }
    coordinator_.reset();
    std::filesystem::remove_all(state_dir_);
  }

  grpc::Status write(const std::string& key, const google::protobuf::Value& value) {
    v1::WriteBeliefRequest request;
    request.set_key(key);
    *request.mutable_value() = value;
    request.set_writer("operator");
    v1::WriteBeliefResponse response;
    return stub_->WriteBelief(deadline().get(), request, &response);
  }
  std::optional<v1::Belief> read(const std::string& key) {
    v1::ReadBeliefRequest request;
    request.set_key(key);
    v1::ReadBeliefResponse response;
    if (!stub_->ReadBelief(deadline().get(), request, &response).ok()) return std::nullopt;
    return response.belief();
  }
  // The request's state field once it is `state` (bounded wait).
  bool requestInState(const std::string& request_id, const std::string& state) {
    return FlightStack::waitFor(
        [&] {
          auto belief = read("operator/requests/" + request_id);
          if (!belief) return false;
          const auto& fields = belief->value().struct_value().fields();
          return fields.contains("state") && fields.at("state").string_value() == state;
        },
        seconds(10));
  }
  static google::protobuf::Value text(const std::string& s) {
    google::protobuf::Value v;
    v.set_string_value(s);
    return v;
  }

  std::string state_dir_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::unique_ptr<support::ServerProcess> system_;
  std::unique_ptr<SystemClient> client_;
};

TEST_F(OperatorInteractionTest, AnAnswerWrittenThroughWriteBeliefAchievesTheGoal) {
  const std::string id =
      client_->start("REQUEST_OPERATOR_ASSISTANCE",
                     R"({"question": "Land in the yard?", "timeout_s": 60, "request_id": "q1",
          "answer_key": "drone1/landing_ok"})");
  ASSERT_FALSE(id.empty());
  ASSERT_TRUE(requestInState("q1", "open")) << "the question did not reach belief memory";
  const auto request = read("operator/requests/q1");
  const auto& fields = request->value().struct_value().fields();
  EXPECT_EQ(fields.at("question").string_value(), "Land in the yard?");
  EXPECT_EQ(fields.at("robot_id").string_value(), "drone1");
  EXPECT_EQ(fields.at("answer_key").string_value(), "drone1/landing_ok");

  ASSERT_TRUE(write("operator/answers/q1", text("yes")).ok());
  const auto finished = client_->finished(id, seconds(10));
  ASSERT_TRUE(finished) << "no finished event";
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("yes"), std::string::npos)
      << finished->finished().message();
  const auto copied = read("drone1/landing_ok");
  ASSERT_TRUE(copied) << "the answer was not copied to answer_key";
  EXPECT_EQ(copied->value().string_value(), "yes");
  EXPECT_EQ(copied->writer(), "drone1/REQUEST_OPERATOR_ASSISTANCE");
  EXPECT_TRUE(requestInState("q1", "answered"));
}

TEST_F(OperatorInteractionTest, AnAnswerSetWithBehaviorctlAchievesTheGoal) {
  const std::string id = client_->start("REQUEST_OPERATOR_ASSISTANCE",
                                        R"({"question": "Continue?", "request_id": "q2"})");
  ASSERT_FALSE(id.empty());
  ASSERT_TRUE(requestInState("q2", "open"));
  std::string output;
  const int code =
      run(std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " + coordinator_->address() +
              " belief set operator/answers/q2 '{\"continue\": false}'",
          &output);
  ASSERT_EQ(code, 0) << output;
  const auto finished = client_->finished(id, seconds(10));
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  // The default answer key.
  const auto copied = read("drone1/operator_answers/q2");
  ASSERT_TRUE(copied);
  EXPECT_FALSE(copied->value().struct_value().fields().at("continue").bool_value());
}

TEST_F(OperatorInteractionTest, WithoutAnAnswerItTimesOutAndAnOldAnswerDoesNotCount) {
  // An answer to an earlier question with the same id.
  ASSERT_TRUE(write("operator/answers/q3", text("stale")).ok());
  const std::string id =
      client_->start("REQUEST_OPERATOR_ASSISTANCE",
                     R"({"question": "Anyone there?", "timeout_s": 1.0, "request_id": "q3"})");
  ASSERT_FALSE(id.empty());
  const auto finished = client_->finished(id, seconds(10));
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT)
      << finished->ShortDebugString();
  EXPECT_TRUE(requestInState("q3", "timed_out"));
  EXPECT_FALSE(read("drone1/operator_answers/q3"));
}

TEST_F(OperatorInteractionTest, BadParametersAreRefusedNamingTheField) {
  v1::ActivateResponse response;
  grpc::Status status = client_->activate("REQUEST_OPERATOR_ASSISTANCE",
                                          R"({"question": "?", "request_id": "a/b"})", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("request_id"), std::string::npos) << describe(status);
  status = client_->activate("REQUEST_OPERATOR_ASSISTANCE", R"({"timeout_s": 5})", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("question"), std::string::npos) << describe(status);
}

TEST_F(OperatorInteractionTest, InformOperatorLeavesNumberedMessages) {
  for (const char* message : {"battery at 40 %", "starting the inspection"}) {
    const std::string id =
        client_->start("INFORM_OPERATOR", std::string(R"({"text": ")") + message + "\"}");
    ASSERT_FALSE(id.empty());
    const auto finished = client_->finished(id, seconds(10));
    ASSERT_TRUE(finished);
    EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << finished->ShortDebugString();
  }
  const auto first = read("operator/messages/drone1/1");
  const auto second = read("operator/messages/drone1/2");
  ASSERT_TRUE(first && second);
  EXPECT_EQ(first->value().struct_value().fields().at("text").string_value(), "battery at 40 %");
  EXPECT_EQ(second->value().struct_value().fields().at("text").string_value(),
            "starting the inspection");
}

TEST_F(OperatorInteractionTest, WithoutACoordinatorTheSituationIsRefused) {
  support::ServerProcess alone(BEHAVIORLIB_OPERATOR_INTERACTION_PATH, {"--robot-id", "drone1"});
  ASSERT_TRUE(alone.start()) << alone.error();
  SystemClient client(alone.address());
  const auto situation = client.checkSituation("REQUEST_OPERATOR_ASSISTANCE");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("--coordinator"), std::string::npos)
      << situation.ShortDebugString();
  v1::ActivateResponse response;
  const grpc::Status status =
      client.activate("REQUEST_OPERATOR_ASSISTANCE", R"({"question": "Anyone?"})", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(status);
  EXPECT_NE(status.error_message().find("--coordinator"), std::string::npos) << describe(status);
  EXPECT_EQ(alone.terminate(), 0);
}

}  // namespace
