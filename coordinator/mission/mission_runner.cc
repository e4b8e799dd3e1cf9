#include "coordinator/mission/mission_runner.h"

#include <google/protobuf/util/message_differencer.h>
#include <google/protobuf/util/time_util.h>

#include <sstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"

namespace behaviorlib::coordinator {
namespace {

using google::protobuf::util::TimeUtil;

// A record's position: its node, or (journaled before nodes) its path.
Position positionOf(const v1::MissionStepRecord& r) {
  if (!r.node().empty()) {
    if (auto parsed = parseNode(r.node())) return *parsed;
  }
  Position position;
  for (int i = 0; i < r.path_size(); ++i) {
    position.push_back(
        {i == 0 ? MissionNode::Kind::kStep : MissionNode::Kind::kFallback, r.path(i), 0});
  }
  return position;
}

bool startsWith(const Position& path, const Position& prefix) {
  return path.size() >= prefix.size() && std::equal(prefix.begin(), prefix.end(), path.begin());
}

// How a loop's record names it: "for_each point in 3 items", "repeat 3
// times", "repeat until drone1/done (at most 5 times)".
std::string loopText(const MissionLoop& loop) {
  switch (loop.kind) {
    case MissionLoop::Kind::kForEach:
      return "for_each " + loop.as + " in " +
             (loop.belief.empty() ? std::to_string(loop.items.values_size()) + " items"
                                  : "belief " + loop.belief);
    case MissionLoop::Kind::kTimes:
      return "repeat " + std::to_string(loop.times) + " times";
    case MissionLoop::Kind::kUntil:
      return "repeat until " + loop.until->key + " (at most " + std::to_string(loop.times) +
             " times)";
  }
  return "loop";
}

// A record at `path`: its node, and its v1 path where it has one (no call).
v1::MissionStepRecord recordAt(const Position& path) {
  v1::MissionStepRecord record;
  record.set_node(nodeText(path));
  bool plain = true;
  for (const MissionNode& n : path) plain = plain && n.kind != MissionNode::Kind::kCall;
  if (plain) {
    for (const MissionNode& n : path) record.add_path(n.index);
  }
  return record;
}

}  // namespace

std::string nodeText(const Position& position) {
  std::string out;
  for (size_t i = 0; i < position.size(); ++i) {
    const MissionNode& n = position[i];
    switch (n.kind) {
      case MissionNode::Kind::kStep:
        out += (i == 0 ? "steps/" : "/steps/") + std::to_string(n.index);
        break;
      case MissionNode::Kind::kFallback:
        out += "/fallback/" + std::to_string(n.index);
        break;
      case MissionNode::Kind::kCall:
        out +=
            "/attempt/" + std::to_string(n.call_attempt) + "/call/steps/" + std::to_string(n.index);
        break;
      case MissionNode::Kind::kIteration:
        out += "/attempt/" + std::to_string(n.call_attempt) + "/iteration/" +
               std::to_string(n.iteration) + "/steps/" + std::to_string(n.index);
        break;
    }
  }
  return out;
}

std::optional<Position> parseNode(const std::string& text) {
  std::vector<std::string> parts = absl::StrSplit(text, '/');
  Position position;
  auto number = [](const std::string& part, int* out) {
    return absl::SimpleAtoi(part, out) && *out >= 0;
  };
  size_t i = 0;
  while (i < parts.size()) {
    MissionNode n;
    if (i == 0 && parts[i] == "steps" && i + 1 < parts.size() && number(parts[i + 1], &n.index)) {
      n.kind = MissionNode::Kind::kStep;
      i += 2;
    } else if (i > 0 && parts[i] == "fallback" && i + 1 < parts.size() &&
               number(parts[i + 1], &n.index)) {
      n.kind = MissionNode::Kind::kFallback;
      i += 2;
    } else if (i > 0 && parts[i] == "attempt" && i + 4 < parts.size() && parts[i + 2] == "call" &&
               parts[i + 3] == "steps" && number(parts[i + 1], &n.call_attempt) &&
               number(parts[i + 4], &n.index)) {
      n.kind = MissionNode::Kind::kCall;
      i += 5;
    } else if (i > 0 && parts[i] == "attempt" && i + 5 < parts.size() &&
               parts[i + 2] == "iteration" && parts[i + 4] == "steps" &&
               number(parts[i + 1], &n.call_attempt) && number(parts[i + 3], &n.iteration) &&
               number(parts[i + 5], &n.index)) {
      n.kind = MissionNode::Kind::kIteration;
      i += 6;
    } else {
      return std::nullopt;
    }
    position.push_back(n);
  }
  if (position.empty()) return std::nullopt;
  return position;
}

MissionRunner::MissionRunner(MissionSpec spec, std::string mission_id, std::string robot_id,
                             std::string source, MissionActions& actions, BeliefStore& beliefs,
                             OnChange on_change)
    : spec_(std::move(spec)),
      actions_(actions),
      beliefs_(beliefs),
      on_change_(std::move(on_change)) {
  status_.set_mission_id(std::move(mission_id));
  status_.set_name(spec_.name);
  status_.set_robot_id(std::move(robot_id));
  status_.set_file(spec_.file);
  status_.set_source(std::move(source));
  status_.mutable_imports()->insert(spec_.imports.begin(), spec_.imports.end());
  status_.set_state(v1::MISSION_STATE_RUNNING);
  *status_.mutable_start_time() = TimeUtil::GetCurrentTime();
}

MissionRunner::MissionRunner(MissionSpec spec, const v1::MissionStatus& status,
                             MissionActions& actions, BeliefStore& beliefs, OnChange on_change)
    : spec_(std::move(spec)),
      actions_(actions),
      beliefs_(beliefs),
      on_change_(std::move(on_change)),
      status_(status) {
  resuming_ = true;
  resume_from_.assign(status.steps().begin(), status.steps().end());
  pause_requested_ = status.state() == v1::MISSION_STATE_PAUSED;
}

MissionRunner::~MissionRunner() {
  {
    absl::MutexLock lock(&mutex_);
    quit_ = true;
  }
  if (thread_.joinable()) thread_.join();
}

void MissionRunner::start() {
  thread_ = std::thread([this] { run(); });
}

absl::Status MissionRunner::pause() {
  absl::MutexLock lock(&mutex_);
  if (done_ || status_.state() != v1::MISSION_STATE_RUNNING || status_.in_safety_steps()) {
    return absl::FailedPreconditionError("mission '" + status_.mission_id() + "' is " +
                                         v1::MissionState_Name(status_.state()) +
                                         ", not running: nothing to pause");
  }
  if (pause_requested_)
    return absl::FailedPreconditionError("mission '" + status_.mission_id() +
                                         "' is already pausing");
  pause_requested_ = true;
  return absl::OkStatus();
}

absl::Status MissionRunner::resume() {
  absl::MutexLock lock(&mutex_);
  if (done_ || !pause_requested_) {
    return absl::FailedPreconditionError("mission '" + status_.mission_id() + "' is not paused");
  }
  pause_requested_ = false;
  return absl::OkStatus();
}

absl::Status MissionRunner::abort(const std::string& reason, bool run_safety) {
  absl::MutexLock lock(&mutex_);
  if (done_ || status_.state() == v1::MISSION_STATE_FAILED ||
      status_.state() == v1::MISSION_STATE_ABORTED) {
    return absl::FailedPreconditionError("mission '" + status_.mission_id() + "' already ended (" +
                                         v1::MissionState_Name(status_.state()) + ")");
  }
  abort_requested_ = true;
  abort_reason_ = reason.empty() ? "aborted by request" : reason;
  if (!run_safety) skip_safety_ = true;
  return absl::OkStatus();
}

v1::MissionStatus MissionRunner::status() const {
  absl::MutexLock lock(&mutex_);
  return status_;
}

bool MissionRunner::finished() const {
  absl::MutexLock lock(&mutex_);
  return done_;
}

bool MissionRunner::waitFinished(std::chrono::milliseconds timeout) const {
  absl::MutexLock lock(&mutex_);
  return mutex_.AwaitWithTimeout(absl::Condition(&done_), absl::FromChrono(timeout));
}

void MissionRunner::publish() {
  v1::MissionStatus copy;
  {
    absl::MutexLock lock(&mutex_);
    copy = status_;
  }
  if (on_change_) on_change_(copy);
}

int MissionRunner::addRecord(v1::MissionStepRecord record) {
  int index = 0;
  {
    absl::MutexLock lock(&mutex_);
    *status_.add_steps() = std::move(record);
    index = status_.steps_size() - 1;
  }
  publish();
  return index;
}

void MissionRunner::updateRecord(int index,
                                 const std::function<void(v1::MissionStepRecord&)>& change) {
  {
    absl::MutexLock lock(&mutex_);
    change(*status_.mutable_steps(index));
  }
  publish();
}

void MissionRunner::setState(v1::MissionState state, const std::string& message) {
  {
    absl::MutexLock lock(&mutex_);
    status_.set_state(state);
    if (!message.empty()) status_.set_message(message);
  }
  publish();
}

std::string MissionRunner::stepLabel(const MissionStep& step, const Position& path) const {
  std::string label = step.name.empty() ? nodeText(path) : "'" + step.name + "'";
  if (!step.behavior.empty()) label += " (" + step.behavior + ")";
  if (!step.call.empty()) label += " (call " + step.call + ")";
  if (step.loop) label += " (" + loopText(*step.loop) + ")";
  return "step " + label;
}

void MissionRunner::run() {
  const std::string robot = status().robot_id();
  const std::string id = status().mission_id();
  const bool safety_pending = status().in_safety_steps();

  // Recurrent behaviors: the same request ids after a restart give back the
  // same activations.
  for (size_t i = 0; i < spec_.recurrent.size(); ++i) {
    const MissionStep& r = spec_.recurrent[i];
    auto params = beliefs_.resolve(r.parameters);
    absl::StatusOr<std::string> activation =
        params.ok()
            ? actions_.activate(robot, r.behavior, *params, id + "/recurrent/" + std::to_string(i))
            : absl::StatusOr<std::string>(params.status());
    if (!activation.ok()) {
      if (safety_pending) continue;
      failure_ = "recurrent behavior " + r.behavior +
                 " was refused: " + std::string(activation.status().message());
      runSafety();
      return;
    }
    recurrent_.emplace_back(r.behavior, *activation);
  }

  Flow flow = Flow::kAbort;
  if (safety_pending) {
    failure_ = status().message();
  } else {
    Position resume_path;
    if (resuming_ && !resume_from_.empty()) resume_path = positionOf(resume_from_.back());
    if (!resuming_ || resume_from_.empty()) publish();  // the first record of a new mission
    flow = runList(spec_.steps, {}, MissionNode::Kind::kStep, 0, resume_path);
  }
  switch (flow) {
    case Flow::kQuit:
      return;  // shutdown: the journal keeps the mission running
    case Flow::kDone:
      deactivateRecurrent();
      {
        // One step: a waiter that sees done_ sees the final state too.
        absl::MutexLock lock(&mutex_);
        *status_.mutable_end_time() = TimeUtil::GetCurrentTime();
        status_.set_state(v1::MISSION_STATE_SUCCEEDED);
        done_ = true;
      }
      publish();
      return;
    case Flow::kAbortRequested:
      if (failure_.empty()) {
        absl::MutexLock lock(&mutex_);
        failure_ = abort_reason_;
      }
      {
        absl::MutexLock lock(&mutex_);
        status_.set_state(v1::MISSION_STATE_ABORTED);
      }
      runSafety();
      return;
    case Flow::kAbort:
      runSafety();
      return;
  }
}

void MissionRunner::runSafety() {
  const std::string robot = status().robot_id();
  const std::string id = status().mission_id();
  bool skip = false;
  // What the safety steps did (or that they were skipped), after the failure.
  std::string notes;
  {
    absl::MutexLock lock(&mutex_);
    if (status_.state() != v1::MISSION_STATE_ABORTED) status_.set_state(v1::MISSION_STATE_FAILED);
    status_.set_in_safety_steps(true);
    skip = skip_safety_;
    if (skip) {
      notes = "; safety steps skipped (the vehicle is landed by the coordinator's safety action)";
    }
    status_.set_message(failure_ + notes);
  }
  publish();
  const std::vector<MissionStep> no_steps;
  const std::vector<MissionStep>& safety = skip ? no_steps : spec_.safety;
  for (size_t i = 0; i < safety.size(); ++i) {
    const MissionStep& step = safety[i];
    auto params = beliefs_.resolve(step.parameters);
    absl::StatusOr<std::string> activation =
        params.ok()
            ? actions_.activate(robot, step.behavior, *params, id + "/safety/" + std::to_string(i))
            : absl::StatusOr<std::string>(params.status());
    if (!activation.ok()) {
      notes += "; safety step " + step.behavior +
               " refused: " + std::string(activation.status().message());
      continue;
    }
    for (;;) {
      {
        absl::MutexLock lock(&mutex_);
        if (quit_) return;  // resumed by the next coordinator
      }
      auto finished = actions_.awaitFinished(robot, *activation, kPoll);
      if (!finished) continue;
      if (finished->cause != v1::TERMINATION_CAUSE_GOAL_ACHIEVED) {
        notes += "; safety step " + step.behavior + " finished " + causeName(finished->cause) +
                 ": " + finished->message;
      }
      break;
    }
  }
  deactivateRecurrent();
  {
    absl::MutexLock lock(&mutex_);
    status_.set_in_safety_steps(false);
    status_.set_message(failure_ + notes);
    *status_.mutable_end_time() = TimeUtil::GetCurrentTime();
    done_ = true;
  }
  publish();
}

void MissionRunner::deactivateRecurrent() {
  const std::string robot = status().robot_id();
  for (auto it = recurrent_.rbegin(); it != recurrent_.rend(); ++it) {
    (void)actions_.deactivate(robot, it->first);
  }
}

std::optional<std::string> MissionRunner::recurrentFinished() {
  const std::string robot = status().robot_id();
  for (const auto& [behavior, activation] : recurrent_) {
    if (auto f = actions_.awaitFinished(robot, activation, std::chrono::milliseconds(0))) {
      return "recurrent behavior " + behavior + " finished " + causeName(f->cause) +
             (f->message.empty() ? "" : ": " + f->message);
    }
  }
  return std::nullopt;
}

MissionRunner::Flow MissionRunner::runList(const std::vector<MissionStep>& steps,
                                           const Position& prefix, MissionNode::Kind kind,
                                           int call_attempt, Position resume_path, int iteration) {
  size_t start = 0;
  Position tail;
  if (!resume_path.empty()) {
    start = static_cast<size_t>(resume_path.front().index);
    tail.assign(resume_path.begin() + 1, resume_path.end());
  }
  for (size_t i = start; i < steps.size(); ++i) {
    Position path = prefix;
    path.push_back({kind, static_cast<int>(i), call_attempt, iteration});
    const bool resumed_here = i == start && !resume_path.empty();
    const Flow flow = runStep(steps[i], path, resumed_here ? tail : Position{});
    if (resumed_here) resume_from_.clear();  // resumed: live from here
    if (flow != Flow::kDone) return flow;
  }
  return Flow::kDone;
}

bool MissionRunner::conditionHolds(const BeliefCondition& c) const {
  const std::optional<v1::Belief> belief = beliefs_.get(c.key);
  if (c.exists.has_value()) return belief.has_value() == *c.exists;
  return belief.has_value() &&
         google::protobuf::util::MessageDifferencer::Equals(belief->value(), *c.equals);
}

void MissionRunner::rememberAll(const MissionStep& step) {
  if (step.remember.fields().empty()) return;
  absl::StatusOr<google::protobuf::Struct> values = withItems(step.remember);
  if (values.ok()) values = beliefs_.resolve(*values);
  const std::string writer = "mission:" + status().mission_id();
  if (!values.ok()) return;
  for (const auto& [key, value] : values->fields()) (void)beliefs_.write(key, value, writer);
}

const MissionAction* MissionRunner::actionFor(const MissionStep& step,
                                              const std::string& cause) const {
  if (auto it = step.on.find(cause); it != step.on.end()) return &it->second;
  if (cause == "GOAL_ACHIEVED") return nullptr;  // continue
  if (auto it = step.on.find("otherwise"); it != step.on.end()) return &it->second;
  static const MissionAction kAbort{};
  return &kAbort;
}

MissionRunner::Flow MissionRunner::waitWhilePaused() {
  mutex_.Lock();
  if (pause_requested_ && status_.state() == v1::MISSION_STATE_RUNNING) {
    status_.set_state(v1::MISSION_STATE_PAUSED);
    mutex_.Unlock();
    publish();
    mutex_.Lock();
  }
  const auto paused = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return quit_ || abort_requested_ || !pause_requested_;
  };
  mutex_.Await(absl::Condition(&paused));
  Flow flow = Flow::kDone;
  bool resumed = false;
  if (quit_) {
    flow = Flow::kQuit;
  } else if (abort_requested_) {
    flow = Flow::kAbortRequested;
  } else if (status_.state() == v1::MISSION_STATE_PAUSED) {
    status_.set_state(v1::MISSION_STATE_RUNNING);
    resumed = true;
  }
  mutex_.Unlock();
  if (resumed) publish();
  return flow;
}

