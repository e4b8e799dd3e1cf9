// The coordinator against hostile input (issue: security and hardening): a
// YAML alias bomb in a mission text is refused quickly, in little memory;
// mission files are read only inside --mission-dir; a non-scalar key is a
// clear INVALID_ARGUMENT and the process keeps serving.
//
// One real coordinator process on loopback; its memory and CPU are read from
// /proc.

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;

std::unique_ptr<grpc::ClientContext> deadline() {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  return context;
}

// A field of /proc/<pid>/status in kB ("VmRSS", "VmHWM").
long statusKb(pid_t pid, const std::string& field) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(field + ":", 0) == 0) return std::stol(line.substr(field.size() + 1));
  }
  return -1;
}

// User plus system CPU time of the process, in seconds.
double cpuSeconds(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  // Fields after the command name (which may hold spaces) start after ')'.
  std::istringstream rest(text.substr(text.rfind(')') + 2));
  std::string field;
  unsigned long long utime = 0, stime = 0;
  for (int i = 3; i <= 15 && rest >> field; ++i) {
    if (i == 14) utime = std::stoull(field);
    if (i == 15) stime = std::stoull(field);
  }
  return static_cast<double>(utime + stime) / static_cast<double>(sysconf(_SC_CLK_TCK));
}

// The mission text of the report: anchors nine deep inside a step's
// parameters, 10^9 values once expanded, about 600 bytes.
std::string aliasBombMission() {
  std::string text = "name: bomb\nrobot: drone1\nsteps:\n  - behavior: WAIT\n    parameters:\n";
  text += "      a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n";
  for (int i = 1; i <= 9; ++i) {
    const std::string below = "*a" + std::to_string(i - 1);
    text += "      a" + std::to_string(i) + ": &a" + std::to_string(i) + " [";
    for (int k = 0; k < 10; ++k) text += (k ? "," : "") + below;
    text += "]\n";
  }
  return text;
}

class CoordinatorHardeningTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char state[] = "/tmp/coordinator_hardening_XXXXXX";
    ASSERT_NE(mkdtemp(state), nullptr);
    base_ = state;
    std::filesystem::create_directories(base_ + "/missions");
    std::filesystem::create_directories(base_ + "/state");
    coordinator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_COORDINATOR_PATH,
        std::vector<std::string>{"--state-dir", base_ + "/state", "--mission-dir",
                                 base_ + "/missions"});
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
  }
  void TearDown() override {
    coordinator_.reset();
    std::filesystem::remove_all(base_);
  }
  grpc::Status startText(const std::string& text) {
    v1::StartMissionRequest request;
    request.set_text(text);
    request.set_source_name("hostile.yaml");
    v1::StartMissionResponse response;
    return stub_->StartMission(deadline().get(), request, &response);
  }
  grpc::Status startFile(const std::string& path) {
    v1::StartMissionRequest request;
    request.set_file_path(path);
    v1::StartMissionResponse response;
    return stub_->StartMission(deadline().get(), request, &response);
  }
  bool serving() {
    v1::ListMissionsResponse response;
    return stub_->ListMissions(deadline().get(), v1::ListMissionsRequest(), &response).ok();
  }

  std::string base_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

