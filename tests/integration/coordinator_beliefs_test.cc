// Belief memory served by the real coordinator process: write, read, list,
// delete, the errors a person gets, and the journal that keeps it across a
// crash (kill -9) of the coordinator.

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <thread>

#include "absl/strings/str_format.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/run_command.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;

std::unique_ptr<grpc::ClientContext> deadline() {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  return context;
}

class CoordinatorBeliefsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/coordinator_state_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    state_dir_ = dir;
    start();
  }
  void TearDown() override {
    coordinator_.reset();
    std::filesystem::remove_all(state_dir_);
  }
  void start(std::vector<std::string> extra = {}) {
    std::vector<std::string> args = {"--state-dir", state_dir_};
    args.insert(args.end(), extra.begin(), extra.end());
    coordinator_ = std::make_unique<support::ServerProcess>(BEHAVIORLIB_COORDINATOR_PATH, args);
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
  }
  grpc::Status write(const std::string& key, const std::string& text, v1::Belief* out = nullptr) {
    v1::WriteBeliefRequest request;
    request.set_key(key);
    request.mutable_value()->set_string_value(text);
    request.set_writer("operator");
    v1::WriteBeliefResponse response;
    grpc::Status status = stub_->WriteBelief(deadline().get(), request, &response);
    if (out) *out = response.belief();
    return status;
  }
  grpc::Status read(const std::string& key, v1::Belief* out) {
    v1::ReadBeliefRequest request;
    request.set_key(key);
    v1::ReadBeliefResponse response;
    grpc::Status status = stub_->ReadBelief(deadline().get(), request, &response);
    *out = response.belief();
    return status;
  }

  std::string state_dir_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