MissionRunner::Flow MissionRunner::waitFor(const MissionStep& step,
                                           const std::string& activation_id,
                                           FinishedActivation* finished) {
  const std::string robot = status().robot_id();
  bool paused_behavior = false;
  for (;;) {
    bool quit, abort, pause;
    {
      absl::MutexLock lock(&mutex_);
      quit = quit_;
      abort = abort_requested_;
      pause = pause_requested_;
    }
    if (quit) return Flow::kQuit;
    if (abort) {
      (void)actions_.deactivate(robot, step.behavior);
      return Flow::kAbortRequested;
    }
    if (pause != paused_behavior) {
      absl::Status s =
          pause ? actions_.pause(robot, step.behavior) : actions_.resume(robot, step.behavior);
      paused_behavior = pause;
      {
        absl::MutexLock lock(&mutex_);
        status_.set_state(pause ? v1::MISSION_STATE_PAUSED : v1::MISSION_STATE_RUNNING);
        if (!s.ok())
          status_.set_message(std::string(pause ? "pausing " : "resuming ") + step.behavior + ": " +
                              std::string(s.message()));
      }
      publish();
    }
    if (auto f = actions_.awaitFinished(robot, activation_id, kPoll)) {
      *finished = *f;
      return Flow::kDone;
    }
    if (auto r = recurrentFinished()) {
      (void)actions_.deactivate(robot, step.behavior);
      failure_ = *r;
      failed_cause_.clear();  // not a step's cause: a call does not branch on it
      return Flow::kAbort;
    }
  }
}

