// onWorker(): data from other threads reaches a behavior on its own worker,
// so behavior code needs no lock.

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <future>
#include <mutex>
#include <optional>
#include <stop_token>
#include <thread>
#include <utility>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"
#include "test_behaviors.h"

namespace behaviorlib {
namespace {

using ::testing::ElementsAre;
using testing::eventually;
using ::testing::HasSubstr;
using testing::waitParams;

// Hands every int it is fed to its worker. Sample 1 holds the worker until
// the test releases it, so the test can queue samples behind it.
class FedBehavior final : public Behavior<v1::WaitParameters> {
 public:
  FedBehavior(Delivery delivery, size_t capacity)
      : Behavior("FED"), delivery_(delivery), capacity_(capacity) {}

  std::function<void(const int&)> feed;  // set by onActivate
  std::promise<void> release;

  std::vector<int> received() const {
    std::lock_guard lock(test_mutex_);
    return received_;
  }
  bool handledOnTheWorker() const {
    std::lock_guard lock(test_mutex_);
    return !handler_threads_.empty() && worker_ != std::thread::id() &&
           std::all_of(handler_threads_.begin(), handler_threads_.end(),
                       [&](std::thread::id id) { return id == worker_; });
  }
  bool holding() const { return holding_.load(); }

 protected:
  absl::Status onActivate() override {
    feed = onWorker<int>([this](const int& v) { handle(v); }, delivery_, capacity_);
    return absl::OkStatus();
  }
  void onExecute() override {
    std::lock_guard lock(test_mutex_);
    worker_ = std::this_thread::get_id();
  }

 private:
  void handle(int v) {
    if (v < 0) throw std::runtime_error("bad sample " + std::to_string(v));
    {
      std::lock_guard lock(test_mutex_);
      received_.push_back(v);
      handler_threads_.push_back(std::this_thread::get_id());
    }
    if (v == 1) {
      holding_ = true;
      release_future_.wait();
      holding_ = false;
    }
  }

  const Delivery delivery_;
  const size_t capacity_;
  std::shared_future<void> release_future_ = release.get_future().share();
  std::atomic<bool> holding_{false};
  // The test's own bookkeeping, read from the test thread.
  mutable std::mutex test_mutex_;
  std::vector<int> received_;
  std::vector<std::thread::id> handler_threads_;
  std::thread::id worker_;
};

class WorkerDeliveryTest : public ::testing::Test {
 protected:
  FedBehavior& start(Delivery delivery, size_t capacity = 1024) {
    auto behavior = std::make_unique<FedBehavior>(delivery, capacity);
    behavior_ = behavior.get();
    host_.add(std::move(behavior));
    EXPECT_TRUE(host_.start().ok());
    auto r = detail::engineOf(*behavior_).activateAndWait(waitParams(100));
    EXPECT_TRUE(r.ok()) << r.status();
    return *behavior_;
  }
  // Feeds 1 and waits until its handler holds the worker.
  void holdTheWorker() {
    behavior_->feed(1);
    ASSERT_TRUE(eventually([&] { return behavior_->holding(); }));
  }

  FakeClock clock_;
  BehaviorHost host_{testing::hostOptions("drone1", "test"), clock_};
  testing::EventCollector events_{host_.events()};
  FedBehavior* behavior_ = nullptr;
};

TEST_F(WorkerDeliveryTest, EverySampleRunsOnTheWorkerInOrder) {
  auto& b = start(Delivery::kEvery);
  std::thread producer([&] {
    for (int v = 2; v <= 200; ++v) b.feed(v);
  });
  producer.join();
  ASSERT_TRUE(eventually([&] { return b.received().size() == 199; }));
  std::vector<int> expected;
  for (int v = 2; v <= 200; ++v) expected.push_back(v);
  EXPECT_EQ(b.received(), expected);
  EXPECT_TRUE(b.handledOnTheWorker());
}

TEST_F(WorkerDeliveryTest, LatestDeliversOnlyTheNewestWhileTheWorkerIsBusy) {
  auto& b = start(Delivery::kLatest);
  holdTheWorker();
  b.feed(2);
  b.feed(3);
  b.feed(4);
  b.release.set_value();
  ASSERT_TRUE(eventually([&] { return b.received().size() == 2; }));
  EXPECT_THAT(b.received(), ElementsAre(1, 4));
}

TEST_F(WorkerDeliveryTest, EveryKeepsTheNewestUpToItsCapacity) {
  auto& b = start(Delivery::kEvery, 3);
  holdTheWorker();
  for (int v = 2; v <= 6; ++v) b.feed(v);
  b.release.set_value();
  ASSERT_TRUE(eventually([&] { return b.received().size() == 4; }));
  EXPECT_THAT(b.received(), ElementsAre(1, 4, 5, 6));
}

TEST_F(WorkerDeliveryTest, SamplesOfAnEndedActivationAreDropped) {
  auto& b = start(Delivery::kEvery);
  holdTheWorker();
  b.feed(2);
  // Queued behind the held handler; commands run before waiting samples.
  std::promise<absl::StatusOr<v1::DeactivateResponse>> deactivated;
  detail::engineOf(b).deactivate(
      {}, [&](absl::StatusOr<v1::DeactivateResponse> r) { deactivated.set_value(std::move(r)); });
  b.release.set_value();
  auto r = deactivated.get_future().get();
  ASSERT_TRUE(r.ok()) << r.status();
  // The old activation's callback stays dropped in the next activation.
  const auto old_feed = b.feed;
  ASSERT_TRUE(detail::engineOf(b).activateAndWait(waitParams(100)).ok());
  old_feed(3);
  b.feed(5);  // queued after 3: once 5 arrives, 3 has been passed over
  ASSERT_TRUE(eventually([&] { return b.received().size() >= 2; }));
  EXPECT_THAT(b.received(), ElementsAre(1, 5));
}

TEST_F(WorkerDeliveryTest, AHandlerThatThrowsEndsTheActivationWithProcessFailure) {
  auto& b = start(Delivery::kEvery);
  b.feed(-7);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_THAT(finished.finished().message(), HasSubstr("bad sample -7"));
}

// Runs one background job at activation: `job_value` < 0 makes it throw.
class BackgroundBehavior final : public Behavior<v1::WaitParameters> {
 public:
  explicit BackgroundBehavior(int job_value) : Behavior("BACKGROUND"), job_value_(job_value) {}

