#pragma once

// CONTRACT_PROBE (contract_probe.proto): after after_s of active time, ends
// through the functions its parameters name, so that the lifecycle contract
// suite (behavior_system_test) provokes every termination cause. Its twin in
// Python is contract_behaviors.py; the suite runs against both.

#include <chrono>
#include <stdexcept>
#include <thread>

#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/tests/v1/contract_probe.pb.h"

namespace behaviorlib::contract {

class ContractProbeBehavior final : public Behavior<tests::v1::ContractProbeParameters> {
 protected:
  absl::Status onActivate() override {
    if (!parameters().refuse_activation().empty()) {
      return absl::FailedPreconditionError(parameters().refuse_activation());
    }
    active_ = true;
    blocked_ = false;
    if (parameters().time_out_s() > 0) {
      setMaximumExecutionTime(seconds(parameters().time_out_s()),
                              "the probe's time_out_s of active time passed");
    }
    return absl::OkStatus();
  }

  void onDeactivate() override { active_ = false; }

  void onExecute() override {
    if (!due()) return;
    if (parameters().throw_in_execute()) throw std::runtime_error("the probe throws");
    if (parameters().block_s() > 0 && !blocked_) {
      blocked_ = true;
      std::this_thread::sleep_for(std::chrono::duration<double>(parameters().block_s()));
    }
  }

  Verdict checkProcesses() override {
    if (due() && parameters().fail_processes())
      return Verdict::finish("the probe's process failed");
    return Verdict::keepGoing();
  }
  // Also asked before an activation (and by CheckSituation while inactive),
  // when there are no parameters: the situation is then fine.
  Situation checkSituation() override {
    if (active_ && due() && parameters().change_situation()) {
      return Situation::infeasible(v1::SITUATION_REASON_CONFIGURATION,
                                   "the probe's situation changed");
    }
    return Situation::ok();
  }
  Verdict checkGoal() override {
    if (due() && parameters().achieve_goal()) return Verdict::finish("the probe's goal achieved");
    return Verdict::keepGoing();
  }
  Verdict checkProgress() override {
    if (due() && parameters().wrong_progress())
      return Verdict::finish("the probe made no progress");
    return Verdict::keepGoing();
  }

 private:
  bool due() const { return activeTime() >= seconds(parameters().after_s()); }

  bool active_ = false;
  bool blocked_ = false;
};

}  // namespace behaviorlib::contract