MissionRunner::Flow MissionRunner::runStep(const MissionStep& step, const Position& path,
                                           Position resume_tail) {
  const std::string robot = status().robot_id();
  const std::string label = stepLabel(step, path);

  // The latest record of this step, when resuming into it.
  std::optional<v1::MissionStepRecord> recorded;
  for (auto it = resume_from_.rbegin(); it != resume_from_.rend(); ++it) {
    if (positionOf(*it) == path) {
      recorded = *it;
      break;
    }
  }
  const bool resume_here =
      !resume_from_.empty() && startsWith(positionOf(resume_from_.back()), path);
  if (!resume_here) recorded.reset();

  if (!resume_tail.empty() && recorded &&
      resume_tail.front().kind == MissionNode::Kind::kFallback) {
    // We were inside this step's fallback: the recorded cause says which.
    const std::string cause = recorded->state() == v1::MISSION_STEP_STATE_REFUSED
                                  ? "REFUSED"
                                  : causeName(recorded->cause());
    const MissionAction* action = actionFor(step, cause);
    while (action && action->kind == MissionAction::Kind::kRetry) action = action->then.get();
    if (action && action->kind == MissionAction::Kind::kFallback) {
      return runList(action->fallback, path, MissionNode::Kind::kFallback, 0, resume_tail);
    }
  }

  if (Flow f = waitWhilePaused(); f != Flow::kDone) return f;

  if (step.condition && !(recorded && recorded->state() == v1::MISSION_STEP_STATE_SKIPPED)) {
    if (!conditionHolds(*step.condition)) {
      v1::MissionStepRecord skipped = recordAt(path);
      skipped.set_name(step.name);
      skipped.set_behavior(step.behavior);
      skipped.set_call(step.call);
      skipped.set_state(v1::MISSION_STEP_STATE_SKIPPED);
      skipped.set_message("condition on belief '" + step.condition->key + "' does not hold");
      addRecord(std::move(skipped));
      return Flow::kDone;
    }
  } else if (recorded && recorded->state() == v1::MISSION_STEP_STATE_SKIPPED) {
    return Flow::kDone;
  }
  if (!step.call.empty() || step.loop) {
    return runCall(step, path, std::move(resume_tail), recorded);
  }
  if (step.behavior.empty()) {
    rememberAll(step);
    return Flow::kDone;
  }

  int attempt = recorded ? recorded->attempt() : 1;
  for (;;) {
    const std::string request_id =
        status().mission_id() + "/" + nodeText(path) + "/attempt/" + std::to_string(attempt);
    std::string cause;
    std::string message;
    FinishedActivation finished;
    int index = -1;
    const bool reuse =
        recorded && recorded->attempt() == attempt && recorded->request_id() == request_id;
    if (reuse && (recorded->state() == v1::MISSION_STEP_STATE_FINISHED ||
                  recorded->state() == v1::MISSION_STEP_STATE_REFUSED)) {
      // It ended before the restart: follow its recorded cause.
      cause = recorded->state() == v1::MISSION_STEP_STATE_REFUSED ? "REFUSED"
                                                                  : causeName(recorded->cause());
      message = recorded->message();
      finished.cause = recorded->cause();
    } else {
      if (reuse) {
        absl::MutexLock lock(&mutex_);
        for (int i = status_.steps_size() - 1; i >= 0; --i) {
          if (status_.steps(i).request_id() == request_id) {
            index = i;
            break;
          }
        }
      }
      absl::StatusOr<google::protobuf::Struct> params = withItems(step.parameters);
      if (params.ok()) params = beliefs_.resolve(*params);
      if (index < 0) {
        v1::MissionStepRecord record = recordAt(path);
        record.set_name(step.name);
        record.set_behavior(step.behavior);
        record.set_attempt(attempt);
        record.set_request_id(request_id);
        record.set_state(v1::MISSION_STEP_STATE_RUNNING);
        if (params.ok()) *record.mutable_parameters() = *params;
        index = addRecord(std::move(record));  // journaled before the activation
      }
      absl::StatusOr<std::string> activation =
          params.ok() ? actions_.activate(robot, step.behavior, *params, request_id)
                      : absl::StatusOr<std::string>(params.status());
      if (!activation.ok()) {
        cause = "REFUSED";
        message = std::string(activation.status().message());
        updateRecord(index, [&](v1::MissionStepRecord& r) {
          r.set_state(v1::MISSION_STEP_STATE_REFUSED);
          r.set_message(message);
        });
      } else {
        updateRecord(index, [&](v1::MissionStepRecord& r) { r.set_activation_id(*activation); });
        const Flow flow = waitFor(step, *activation, &finished);
        if (flow == Flow::kAbortRequested) {
          updateRecord(index, [&](v1::MissionStepRecord& r) {
            r.set_state(v1::MISSION_STEP_STATE_FINISHED);
            r.set_cause(v1::TERMINATION_CAUSE_INTERRUPTED);
            r.set_message("mission aborted");
          });
        }
        if (flow != Flow::kDone) return flow;
        cause = causeName(finished.cause);
        message = finished.message;
        updateRecord(index, [&](v1::MissionStepRecord& r) {
          r.set_state(v1::MISSION_STEP_STATE_FINISHED);
          r.set_cause(finished.cause);
          r.set_message(message);
        });
        // An abort requested while the step was finishing (the safety
        // policy stands the robot down, which ends the step) wins over the
        // step's own outcome; the record keeps the real cause.
        bool aborting = false;
        {
          absl::MutexLock lock(&mutex_);
          aborting = abort_requested_;
        }
        if (aborting) return Flow::kAbortRequested;
      }
    }
    recorded.reset();
    if (std::optional<Flow> flow = afterCause(step, path, cause, message, &attempt)) return *flow;
  }
}