  struct Seen {
    int value = 0;
    std::thread::id job_thread, done_thread, worker;
  };
  std::optional<Seen> seen() const {
    std::lock_guard lock(test_mutex_);
    return seen_;
  }

 protected:
  absl::Status onActivate() override {
    const int value = job_value_;
    inBackground<std::pair<int, std::thread::id>>(
        [value] {
          if (value < 0) throw std::runtime_error("no plan");
          return std::pair{value * 2, std::this_thread::get_id()};
        },
        [this](const std::pair<int, std::thread::id>& result) {
          std::lock_guard lock(test_mutex_);
          seen_ = Seen{result.first, result.second, std::this_thread::get_id(), worker_};
        });
    std::lock_guard lock(test_mutex_);
    worker_ = std::this_thread::get_id();
    return absl::OkStatus();
  }

 private:
  const int job_value_;
  mutable std::mutex test_mutex_;
  std::optional<Seen> seen_;
  std::thread::id worker_;
};

class BackgroundJobTest : public ::testing::Test {
 protected:
  BackgroundBehavior& start(int job_value) {
    auto behavior = std::make_unique<BackgroundBehavior>(job_value);
    auto& b = *behavior;
    host_.add(std::move(behavior));
    EXPECT_TRUE(host_.start().ok());
    auto r = detail::engineOf(b).activateAndWait(waitParams(100));
    EXPECT_TRUE(r.ok()) << r.status();
    return b;
  }
  FakeClock clock_;
  BehaviorHost host_{testing::hostOptions("drone1", "test"), clock_};
  testing::EventCollector events_{host_.events()};
};

TEST_F(BackgroundJobTest, TheJobRunsBesideTheWorkerAndItsResultArrivesOnTheWorker) {
  auto& b = start(21);
  ASSERT_TRUE(eventually([&] { return b.seen().has_value(); }));
  const auto seen = *b.seen();
  EXPECT_EQ(seen.value, 42);
  EXPECT_EQ(seen.done_thread, seen.worker);
  EXPECT_NE(seen.job_thread, seen.worker);
}

TEST_F(BackgroundJobTest, AJobThatThrowsEndsTheActivationWithProcessFailure) {
  auto& b = start(-1);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_THAT(finished.finished().message(), HasSubstr("a background job threw: no plan"));
  EXPECT_FALSE(b.seen().has_value());
}

// Cancellable background jobs: each waits (bounded) until it is called off,
// then says whether it was. At activation, job 1 is started and superseded
// by job 2 at once; job 2 runs until the activation ends.
class CallOffBehavior final : public Behavior<v1::WaitParameters> {
 public:
  CallOffBehavior() : Behavior("CALL_OFF") {}

  std::vector<int> delivered() const {
    std::lock_guard lock(test_mutex_);
    return delivered_;
  }
  std::vector<int> calledOff() const {
    std::lock_guard lock(test_mutex_);
    return called_off_;
  }

 protected:
  absl::Status onActivate() override {
    std::stop_source first = start(1);
    first.request_stop();  // superseded
    start(2);
    return absl::OkStatus();
  }

 private:
  std::stop_source start(int id) {
    return inBackground<int>(
        [this, id](std::stop_token stop) {
          const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
          while (!stop.stop_requested() && std::chrono::steady_clock::now() < deadline) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
          }
          std::lock_guard lock(test_mutex_);
          if (stop.stop_requested()) called_off_.push_back(id);
          return id;
        },
        [this](const int& id) {
          std::lock_guard lock(test_mutex_);
          delivered_.push_back(id);
        });
  }

  mutable std::mutex test_mutex_;
  std::vector<int> delivered_, called_off_;
};

TEST(CancellableJobTest, ASupersededJobAndTheJobsOfAnEndedActivationAreCalledOffAndDropped) {
  FakeClock clock;
  BehaviorHost host(testing::hostOptions("drone1", "test"), clock);
  auto behavior = std::make_unique<CallOffBehavior>();
  auto& b = *behavior;
  host.add(std::move(behavior));
  ASSERT_TRUE(host.start().ok());
  ASSERT_TRUE(detail::engineOf(b).activateAndWait(waitParams(100)).ok());
  // Job 1 was called off by the behavior; job 2 runs.
  ASSERT_TRUE(eventually([&] { return b.calledOff() == std::vector<int>{1}; }));
  // The activation's end calls job 2 off.
  ASSERT_TRUE(detail::engineOf(b).deactivateAndWait().ok());
  ASSERT_TRUE(eventually([&] { return b.calledOff() == std::vector<int>{1, 2}; }));
  // Neither result reached the behavior (stop() joins the worker and the
  // background thread, so a late delivery would have happened by now).
  host.stop();
  EXPECT_TRUE(b.delivered().empty());
}

}  // namespace
}  // namespace behaviorlib
