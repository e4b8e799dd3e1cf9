// The coordinator built in-process (coordinator/process): the same wiring as
// the binary, served on a free loopback port and driven over real gRPC, with
// no process to start. Belief memory survives a restart through the journal;
// shutdown ends an event stream UNAVAILABLE with its resume point; a state
// directory that cannot be used is refused, naming it.

#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/process/coordinator_process.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::HasSubstr;

class TempDir {
 public:
  TempDir() {
    char pattern[] = "/tmp/behaviorlib-coordinator-XXXXXX";
    path_ = mkdtemp(pattern);
  }
  ~TempDir() { std::filesystem::remove_all(path_); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

CoordinatorOptions loopbackOptions(const std::string& state_dir) {
  CoordinatorOptions options;
  options.listen = "127.0.0.1:0";
  options.metrics_listen = "";
  options.state_dir = state_dir;
  return options;
}

std::unique_ptr<v1::Coordinator::Stub> connect(const Coordinator& coordinator) {
  return v1::Coordinator::NewStub(grpc::CreateChannel(
      "127.0.0.1:" + std::to_string(coordinator.grpcPort()), grpc::InsecureChannelCredentials()));
}

grpc::Status writeBelief(v1::Coordinator::Stub& stub, const std::string& key, double value) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WriteBeliefRequest request;
  request.set_key(key);
  request.mutable_value()->set_number_value(value);
  request.set_writer("test");
  v1::WriteBeliefResponse response;
  return stub.WriteBelief(&context, request, &response);
}

grpc::Status readBelief(v1::Coordinator::Stub& stub, const std::string& key, v1::Belief* out) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::ReadBeliefRequest request;
  request.set_key(key);
  v1::ReadBeliefResponse response;
  grpc::Status status = stub.ReadBelief(&context, request, &response);
  *out = response.belief();
  return status;
}

TEST(CoordinatorInProcessTest, BeliefsSurviveARestartThroughTheJournal) {
  TempDir state;
  std::string first_incarnation;
  {
    auto coordinator = Coordinator::start(loopbackOptions(state.path()));
    ASSERT_TRUE(coordinator.ok()) << coordinator.status();
    first_incarnation = (*coordinator)->incarnation();
    auto stub = connect(**coordinator);
    ASSERT_TRUE(writeBelief(*stub, "drone1/altitude_m", 1.5).ok());
  }  // the destructor shuts it down
  auto coordinator = Coordinator::start(loopbackOptions(state.path()));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  EXPECT_NE((*coordinator)->incarnation(), first_incarnation);
  auto stub = connect(**coordinator);
  v1::Belief belief;
  ASSERT_TRUE(readBelief(*stub, "drone1/altitude_m", &belief).ok());
  EXPECT_DOUBLE_EQ(belief.value().number_value(), 1.5);
  EXPECT_EQ(belief.writer(), "test");
}

TEST(CoordinatorInProcessTest, ShutdownEndsAnEventStreamWithItsResumePoint) {
  auto coordinator = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  auto stub = connect(**coordinator);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WatchFleetEventsRequest request;
  auto reader = stub->WatchEvents(&context, request);
  v1::WatchFleetEventsResponse start;
  ASSERT_TRUE(reader->Read(&start));
  ASSERT_TRUE(start.has_start());
  EXPECT_EQ(start.start().incarnation(), (*coordinator)->incarnation());

  (*coordinator)->shutdown();
  v1::WatchFleetEventsResponse more;
  while (reader->Read(&more)) {
  }
  const grpc::Status status = reader->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(status.error_message(), HasSubstr("the coordinator is shutting down"));
  EXPECT_THAT(status.error_message(),
              HasSubstr("resume with since_seq=0 and incarnation=" + start.start().incarnation()));
}

TEST(CoordinatorInProcessTest, AStateDirectoryThatIsAFileIsRefusedNamingIt) {
  TempDir state;
  const std::string file = state.path() + "/not-a-directory";
  std::ofstream(file) << "x";
  auto coordinator = Coordinator::start(loopbackOptions(file));
  ASSERT_FALSE(coordinator.ok());
  EXPECT_EQ(coordinator.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(coordinator.status().message()), HasSubstr("--state-dir"));
}

TEST(CoordinatorInProcessTest, AnAddressInUseIsRefused) {
  auto first = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(first.ok()) << first.status();
  CoordinatorOptions options = loopbackOptions("");
  options.listen = "127.0.0.1:" + std::to_string((*first)->grpcPort());
  auto second = Coordinator::start(std::move(options));
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.status().code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace behaviorlib::coordinator
