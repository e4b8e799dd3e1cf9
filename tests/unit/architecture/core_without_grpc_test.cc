// The core builds, links and runs without gRPC (docs/architecture.md): this
// program links behaviorlib::core and GoogleTest and nothing else. A behavior
// runs to its goal on a fake clock, a bad parameter is refused with its
// error details, and no gRPC library is loaded into the process.

#include <gtest/gtest.h>
#include <link.h>

#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib {
namespace {

using std::chrono::milliseconds;

// WAIT as a user would write it: the goal is the time elapsed.
class Wait final : public Behavior<v1::WaitParameters> {
 protected:
  Verdict checkGoal() override {
    if (activeTime() >= std::chrono::duration<double>(parameters().duration_s())) {
      return Verdict::finish("waited");
    }
    return Verdict::keepGoing();
  }
};

class CoreWithoutGrpcTest : public ::testing::Test {
 protected:
  void SetUp() override {
    BehaviorHostOptions options;
    options.robot_id = "drone1";
    options.system = "core_only";
    host_ = std::make_unique<BehaviorHost>(options, clock_);
    host_->add(std::make_unique<Wait>());
    ASSERT_TRUE(host_->start().ok());
    events_ = host_->events().subscribe({}, [] {});
  }
  void TearDown() override { host_->stop(); }

  FakeClock clock_;
  std::unique_ptr<BehaviorHost> host_;
  std::unique_ptr<EventSubscription> events_;
};

TEST_F(CoreWithoutGrpcTest, ABehaviorRunsToItsGoalOnAFakeClock) {
  auto parameters = std::make_unique<v1::WaitParameters>();
  parameters->set_duration_s(0.05);
  auto activated = host_->find("WAIT")->activateAndWait(std::move(parameters));
  ASSERT_TRUE(activated.ok()) << activated.status();

  v1::BehaviorEvent finished;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!finished.has_finished() && std::chrono::steady_clock::now() < deadline) {
    clock_.advance(milliseconds(10));
    std::this_thread::sleep_for(milliseconds(1));
    while (auto event = events_->pop()) {
      if (event->has_finished()) finished = *event;
    }
  }
  ASSERT_TRUE(finished.has_finished());
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(finished.behavior(), "WAIT");
}

TEST_F(CoreWithoutGrpcTest, ABadParameterIsRefusedWithItsDetails) {
  auto parameters = std::make_unique<v1::WaitParameters>();
  parameters->set_duration_s(-1);
  auto activated = host_->find("WAIT")->activateAndWait(std::move(parameters));
  ASSERT_FALSE(activated.ok());
  EXPECT_EQ(activated.status().code(), absl::StatusCode::kInvalidArgument);
  auto bad = errors::badRequest(activated.status());
  ASSERT_TRUE(bad.has_value()) << activated.status();
  ASSERT_GE(bad->field_violations_size(), 1);
  EXPECT_EQ(bad->field_violations(0).field(), "parameters.duration_s");
}

TEST(CoreWithoutGrpc, NoGrpcLibraryIsLoaded) {
  std::vector<std::string> loaded;
  dl_iterate_phdr(
      [](dl_phdr_info* info, size_t, void* out) {
        if (info->dlpi_name != nullptr) {
          static_cast<std::vector<std::string>*>(out)->push_back(info->dlpi_name);
        }
        return 0;
      },
      &loaded);
  EXPECT_GT(loaded.size(), 1u);
  for (const std::string& name : loaded) {
    EXPECT_EQ(name.find("grpc"), std::string::npos) << name;
  }
}

}  // namespace
}  // namespace behaviorlib
