#pragma once

// AnswerWatch: one question to the operator, carried out on its own thread
// so that the behavior's monitoring never waits on the coordinator.
//
//   AnswerWatch watch(beliefs, {.request_key = "operator/requests/q1", ...});
//   watch.start();
//   ... watch.state() == AnswerWatch::State::kAnswered -> watch.answer()
//   watch.stop();
//
// The thread writes the question, then reads the answer key every
// poll_period until a belief written after the question appears, copies its
// value to copy_key, and stops. A failing coordinator is retried; the run
// of failures is reported by failure() until a call succeeds again.

#include <google/protobuf/struct.pb.h>

#include <chrono>
#include <optional>
#include <string>
#include <thread>

#include "absl/synchronization/mutex.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::operator_interaction {

class AnswerWatch {
 public:
  struct Request {
    std::string request_key;           ///< where the question goes
    google::protobuf::Value question;  ///< what is written there
    std::string answer_key;            ///< where the operator answers
    std::string copy_key;              ///< where the answer is copied to
    std::string writer;                ///< "<robot>/REQUEST_OPERATOR_ASSISTANCE"
    std::chrono::milliseconds poll_period{100};
  };
  enum class State { kAsking, kWaiting, kAnswered };

  AnswerWatch(const server::BeliefClient& beliefs, Request request);
  /// Stops the thread.
  ~AnswerWatch();
  AnswerWatch(const AnswerWatch&) = delete;
  AnswerWatch& operator=(const AnswerWatch&) = delete;

  void start();
  /// Stops and joins the thread (promptly: at most one call's deadline).
  void stop();

  State state() const;
  /// The answer, once kAnswered.
  std::optional<v1::Belief> answer() const;
  /// The message of the first failure of the current run of failures
  /// talking to the coordinator; nullopt while calls succeed.
  std::optional<std::string> failure() const;
  /// The version of the question's belief (0 before it is written).
  uint64_t questionVersion() const;

 private:
  void run();
  // Records a call's outcome; true when it succeeded.
  bool record(const absl::Status& status);
  // Waits `period` or until stopped; true when stopped.
  bool pause(std::chrono::milliseconds period);

  const server::BeliefClient& beliefs_;
  const Request request_;
  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  State state_ ABSL_GUARDED_BY(mutex_) = State::kAsking;
  uint64_t question_version_ ABSL_GUARDED_BY(mutex_) = 0;
  std::optional<v1::Belief> answer_ ABSL_GUARDED_BY(mutex_);
  std::optional<std::string> failure_ ABSL_GUARDED_BY(mutex_);
  std::thread thread_;
};

}  // namespace behaviorlib::operator_interaction
