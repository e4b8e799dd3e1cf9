#include "behaviorlib/process_supervisor.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "test_behaviors.h"

namespace behaviorlib {
namespace {

using testing::eventually;
using ::testing::HasSubstr;

TEST(ChildProcessTest, RunningChildKeepsGoingAndExitIsReportedWithItsCode) {
  ChildProcess sleeper({"sleep", "30"});
  ASSERT_TRUE(sleeper.start().ok());
  EXPECT_FALSE(sleeper.check().finishes());
  EXPECT_EQ(sleeper.start().code(), absl::StatusCode::kFailedPrecondition);
  sleeper.stop();
  EXPECT_TRUE(sleeper.check().finishes());

  ChildProcess failing({"sh", "-c", "exit 3"});
  ASSERT_TRUE(failing.start().ok());
  ASSERT_TRUE(eventually([&] { return failing.check().finishes(); }));
  EXPECT_THAT(failing.check().message(), HasSubstr("exited with code 3"));
}

TEST(ChildProcessTest, KilledChildIsReportedWithTheSignal) {
  ChildProcess child({"sleep", "30"});
  ASSERT_TRUE(child.start().ok());
  ::kill(child.pid(), SIGKILL);
  ASSERT_TRUE(eventually([&] { return child.check().finishes(); }));
  EXPECT_THAT(child.check().message(), HasSubstr("killed by signal 9"));
}

TEST(ChildProcessTest, MissingProgramIsReported) {
  ChildProcess missing({"/nonexistent/program"});
  ASSERT_TRUE(missing.start().ok());
  ASSERT_TRUE(eventually([&] { return missing.check().finishes(); }));
  EXPECT_THAT(missing.check().message(), HasSubstr("could not be started"));
}

TEST(SupervisedThreadTest, ExceptionSilenceAndUnexpectedReturnAreFailures) {
  SupervisedThread throwing(
      [](const std::atomic<bool>&, Heartbeat&) { throw std::runtime_error("socket closed"); },
      std::chrono::seconds(5));
  ASSERT_TRUE(eventually([&] { return throwing.check().finishes(); }));
  EXPECT_THAT(throwing.check().message(), HasSubstr("socket closed"));

  SupervisedThread silent(
      [](const std::atomic<bool>& stop, Heartbeat&) {
        while (!stop) std::this_thread::sleep_for(std::chrono::milliseconds(1));
      },
      std::chrono::milliseconds(50));
  ASSERT_TRUE(eventually([&] { return silent.check().finishes(); }));
  EXPECT_THAT(silent.check().message(), HasSubstr("silent"));

  SupervisedThread healthy(
      [](const std::atomic<bool>& stop, Heartbeat& beat) {
        while (!stop) {
          beat.beat();
          std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }
      },
      std::chrono::seconds(2));
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  EXPECT_FALSE(healthy.check().finishes());

  SupervisedThread returning([](const std::atomic<bool>&, Heartbeat&) {}, std::chrono::seconds(5));
  ASSERT_TRUE(eventually([&] { return returning.check().finishes(); }));
  EXPECT_THAT(returning.check().message(), HasSubstr("returned unexpectedly"));
}

}  // namespace
}  // namespace behaviorlib