TEST_F(CoordinatorBeliefsTest, WritesReadsListsAndDeletes) {
  v1::Belief written;
  ASSERT_TRUE(write("drone1/answer", "yes", &written).ok());
  EXPECT_EQ(written.version(), 1u);
  EXPECT_EQ(written.writer(), "operator");
  ASSERT_TRUE(write("drone2/answer", "no").ok());
  v1::Belief belief;
  ASSERT_TRUE(read("drone1/answer", &belief).ok());
  EXPECT_EQ(belief.value().string_value(), "yes");

  v1::ListBeliefsRequest list;
  list.set_prefix("drone1/");
  v1::ListBeliefsResponse listed;
  ASSERT_TRUE(stub_->ListBeliefs(deadline().get(), list, &listed).ok());
  ASSERT_EQ(listed.beliefs_size(), 1);
  EXPECT_EQ(listed.beliefs(0).key(), "drone1/answer");

  v1::DeleteBeliefRequest erase;
  erase.set_key("drone1/answer");
  erase.set_writer("operator");
  v1::DeleteBeliefResponse erased;
  ASSERT_TRUE(stub_->DeleteBelief(deadline().get(), erase, &erased).ok());
  EXPECT_EQ(read("drone1/answer", &belief).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(stub_->DeleteBelief(deadline().get(), erase, &erased).error_code(),
            grpc::StatusCode::NOT_FOUND);
}

// `behaviorctl belief list` follows the pages: more beliefs than the
// server's default page (500) are printed as one reply, each key once, in
// order.
TEST_F(CoordinatorBeliefsTest, BehaviorctlListsEveryPage) {
  constexpr int kBeliefs = 1001;  // three pages of 500
  for (int i = 0; i < kBeliefs; ++i) {
    ASSERT_TRUE(write(absl::StrFormat("many/b%04d", i), "x").ok()) << i;
  }
  ASSERT_TRUE(write("other/b", "x").ok());
  std::string output;
  ASSERT_EQ(support::run(std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " +
                             coordinator_->address() + " belief list many/ -o json",
                         &output),
            0)
      << output.substr(0, 1000);
  v1::ListBeliefsResponse listed;
  ASSERT_TRUE(google::protobuf::util::JsonStringToMessage(output, &listed).ok())
      << output.substr(0, 1000);
  ASSERT_EQ(listed.beliefs_size(), kBeliefs);
  for (int i = 0; i < kBeliefs; ++i) {
    EXPECT_EQ(listed.beliefs(i).key(), absl::StrFormat("many/b%04d", i));
  }
  EXPECT_TRUE(listed.next_page_token().empty());
}

TEST_F(CoordinatorBeliefsTest, BadRequestsSayWhatIsWrong) {
  grpc::Status bad_key = write("drone 1/answer", "yes");
  EXPECT_EQ(bad_key.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(bad_key.error_message().find("has the character ' '"), std::string::npos)
      << bad_key.error_message();
  v1::WriteBeliefRequest anonymous;
  anonymous.set_key("k");
  v1::WriteBeliefResponse response;
  grpc::Status no_writer = stub_->WriteBelief(deadline().get(), anonymous, &response);
  EXPECT_EQ(no_writer.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(no_writer.error_message().find("writer"), std::string::npos);
  v1::Belief belief;
  grpc::Status missing = read("nowhere", &belief);
  EXPECT_EQ(missing.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_NE(missing.error_message().find("nowhere"), std::string::npos);
}

TEST_F(CoordinatorBeliefsTest, BeliefsSurviveACrashOfTheCoordinator) {
  ASSERT_TRUE(write("map_file", "/maps/building.bt").ok());
  ASSERT_TRUE(write("gone", "soon").ok());
  v1::DeleteBeliefRequest erase;
  erase.set_key("gone");
  erase.set_writer("operator");
  v1::DeleteBeliefResponse erased;
  ASSERT_TRUE(stub_->DeleteBelief(deadline().get(), erase, &erased).ok());
  coordinator_->kill();  // SIGKILL: no orderly shutdown
  start();
  v1::Belief belief;
  ASSERT_TRUE(read("map_file", &belief).ok());
  EXPECT_EQ(belief.value().string_value(), "/maps/building.bt");
  EXPECT_EQ(read("gone", &belief).error_code(), grpc::StatusCode::NOT_FOUND);
  // Versions go on from where they were.
  v1::Belief next;
  ASSERT_TRUE(write("after", "restart", &next).ok());
  EXPECT_EQ(next.version(), 4u);
}

// Past --journal-compact-bytes the journal is compacted while the
// coordinator runs; what it held survives a crash after that.
TEST_F(CoordinatorBeliefsTest, TheJournalIsCompactedOnlinePastItsThreshold) {
  coordinator_->kill();
  start({"--journal-compact-bytes", "4096"});
  const std::string journal = state_dir_ + "/coordinator.journal";
  const std::string padding(100, 'x');
  for (int i = 0; i < 300; ++i) {
    ASSERT_TRUE(write("drone1/counter", padding + std::to_string(i)).ok());
  }
  // About 40 kB appended; the compactor looks once a second.
  bool compacted = false;
  for (int i = 0; i < 100 && !compacted; ++i) {
    compacted = std::filesystem::file_size(journal) < 4096;
    if (!compacted) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(compacted) << std::filesystem::file_size(journal) << " bytes";
  ASSERT_TRUE(write("drone1/after", "compaction").ok());
  coordinator_->kill();
  start();
  v1::Belief belief;
  ASSERT_TRUE(read("drone1/counter", &belief).ok());
  EXPECT_EQ(belief.value().string_value(), padding + "299");
  ASSERT_TRUE(read("drone1/after", &belief).ok());
  EXPECT_EQ(belief.version(), 301u) << "versions go on";
}

TEST_F(CoordinatorBeliefsTest, BehaviorSystemsWriteTypedBeliefsThroughTheLibraryClient) {
  behaviorlib::server::BeliefClient client(coordinator_->address());
  v1::PoseStamped marker;
  marker.mutable_header()->set_frame_id("world");
  marker.mutable_pose()->mutable_position_m()->set_x(2.5);
  marker.mutable_pose()->mutable_position_m()->set_z(1.0);
  auto written =
      client.writeMessage("drone1/markers/QR_7", marker, "drone1/PAY_ATTENTION_TO_QR_CODES");
  ASSERT_TRUE(written.ok()) << written.status();
  EXPECT_EQ(written->type(), "behaviorlib.v1.PoseStamped");
  // Another reader sees the typed value with its fields.
  v1::Belief belief;
  ASSERT_TRUE(read("drone1/markers/QR_7", &belief).ok());
  EXPECT_EQ(belief.writer(), "drone1/PAY_ATTENTION_TO_QR_CODES");
  const auto& fields = belief.value().struct_value().fields();
  ASSERT_TRUE(fields.contains("pose"));
  EXPECT_DOUBLE_EQ(fields.at("pose")
                       .struct_value()
                       .fields()
                       .at("position_m")
                       .struct_value()
                       .fields()
                       .at("x")
                       .number_value(),
                   2.5);
  auto bad = client.write("", google::protobuf::Value(), "drone1/X");
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find(coordinator_->address()), std::string::npos);
  // A coordinator that is gone is UNAVAILABLE, named.
  coordinator_->kill();
  auto gone = client.read("drone1/markers/QR_7");
  EXPECT_EQ(gone.status().code(), absl::StatusCode::kUnavailable) << gone.status();
}

TEST_F(CoordinatorBeliefsTest, WatchBeliefsSendsTheCurrentBeliefsThenEveryChange) {
  ASSERT_TRUE(write("drone1/before", "a").ok());
  ASSERT_TRUE(write("drone2/other", "x").ok());
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WatchBeliefsRequest request;
  request.set_prefix("drone1/");
  auto reader = stub_->WatchBeliefs(&context, request);
  v1::WatchBeliefsResponse message;
  ASSERT_TRUE(reader->Read(&message));
  EXPECT_EQ(message.belief().key(), "drone1/before");
  ASSERT_TRUE(write("drone2/ignored", "y").ok());
  ASSERT_TRUE(write("drone1/after", "b").ok());
  ASSERT_TRUE(reader->Read(&message));
  EXPECT_EQ(message.belief().key(), "drone1/after");  // drone2/ is filtered out
  v1::DeleteBeliefRequest erase;
  erase.set_key("drone1/before");
  erase.set_writer("operator");
  v1::DeleteBeliefResponse erased;
  ASSERT_TRUE(stub_->DeleteBelief(deadline().get(), erase, &erased).ok());
  ASSERT_TRUE(reader->Read(&message));
  EXPECT_EQ(message.belief().key(), "drone1/before");
  EXPECT_TRUE(message.belief().deleted());
  // Resuming after a version replays what came after it.
  const uint64_t resume_from = message.belief().version() - 1;
  context.TryCancel();
  reader->Finish();
  grpc::ClientContext again;
  again.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  request.set_since_version(resume_from);
  auto replay = stub_->WatchBeliefs(&again, request);
  ASSERT_TRUE(replay->Read(&message));
  EXPECT_EQ(message.belief().key(), "drone1/before");
  EXPECT_TRUE(message.belief().deleted());
  again.TryCancel();
  replay->Finish();
}

}  // namespace