std::optional<MissionRunner::Flow> MissionRunner::afterCause(const MissionStep& step,
                                                             const Position& path,
                                                             const std::string& cause,
                                                             const std::string& message,
                                                             int* attempt) {
  const MissionAction* action = actionFor(step, cause);
  if (action == nullptr || action->kind == MissionAction::Kind::kContinue) {
    if (cause == "GOAL_ACHIEVED") rememberAll(step);
    return Flow::kDone;
  }
  const std::string what = stepLabel(step, path) + " " +
                           (cause == "REFUSED" ? "was refused" : "finished " + cause) +
                           (message.empty() ? "" : ": " + message);
  if (action->kind == MissionAction::Kind::kRetry) {
    if (*attempt <= action->retries) {
      ++*attempt;
      return std::nullopt;
    }
    action = action->then.get();
    if (action == nullptr || action->kind == MissionAction::Kind::kAbort) {
      failure_ = what + " (after " + std::to_string(*attempt) + " attempts)";
      failed_cause_ = cause;
      return Flow::kAbort;
    }
    if (action->kind == MissionAction::Kind::kContinue) return Flow::kDone;
  }
  if (action->kind == MissionAction::Kind::kAbort) {
    failure_ = what;
    failed_cause_ = cause;
    return Flow::kAbort;
  }
  return runList(action->fallback, path, MissionNode::Kind::kFallback, 0, {});  // kFallback
}