TEST_F(CoordinatorHardeningTest, AnAliasBombIsRefusedInLittleTimeAndMemory) {
  const std::string bomb = aliasBombMission();
  ASSERT_LT(bomb.size(), 700u);
  ASSERT_TRUE(serving());
  const pid_t pid = coordinator_->pid();
  const long rss_before_kb = statusKb(pid, "VmRSS");
  const double cpu_before_s = cpuSeconds(pid);
  const grpc::Status s = startText(bomb);
  const double cpu_s = cpuSeconds(pid) - cpu_before_s;
  const long peak_kb = statusKb(pid, "VmHWM");
  std::printf("alias bomb of %zu bytes: refused with %.3f s of the coordinator's CPU; peak RSS "
              "%ld kB, %ld kB before\n",
              bomb.size(), cpu_s, peak_kb, rss_before_kb);
  ASSERT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
  EXPECT_NE(s.error_message().find("hostile.yaml:"), std::string::npos) << s.error_message();
  EXPECT_NE(s.error_message().find("aliases are expanded"), std::string::npos) << s.error_message();
  // CPU time of the coordinator (not wall time: a busy machine stretches
  // that) and its peak resident memory. Before the limits: 8 s and 1.3 GB.
  EXPECT_LT(cpu_s, 0.05) << "the coordinator spent " << cpu_s << " s of CPU on the refusal";
  EXPECT_LT(peak_kb - rss_before_kb, 10 * 1024)
      << "peak RSS " << peak_kb << " kB, " << rss_before_kb << " kB before";
  EXPECT_TRUE(serving());
}

TEST_F(CoordinatorHardeningTest, OversizedRequestsAreRefusedAndTheServerGoesOn) {
  // Above the mission cap (1 MiB) but within gRPC's message limit: ours.
  grpc::Status s = startText("name: m\n# " + std::string(1200 * 1024, 'x') + "\n");
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
  EXPECT_NE(s.error_message().find("more than the 1048576 allowed"), std::string::npos)
      << s.error_message();
  // Above the server's message limit (4 MiB): refused before any handler.
  s = startText(std::string(5 << 20, 'x'));
  EXPECT_EQ(s.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << s.error_message();
  EXPECT_TRUE(serving());
}

TEST_F(CoordinatorHardeningTest, NonScalarKeysAndDeepNestingAreInvalidArgumentWithTheLine) {
  grpc::Status s = startText("name: m\nrobot: drone1\n? [a, b]\n: 1\nsteps: []\n");
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
  EXPECT_NE(s.error_message().find("hostile.yaml:3:"), std::string::npos) << s.error_message();
  s = startText("name: m\nsteps:\n  - behavior: WAIT\n    parameters: {d: " +
                std::string(5000, '[') + std::string(5000, ']') + "}\n");
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
  EXPECT_NE(s.error_message().find("nested deeper"), std::string::npos) << s.error_message();
  EXPECT_TRUE(serving());
}

TEST_F(CoordinatorHardeningTest, MissionFilesAreReadOnlyInsideTheMissionDirectory) {
  std::ofstream(base_ + "/outside.yaml") << "name: m\nrobot: drone1\nsteps: [{behavior: LAND}]\n";
  std::filesystem::create_symlink(base_ + "/outside.yaml", base_ + "/missions/link.yaml");
  // A link to the journal's directory, as a shared volume could offer.
  std::ofstream(base_ + "/state/record") << "name: m\nrobot: drone1\nsteps: []\n";
  std::filesystem::create_symlink(base_ + "/state", base_ + "/missions/state");
  for (const std::string& path :
       {base_ + "/outside.yaml", std::string("../outside.yaml"), std::string("link.yaml"),
        std::string("/dev/zero"), std::string("state/record"), std::string("/etc/passwd")}) {
    const grpc::Status s = startFile(path);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::PERMISSION_DENIED)
        << path << ": " << s.error_message();
    EXPECT_NE(s.error_message().find(std::filesystem::canonical(base_ + "/missions").string()),
              std::string::npos)
        << s.error_message();
  }
  // Inside, the file is read and parsed (the robot has no system: refused
  // after parsing, naming it).
  std::ofstream(base_ + "/missions/ok.yaml")
      << "name: m\nrobot: drone1\nsteps: [{behavior: LAND}]\n";
  const grpc::Status s = startFile("ok.yaml");
  EXPECT_EQ(s.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << s.error_message();
  EXPECT_NE(s.error_message().find("drone1"), std::string::npos) << s.error_message();
  EXPECT_TRUE(serving());
}

}  // namespace
