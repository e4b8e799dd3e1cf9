#pragma once

// The greeter system's behaviors. Each is one class: the paper's functions
// it needs, the rest inherited. Its name and parameters come from its
// declaration in proto/acme/v1/greeter.proto.

#include <string>

#include "absl/strings/str_cat.h"
#include "acme/v1/greeter.pb.h"
#include "behaviorlib/behavior_execution_manager.h"

namespace acme {

class SayHelloBehavior final : public behaviorlib::Behavior<v1::SayHelloParameters> {
 public:
  int greetings() const { return greetings_; }

 protected:
  absl::Status onActivate() override {
    greetings_ = 0;
    return absl::OkStatus();
  }
  void onExecute() override { ++greetings_; }
  behaviorlib::Verdict checkGoal() override {
    if (greetings_ < parameters().times()) return behaviorlib::Verdict::keepGoing();
    return behaviorlib::Verdict::finish(
        absl::StrCat("said hello to ", parameters().name(), " ", greetings_, " times"));
  }

 private:
  int greetings_ = 0;
};

class KeepCountingBehavior final : public behaviorlib::Behavior<v1::KeepCountingParameters> {
 protected:
  absl::Status onActivate() override {
    count_ = 0;
    return absl::OkStatus();
  }
  void onExecute() override { ++count_; }
  behaviorlib::Verdict checkProgress() override {
    if (count_ <= parameters().limit()) return behaviorlib::Verdict::keepGoing();
    return behaviorlib::Verdict::finish(absl::StrCat("counted past ", parameters().limit()));
  }

 private:
  int count_ = 0;
};

}  // namespace acme