MissionRunner::Flow MissionRunner::runCall(const MissionStep& step, const Position& path,
                                           Position resume_tail,
                                           std::optional<v1::MissionStepRecord> recorded) {
  int attempt = recorded ? recorded->attempt() : 1;
  for (;;) {
    std::string cause;
    std::string message;
    const bool reuse = recorded && recorded->attempt() == attempt;
    if (reuse && (recorded->state() == v1::MISSION_STEP_STATE_FINISHED ||
                  recorded->state() == v1::MISSION_STEP_STATE_REFUSED)) {
      // It ended before the restart: follow its recorded cause.
      cause = recorded->state() == v1::MISSION_STEP_STATE_REFUSED ? "REFUSED"
                                                                  : causeName(recorded->cause());
      message = recorded->message();
    } else {
      const std::string node = nodeText(path);
      int index = -1;
      if (reuse) {
        absl::MutexLock lock(&mutex_);
        for (int i = status_.steps_size() - 1; i >= 0; --i) {
          if (status_.steps(i).node() == node && status_.steps(i).attempt() == attempt) {
            index = i;
            break;
          }
        }
      }
      if (index < 0) {
        v1::MissionStepRecord record = recordAt(path);
        record.set_name(step.name);
        record.set_call(step.call);
        record.set_attempt(attempt);
        record.set_state(v1::MISSION_STEP_STATE_RUNNING);
        *record.mutable_parameters() = step.with;
        if (step.loop) record.set_loop(loopText(*step.loop));
        index = addRecord(std::move(record));
      }
      // Resuming inside this attempt's steps: where it was.
      Position tail;
      if (reuse && !resume_tail.empty() &&
          (resume_tail.front().kind == MissionNode::Kind::kCall ||
           resume_tail.front().kind == MissionNode::Kind::kIteration) &&
          resume_tail.front().call_attempt == attempt) {
        tail = resume_tail;
      }
      resume_tail.clear();
      Flow flow = Flow::kDone;
      std::optional<std::string> ended = runBody(step, path, attempt, tail, &message, &flow);
      if (!ended) {
        if (flow == Flow::kAbortRequested) {
          updateRecord(index, [&](v1::MissionStepRecord& r) {
            r.set_state(v1::MISSION_STEP_STATE_FINISHED);
            r.set_cause(v1::TERMINATION_CAUSE_INTERRUPTED);
            r.set_message("mission aborted");
          });
        }
        return flow;  // the mission stops, aborts or fails for another reason
      }
      cause = *ended;
      updateRecord(index, [&](v1::MissionStepRecord& r) {
        if (cause == "REFUSED") {
          r.set_state(v1::MISSION_STEP_STATE_REFUSED);
        } else {
          r.set_state(v1::MISSION_STEP_STATE_FINISHED);
          v1::TerminationCause parsed = v1::TERMINATION_CAUSE_UNSPECIFIED;
          v1::TerminationCause_Parse("TERMINATION_CAUSE_" + cause, &parsed);
          r.set_cause(parsed);
        }
        r.set_message(message);
      });
    }
    recorded.reset();
    failed_cause_.clear();
    if (std::optional<Flow> flow = afterCause(step, path, cause, message, &attempt)) return *flow;
  }
}

std::optional<std::string> MissionRunner::runBody(const MissionStep& step, const Position& path,
                                                  int attempt, const Position& tail,
                                                  std::string* message, Flow* flow) {
  if (step.loop) return runLoop(step, path, attempt, tail, message, flow);
  failed_cause_.clear();
  *flow = runList(step.body, path, MissionNode::Kind::kCall, attempt, tail);
  if (*flow == Flow::kDone) return "GOAL_ACHIEVED";
  if (*flow == Flow::kAbort && !failed_cause_.empty()) {
    // A step of the sub-mission failed it: the call ends with its cause.
    *message = failure_;
    return failed_cause_;
  }
  return std::nullopt;
}

std::optional<std::string> MissionRunner::runLoop(const MissionStep& step, const Position& path,
                                                  int attempt, const Position& tail,
                                                  std::string* message, Flow* flow) {
  const MissionLoop& loop = *step.loop;
  google::protobuf::ListValue items = loop.items;
  int count = loop.times;
  if (loop.kind == MissionLoop::Kind::kForEach) {
    if (!loop.belief.empty()) {
      // The belief's list as it is when the loop starts (each attempt).
      const std::optional<v1::Belief> belief = beliefs_.get(loop.belief);
      if (!belief || !belief->value().has_list_value()) {
        *message = "for_each: belief '" + loop.belief + "' " +
                   (belief ? "is not a list" : "is not in memory");
        return "REFUSED";
      }
      items = belief->value().list_value();
      if (items.values_size() > loop.max_items) {
        *message = "for_each: belief '" + loop.belief + "' holds " +
                   std::to_string(items.values_size()) + " items, more than max_items " +
                   std::to_string(loop.max_items);
        return "REFUSED";
      }
    }
    count = items.values_size();
  }
  int first = 0;
  if (!tail.empty() && tail.front().kind == MissionNode::Kind::kIteration) {
    first = tail.front().iteration;
  }
  for (int i = first; i < count; ++i) {
    if (loop.kind == MissionLoop::Kind::kForEach) items_.emplace_back(loop.as, items.values(i));
    failed_cause_.clear();
    *flow = runList(step.body, path, MissionNode::Kind::kIteration, attempt,
                    i == first ? tail : Position{}, i);
    if (loop.kind == MissionLoop::Kind::kForEach) items_.pop_back();
    if (*flow == Flow::kAbort && !failed_cause_.empty()) {
      *message = failure_;
      return failed_cause_;
    }
    if (*flow != Flow::kDone) return std::nullopt;
    if (loop.kind == MissionLoop::Kind::kUntil && conditionHolds(*loop.until)) {
      return "GOAL_ACHIEVED";
    }
  }
  if (loop.kind == MissionLoop::Kind::kUntil) {
    *message = "repeat: belief '" + loop.until->key + "' did not come to hold in " +
               std::to_string(count) + " iterations";
    return "WRONG_PROGRESS";
  }
  return "GOAL_ACHIEVED";
}

absl::StatusOr<google::protobuf::Struct> MissionRunner::withItems(
    const google::protobuf::Struct& parameters) {
  if (items_.empty()) return parameters;
  google::protobuf::Value whole;
  *whole.mutable_struct_value() = parameters;
  const absl::Status s = substituteTokens(
      &whole, "each",
      [this](const std::string& name) -> const google::protobuf::Value* {
        for (auto it = items_.rbegin(); it != items_.rend(); ++it) {  // the innermost loop's first
          if (it->first == name) return &it->second;
        }
        return nullptr;
      },
      [](const std::string& name) { return "${each." + name + "} is no loop's item here"; });
  if (!s.ok()) return s;
  return whole.struct_value();
}

}  // namespace behaviorlib::coordinator
