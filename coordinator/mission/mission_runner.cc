#include "coordinator/mission/mission_runner.h"

#include <google/protobuf/util/message_differencer.h>
#include <google/protobuf/util/time_util.h>

#include <cmath>
#include <sstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/parameters.h"

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

std::string parallelText(const MissionParallel& parallel) {
  return std::string(parallel.any ? "any" : "all") + " of " +
         std::to_string(parallel.branches.size()) + " branches";
}

std::string waitText(const MissionWait& wait) {
  if (!wait.belief) return "step '" + wait.step + "' achieved";
  return "belief '" + wait.belief->key + "' " +
         (wait.belief->exists ? (*wait.belief->exists ? "exists" : "does not exist")
                              : "equals the value given");
}

// A record at `path`: its node, and its v1 path where it has one (no call).
v1::MissionStepRecord recordAt(const Position& path) {
  v1::MissionStepRecord record;
  record.set_node(nodeText(path));
  bool plain = true;
  for (const MissionNode& n : path) {
    plain = plain && n.kind != MissionNode::Kind::kCall && n.kind != MissionNode::Kind::kBranch;
  }
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
      case MissionNode::Kind::kBranch:
        out += "/attempt/" + std::to_string(n.call_attempt) + "/branch/" +
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
               (parts[i + 2] == "iteration" || parts[i + 2] == "branch") &&
               parts[i + 4] == "steps" && number(parts[i + 1], &n.call_attempt) &&
               number(parts[i + 3], &n.iteration) && number(parts[i + 5], &n.index)) {
      n.kind =
          parts[i + 2] == "branch" ? MissionNode::Kind::kBranch : MissionNode::Kind::kIteration;
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
                             OnChange on_change, Options options)
    : spec_(std::move(spec)),
      robot_(robot_id),
      actions_(actions),
      beliefs_(beliefs),
      on_change_(std::move(on_change)),
      clock_(options.clock != nullptr ? *options.clock : steady_clock_),
      vehicles_(options.vehicles) {
  status_.set_mission_id(std::move(mission_id));
  status_.set_name(spec_.name);
  status_.set_robot_id(std::move(robot_id));
  for (const std::string& robot : missionRobots(spec_, robot_)) status_.add_robot_ids(robot);
  status_.set_file(spec_.file);
  status_.set_source(std::move(source));
  status_.mutable_imports()->insert(spec_.imports.begin(), spec_.imports.end());
  status_.set_state(v1::MISSION_STATE_RUNNING);
  *status_.mutable_start_time() = TimeUtil::GetCurrentTime();
}

MissionRunner::MissionRunner(MissionSpec spec, const v1::MissionStatus& status,
                             MissionActions& actions, BeliefStore& beliefs, OnChange on_change,
                             Options options)
    : spec_(std::move(spec)),
      robot_(status.robot_id()),
      actions_(actions),
      beliefs_(beliefs),
      on_change_(std::move(on_change)),
      status_(status),
      clock_(options.clock != nullptr ? *options.clock : steady_clock_),
      vehicles_(options.vehicles) {
  resuming_ = true;
  resume_from_.assign(status.steps().begin(), status.steps().end());
  pause_requested_ = status.state() == v1::MISSION_STATE_PAUSED;
  if (status_.robot_ids().empty()) {
    for (const std::string& robot : missionRobots(spec_, robot_)) status_.add_robot_ids(robot);
  }
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

absl::Status MissionRunner::abort(const std::string& reason, bool run_safety,
                                  const std::string& robot) {
  absl::MutexLock lock(&mutex_);
  if (done_ || status_.state() == v1::MISSION_STATE_FAILED ||
      status_.state() == v1::MISSION_STATE_ABORTED) {
    return absl::FailedPreconditionError("mission '" + status_.mission_id() + "' already ended (" +
                                         v1::MissionState_Name(status_.state()) + ")");
  }
  abort_requested_ = true;
  abort_reason_ = reason.empty() ? "aborted by request" : reason;
  if (!run_safety) {
    // A fleet mission's other robots still run their safety steps.
    if (robot.empty() || status_.robot_ids_size() <= 1) {
      skip_safety_ = true;
    } else {
      skip_safety_of_.push_back(robot);
    }
  }
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

int MissionRunner::findRecord(const std::string& node, int attempt) const {
  absl::MutexLock lock(&mutex_);
  for (int i = status_.steps_size() - 1; i >= 0; --i) {
    if (status_.steps(i).node() == node && status_.steps(i).attempt() == attempt) return i;
  }
  return -1;
}

void MissionRunner::recordStopped(int index, Flow flow) {
  if (flow != Flow::kAbortRequested && flow != Flow::kInterrupted) return;
  updateRecord(index, [&](v1::MissionStepRecord& r) {
    r.set_state(v1::MISSION_STEP_STATE_FINISHED);
    r.set_cause(v1::TERMINATION_CAUSE_INTERRUPTED);
    r.set_message(flow == Flow::kAbortRequested
                      ? "mission aborted"
                      : "interrupted: another branch decided the parallel step");
  });
}

const std::string& MissionRunner::robotOf(const MissionStep& step) const {
  return step.robot.empty() ? robot_ : step.robot;
}

bool MissionRunner::interruptedLocked(const Track& t) const {
  for (int id : t.parallels) {
    if (auto it = parallels_.find(id); it != parallels_.end() && it->second) return true;
  }
  return false;
}

bool MissionRunner::interrupted(const Track& t) const {
  if (t.parallels.empty()) return false;
  absl::MutexLock lock(&mutex_);
  return interruptedLocked(t);
}

std::string MissionRunner::stepLabel(const MissionStep& step, const Position& path) const {
  std::string label = step.name.empty() ? nodeText(path) : "'" + step.name + "'";
  if (!step.behavior.empty()) label += " (" + step.behavior + ")";
  if (!step.call.empty()) label += " (call " + step.call + ")";
  if (step.loop) label += " (" + loopText(*step.loop) + ")";
  if (step.parallel) label += " (parallel, " + parallelText(*step.parallel) + ")";
  if (step.wait) label += " (wait for " + waitText(*step.wait) + ")";
  if (!step.robot.empty() && step.robot != robot_) label += " on " + step.robot;
  return "step " + label;
}

void MissionRunner::run() {
  const std::string id = status().mission_id();
  const bool safety_pending = status().in_safety_steps();

  // Recurrent behaviors: the same request ids after a restart give back the
  // same activations.
  for (size_t i = 0; i < spec_.recurrent.size(); ++i) {
    const MissionStep& r = spec_.recurrent[i];
    auto params = beliefs_.resolve(r.parameters);
    absl::StatusOr<std::string> activation =
        params.ok() ? actions_.activate(robotOf(r), r.behavior, *params,
                                        id + "/recurrent/" + std::to_string(i))
                    : absl::StatusOr<std::string>(params.status());
    if (!activation.ok()) {
      if (safety_pending) continue;
      runSafety("recurrent behavior " + r.behavior + (r.robot.empty() ? "" : " on " + r.robot) +
                " was refused: " + std::string(activation.status().message()));
      return;
    }
    recurrent_.push_back({robotOf(r), r.behavior, *activation});
  }

  Track main;
  Flow flow = Flow::kAbort;
  if (safety_pending) {
    main.failure = status().message();
  } else {
    Position resume_path;
    if (resuming_ && !resume_from_.empty()) resume_path = positionOf(resume_from_.back());
    if (!resuming_ || resume_from_.empty()) publish();  // the first record of a new mission
    main.resume_from = resume_from_;
    flow = runList(spec_.steps, {}, MissionNode::Kind::kStep, 0, resume_path, 0, main);
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
    case Flow::kInterrupted:  // no parallel step around the main sequence: not reached
    {
      absl::MutexLock lock(&mutex_);
      if (main.failure.empty()) main.failure = abort_reason_;
      status_.set_state(v1::MISSION_STATE_ABORTED);
    }
      runSafety(main.failure);
      return;
    case Flow::kAbort:
      runSafety(main.failure);
      return;
  }
}

void MissionRunner::runSafety(const std::string& failure) {
  const std::string id = status().mission_id();
  std::vector<std::string> skipped;
  bool skip_all = false;
  {
    absl::MutexLock lock(&mutex_);
    if (status_.state() != v1::MISSION_STATE_ABORTED) status_.set_state(v1::MISSION_STATE_FAILED);
    status_.set_in_safety_steps(true);
    skip_all = skip_safety_;
    skipped = skip_safety_of_;
    status_.set_message(failure);
  }
  // What the safety steps did (or that they were skipped), after the failure.
  absl::Mutex notes_mutex;
  std::string notes;
  if (skip_all) {
    notes = "; safety steps skipped (the vehicle is landed by the coordinator's safety action)";
  }
  for (const std::string& robot : skipped) {
    notes += "; " + robot +
             "'s safety steps skipped (the vehicle is landed by the coordinator's safety action)";
  }
  if (!notes.empty()) {
    absl::MutexLock lock(&mutex_);
    status_.set_message(failure + notes);
  }
  publish();
  // Each robot's safety steps in order, the robots at once.
  std::map<std::string, std::vector<size_t>> by_robot;
  for (size_t i = 0; i < spec_.safety.size() && !skip_all; ++i) {
    const std::string& robot = robotOf(spec_.safety[i]);
    if (std::find(skipped.begin(), skipped.end(), robot) == skipped.end()) {
      by_robot[robot].push_back(i);
    }
  }
  std::atomic<bool> quit{false};
  auto run_robot = [&](const std::string& robot, const std::vector<size_t>& steps) {
    for (size_t i : steps) {
      const MissionStep& step = spec_.safety[i];
      auto params = beliefs_.resolve(step.parameters);
      absl::StatusOr<std::string> activation =
          params.ok() ? actions_.activate(robot, step.behavior, *params,
                                          id + "/safety/" + std::to_string(i))
                      : absl::StatusOr<std::string>(params.status());
      const std::string what = "safety step " + step.behavior +
                               (robot == robot_ && step.robot.empty() ? "" : " on " + robot);
      if (!activation.ok()) {
        absl::MutexLock lock(&notes_mutex);
        notes += "; " + what + " refused: " + std::string(activation.status().message());
        continue;
      }
      for (;;) {
        {
          absl::MutexLock lock(&mutex_);
          if (quit_) {
            quit = true;
            return;  // resumed by the next coordinator
          }
        }
        auto finished = actions_.awaitFinished(robot, *activation, kPoll);
        if (!finished) continue;
        if (finished->cause != v1::TERMINATION_CAUSE_GOAL_ACHIEVED) {
          absl::MutexLock lock(&notes_mutex);
          notes +=
              "; " + what + " finished " + causeName(finished->cause) + ": " + finished->message;
        }
        break;
      }
    }
  };
  std::vector<std::thread> robots;
  for (const auto& [robot, steps] : by_robot) {
    if (robots.size() + 1 == by_robot.size()) {
      run_robot(robot, steps);  // the last one on this thread
    } else {
      robots.emplace_back(run_robot, robot, steps);
    }
  }
  for (auto& thread : robots) thread.join();
  if (quit) return;
  deactivateRecurrent();
  {
    absl::MutexLock lock(&mutex_);
    absl::MutexLock notes_lock(&notes_mutex);
    status_.set_in_safety_steps(false);
    status_.set_message(failure + notes);
    *status_.mutable_end_time() = TimeUtil::GetCurrentTime();
    done_ = true;
  }
  publish();
}

void MissionRunner::deactivateRecurrent() {
  for (auto it = recurrent_.rbegin(); it != recurrent_.rend(); ++it) {
    (void)actions_.deactivate(it->robot, it->behavior);
  }
}

std::optional<std::string> MissionRunner::recurrentFinished() {
  for (const Recurrent& r : recurrent_) {
    if (auto f = actions_.awaitFinished(r.robot, r.activation_id, std::chrono::milliseconds(0))) {
      return "recurrent behavior " + r.behavior + (r.robot == robot_ ? "" : " on " + r.robot) +
             " finished " + causeName(f->cause) + (f->message.empty() ? "" : ": " + f->message);
    }
  }
  return std::nullopt;
}

MissionRunner::Flow MissionRunner::runList(const std::vector<MissionStep>& steps,
                                           const Position& prefix, MissionNode::Kind kind,
                                           int call_attempt, Position resume_path, int iteration,
                                           Track& t) {
  size_t start = 0;
  Position tail;
  if (!resume_path.empty()) {
    start = static_cast<size_t>(resume_path.front().index);
    tail.assign(resume_path.begin() + 1, resume_path.end());
  }
  for (size_t i = start; i < steps.size(); ++i) {
    if (interrupted(t)) return Flow::kInterrupted;
    Position path = prefix;
    path.push_back({kind, static_cast<int>(i), call_attempt, iteration});
    const bool resumed_here = i == start && !resume_path.empty();
    const Flow flow = runStep(steps[i], path, resumed_here ? tail : Position{}, t);
    if (resumed_here) t.resume_from.clear();  // resumed: live from here
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

bool MissionRunner::waitHolds(const MissionWait& wait) const {
  if (wait.belief) return conditionHolds(*wait.belief);
  absl::MutexLock lock(&mutex_);
  for (const v1::MissionStepRecord& r : status_.steps()) {
    if (r.name() == wait.step && r.state() == v1::MISSION_STEP_STATE_FINISHED &&
        r.cause() == v1::TERMINATION_CAUSE_GOAL_ACHIEVED) {
      return true;
    }
  }
  return false;
}

void MissionRunner::rememberAll(const MissionStep& step, const Track& t) {
  if (step.remember.fields().empty()) return;
  absl::StatusOr<google::protobuf::Struct> values = withItems(step.remember, t);
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

MissionRunner::Flow MissionRunner::waitWhilePaused(const Track& t) {
  mutex_.Lock();
  if (pause_requested_ && status_.state() == v1::MISSION_STATE_RUNNING) {
    status_.set_state(v1::MISSION_STATE_PAUSED);
    mutex_.Unlock();
    publish();
    mutex_.Lock();
  }
  const auto paused = [this, &t]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return quit_ || abort_requested_ || !pause_requested_ || interruptedLocked(t);
  };
  mutex_.Await(absl::Condition(&paused));
  Flow flow = Flow::kDone;
  bool resumed = false;
  if (quit_) {
    flow = Flow::kQuit;
  } else if (abort_requested_) {
    flow = Flow::kAbortRequested;
  } else if (interruptedLocked(t)) {
    flow = Flow::kInterrupted;
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
                                           FinishedActivation* finished, Track& t) {
  const std::string& robot = robotOf(step);
  bool paused_behavior = false;
  std::map<std::string, TopicSeen> seen;  // the `when:` conditions' topics
  for (;;) {
    bool quit, abort, pause, stop_branch;
    {
      absl::MutexLock lock(&mutex_);
      quit = quit_;
      abort = abort_requested_;
      pause = pause_requested_;
      stop_branch = interruptedLocked(t);
    }
    if (quit) return Flow::kQuit;
    if (abort || stop_branch) {
      (void)actions_.deactivate(robot, step.behavior);
      return abort ? Flow::kAbortRequested : Flow::kInterrupted;
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
    if (!step.when.empty() && !pause) {
      if (auto ended = vehicleConditionHolds(step, &seen)) {
        // The condition ends the step: its behavior is deactivated (and its
        // own finished event, INTERRUPTED, is not the step's cause).
        (void)actions_.deactivate(robot, step.behavior);
        *finished = *ended;
        return Flow::kDone;
      }
    }
    if (auto r = recurrentFinished()) {
      (void)actions_.deactivate(robot, step.behavior);
      t.failure = *r;
      t.failed_cause.clear();  // not a step's cause: a call does not branch on it
      return Flow::kAbort;
    }
  }
}

std::optional<FinishedActivation> MissionRunner::vehicleConditionHolds(
    const MissionStep& step, std::map<std::string, TopicSeen>* seen) {
  const std::string& robot = robotOf(step);
  const TimePoint now = clock_.now();
  auto cause = [](const std::string& name) {
    v1::TerminationCause parsed = v1::TERMINATION_CAUSE_UNSPECIFIED;
    v1::TerminationCause_Parse("TERMINATION_CAUSE_" + name, &parsed);
    return parsed;
  };
  // Whether the topic's sample is fresh: its stamp advanced within
  // max_age_s (counted from the step's first look when there is none yet).
  auto fresh = [&](const std::string& topic, const v1::Header* header, double max_age_s,
                   FinishedActivation* stale) {
    const int64_t stamp_ns =
        header == nullptr ? -1 : header->stamp().seconds() * 1000000000LL + header->stamp().nanos();
    auto [it, added] = seen->try_emplace(topic, TopicSeen{stamp_ns, now});
    if (!added && stamp_ns != it->second.stamp_ns) it->second = {stamp_ns, now};
    const double age_s = toSeconds(now - it->second.since);
    if (age_s <= max_age_s) return true;
    stale->cause = v1::TERMINATION_CAUSE_PROCESS_FAILURE;
    stale->message = "condition on the vehicle: " + topic +
                     (stamp_ns < 0 ? " has no sample" : " did not advance") + " for " +
                     params::numberText(std::round(age_s * 100) / 100) + " s (limit " +
                     params::numberText(max_age_s) + " s)";
    return false;
  };
  for (const VehicleCondition& c : step.when) {
    FinishedActivation ended;
    if (vehicles_ == nullptr) {
      ended.cause = v1::TERMINATION_CAUSE_PROCESS_FAILURE;
      ended.message =
          "condition on the vehicle: the coordinator reads no vehicle topics (no --channel)";
      return ended;
    }
    if (c.kind == VehicleCondition::Kind::kBatteryBelow) {
      const std::string topic = "robots/" + robot + "/flight_state";
      absl::StatusOr<v1::FlightStatus> status = vehicles_->flightStatus(robot);
      if (!fresh(topic, status.ok() ? &status->header() : nullptr, c.max_age_s, &ended)) {
        return ended;
      }
      if (status.ok() && status->battery_ratio() < c.battery_ratio) {
        ended.cause = cause(c.ends);
        ended.message = "condition on the vehicle: battery " +
                        params::numberText(std::round(status->battery_ratio() * 1000) / 1000) +
                        " below " + params::numberText(c.battery_ratio);
        return ended;
      }
    } else {
      const std::string topic = "robots/" + robot + "/self_localization/pose";
      absl::StatusOr<v1::PoseStamped> pose = vehicles_->poseEstimate(robot);
      if (!fresh(topic, pose.ok() ? &pose->header() : nullptr, c.max_age_s, &ended)) return ended;
      if (pose.ok()) {
        const auto& p = pose->pose().position_m();
        const double d =
            std::hypot(p.x() - c.point_m[0], p.y() - c.point_m[1], p.z() - c.point_m[2]);
        if (d < c.radius_m) {
          ended.cause = cause(c.ends);
          ended.message =
              "condition on the vehicle: " + params::numberText(std::round(d * 100) / 100) +
              " m from (" + params::numberText(c.point_m[0]) + ", " +
              params::numberText(c.point_m[1]) + ", " + params::numberText(c.point_m[2]) +
              "), within " + params::numberText(c.radius_m) + " m";
          return ended;
        }
      }
    }
  }
  return std::nullopt;
}

MissionRunner::Flow MissionRunner::runStep(const MissionStep& step, const Position& path,
                                           Position resume_tail, Track& t) {
  const std::string& robot = robotOf(step);

  // The latest record of this step, when resuming into it.
  std::optional<v1::MissionStepRecord> recorded;
  for (auto it = t.resume_from.rbegin(); it != t.resume_from.rend(); ++it) {
    if (positionOf(*it) == path) {
      recorded = *it;
      break;
    }
  }
  const bool resume_here =
      !t.resume_from.empty() && startsWith(positionOf(t.resume_from.back()), path);
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
      return runList(action->fallback, path, MissionNode::Kind::kFallback, 0, resume_tail, 0, t);
    }
  }

  if (Flow f = waitWhilePaused(t); f != Flow::kDone) return f;

  if (step.condition && !(recorded && recorded->state() == v1::MISSION_STEP_STATE_SKIPPED)) {
    if (!conditionHolds(*step.condition)) {
      v1::MissionStepRecord skipped = recordAt(path);
      skipped.set_name(step.name);
      skipped.set_behavior(step.behavior);
      skipped.set_call(step.call);
      skipped.set_robot_id(robot);
      skipped.set_state(v1::MISSION_STEP_STATE_SKIPPED);
      skipped.set_message("condition on belief '" + step.condition->key + "' does not hold");
      addRecord(std::move(skipped));
      return Flow::kDone;
    }
  } else if (recorded && recorded->state() == v1::MISSION_STEP_STATE_SKIPPED) {
    return Flow::kDone;
  }
  if (!step.call.empty() || step.loop || step.parallel) {
    return runCall(step, path, std::move(resume_tail), recorded, t);
  }
  if (step.wait) return runWait(step, path, recorded, t);
  if (step.behavior.empty()) {
    rememberAll(step, t);
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
      absl::StatusOr<google::protobuf::Struct> params = withItems(step.parameters, t);
      if (params.ok()) params = beliefs_.resolve(*params);
      if (index < 0) {
        v1::MissionStepRecord record = recordAt(path);
        record.set_name(step.name);
        record.set_behavior(step.behavior);
        record.set_robot_id(robot);
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
        const Flow flow = waitFor(step, *activation, &finished, t);
        recordStopped(index, flow);
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
    if (std::optional<Flow> flow = afterCause(step, path, cause, message, &attempt, t)) {
      return *flow;
    }
  }
}

std::optional<MissionRunner::Flow> MissionRunner::afterCause(const MissionStep& step,
                                                             const Position& path,
                                                             const std::string& cause,
                                                             const std::string& message,
                                                             int* attempt, Track& t) {
  const MissionAction* action = actionFor(step, cause);
  if (action == nullptr || action->kind == MissionAction::Kind::kContinue) {
    if (cause == "GOAL_ACHIEVED") rememberAll(step, t);
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
      t.failure = what + " (after " + std::to_string(*attempt) + " attempts)";
      t.failed_cause = cause;
      return Flow::kAbort;
    }
    if (action->kind == MissionAction::Kind::kContinue) return Flow::kDone;
  }
  if (action->kind == MissionAction::Kind::kAbort) {
    t.failure = what;
    t.failed_cause = cause;
    return Flow::kAbort;
  }
  return runList(action->fallback, path, MissionNode::Kind::kFallback, 0, {}, 0, t);
}

MissionRunner::Flow MissionRunner::runCall(const MissionStep& step, const Position& path,
                                           Position resume_tail,
                                           std::optional<v1::MissionStepRecord> recorded,
                                           Track& t) {
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
      int index = reuse ? findRecord(nodeText(path), attempt) : -1;
      if (index < 0) {
        v1::MissionStepRecord record = recordAt(path);
        record.set_name(step.name);
        record.set_call(step.call);
        record.set_robot_id(robotOf(step));
        record.set_attempt(attempt);
        record.set_state(v1::MISSION_STEP_STATE_RUNNING);
        *record.mutable_parameters() = step.with;
        if (step.loop) record.set_loop(loopText(*step.loop));
        if (step.parallel) record.set_parallel(parallelText(*step.parallel));
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
      std::optional<std::string> ended;
      if (step.parallel) {
        // Each branch finds where it was in the records below this attempt.
        if (!reuse) t.resume_from.clear();
        ended = runParallel(step, path, attempt, &message, &flow, t);
      } else {
        ended = runBody(step, path, attempt, tail, &message, &flow, t);
      }
      if (!ended) {
        recordStopped(index, flow);
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
    t.failed_cause.clear();
    if (std::optional<Flow> flow = afterCause(step, path, cause, message, &attempt, t)) {
      return *flow;
    }
  }
}

MissionRunner::Flow MissionRunner::runWait(const MissionStep& step, const Position& path,
                                           std::optional<v1::MissionStepRecord> recorded,
                                           Track& t) {
  const MissionWait& wait = *step.wait;
  int attempt = recorded ? recorded->attempt() : 1;
  for (;;) {
    std::string cause;
    std::string message;
    const bool reuse = recorded && recorded->attempt() == attempt;
    if (reuse && recorded->state() == v1::MISSION_STEP_STATE_FINISHED) {
      cause = causeName(recorded->cause());
      message = recorded->message();
    } else {
      // The limit counts from now (after a restart, from the resumption), in
      // the vehicles' time, and not while the mission is paused.
      Duration left = seconds(wait.timeout_s);
      TimePoint last = clock_.now();
      int index = reuse ? findRecord(nodeText(path), attempt) : -1;
      if (index < 0) {
        v1::MissionStepRecord record = recordAt(path);
        record.set_name(step.name);
        record.set_robot_id(robotOf(step));
        record.set_attempt(attempt);
        record.set_state(v1::MISSION_STEP_STATE_RUNNING);
        record.set_wait_for(waitText(wait));
        index = addRecord(std::move(record));
      }
      Flow flow = Flow::kDone;
      for (;;) {
        bool paused = false;
        {
          absl::MutexLock lock(&mutex_);
          if (quit_) return Flow::kQuit;
          if (abort_requested_) flow = Flow::kAbortRequested;
          if (flow == Flow::kDone && interruptedLocked(t)) flow = Flow::kInterrupted;
          paused = pause_requested_;
        }
        if (flow != Flow::kDone) break;
        if (paused) {
          flow = waitWhilePaused(t);
          if (flow == Flow::kQuit) return flow;
          if (flow != Flow::kDone) break;
          last = clock_.now();
          continue;
        }
        if (waitHolds(wait)) {
          cause = "GOAL_ACHIEVED";
          break;
        }
        const TimePoint now = clock_.now();
        left -= now - last;
        last = now;
        if (left <= Duration::zero()) {
          cause = "TIME_OUT";
          message = "waited " + params::numberText(wait.timeout_s) + " s for " + waitText(wait);
          break;
        }
        if (auto r = recurrentFinished()) {
          t.failure = *r;
          t.failed_cause.clear();
          flow = Flow::kAbort;
          break;
        }
        const auto stopping = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
          return quit_ || abort_requested_;
        };
        absl::MutexLock lock(&mutex_);
        mutex_.AwaitWithTimeout(absl::Condition(&stopping), absl::FromChrono(kPoll));
      }
      if (flow != Flow::kDone) {
        recordStopped(index, flow);
        return flow;
      }
      updateRecord(index, [&](v1::MissionStepRecord& r) {
        r.set_state(v1::MISSION_STEP_STATE_FINISHED);
        r.set_cause(cause == "GOAL_ACHIEVED" ? v1::TERMINATION_CAUSE_GOAL_ACHIEVED
                                             : v1::TERMINATION_CAUSE_TIME_OUT);
        r.set_message(message);
      });
    }
    recorded.reset();
    if (std::optional<Flow> flow = afterCause(step, path, cause, message, &attempt, t)) {
      return *flow;
    }
  }
}

std::optional<std::string> MissionRunner::runBody(const MissionStep& step, const Position& path,
                                                  int attempt, const Position& tail,
                                                  std::string* message, Flow* flow, Track& t) {
  if (step.loop) return runLoop(step, path, attempt, tail, message, flow, t);
  t.failed_cause.clear();
  *flow = runList(step.body, path, MissionNode::Kind::kCall, attempt, tail, 0, t);
  if (*flow == Flow::kDone) return "GOAL_ACHIEVED";
  if (*flow == Flow::kAbort && !t.failed_cause.empty()) {
    // A step of the sub-mission failed it: the call ends with its cause.
    *message = t.failure;
    return t.failed_cause;
  }
  return std::nullopt;
}

std::optional<std::string> MissionRunner::runLoop(const MissionStep& step, const Position& path,
                                                  int attempt, const Position& tail,
                                                  std::string* message, Flow* flow, Track& t) {
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
    if (loop.kind == MissionLoop::Kind::kForEach) t.items.emplace_back(loop.as, items.values(i));
    t.failed_cause.clear();
    *flow = runList(step.body, path, MissionNode::Kind::kIteration, attempt,
                    i == first ? tail : Position{}, i, t);
    if (loop.kind == MissionLoop::Kind::kForEach) t.items.pop_back();
    if (*flow == Flow::kAbort && !t.failed_cause.empty()) {
      *message = t.failure;
      return t.failed_cause;
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

std::optional<std::string> MissionRunner::runParallel(const MissionStep& step, const Position& path,
                                                      int attempt, std::string* message, Flow* flow,
                                                      Track& t) {
  const MissionParallel& parallel = *step.parallel;
  const size_t n = parallel.branches.size();
  int id = 0;
  {
    absl::MutexLock lock(&mutex_);
    id = next_parallel_++;
    parallels_[id] = false;
  }
  // How each branch ended, in the order they ended.
  struct Outcome {
    Flow flow = Flow::kDone;
    std::string cause;  // GOAL_ACHIEVED, or the cause that failed it
    std::string message;
  };
  std::vector<Outcome> outcomes(n);
  std::vector<size_t> order;  // guarded by mutex_
  auto run_branch = [&](size_t b) {
    Track branch;
    branch.items = t.items;
    branch.parallels = t.parallels;
    branch.parallels.push_back(id);
    // Where this branch was: the records below it, the last one latest.
    Position prefix = path;
    for (const v1::MissionStepRecord& r : t.resume_from) {
      const Position at = positionOf(r);
      if (at.size() > prefix.size() && startsWith(at, prefix) &&
          at[prefix.size()].kind == MissionNode::Kind::kBranch &&
          at[prefix.size()].call_attempt == attempt &&
          at[prefix.size()].iteration == static_cast<int>(b)) {
        branch.resume_from.push_back(r);
      }
    }
    Position tail;
    if (!branch.resume_from.empty()) {
      const Position last = positionOf(branch.resume_from.back());
      tail.assign(last.begin() + static_cast<std::ptrdiff_t>(prefix.size()), last.end());
    }
    Outcome out;
    out.flow = runList(parallel.branches[b].steps, path, MissionNode::Kind::kBranch, attempt, tail,
                       static_cast<int>(b), branch);
    if (out.flow == Flow::kDone) {
      out.cause = "GOAL_ACHIEVED";
    } else if (out.flow == Flow::kAbort && !branch.failed_cause.empty()) {
      out.cause = branch.failed_cause;  // a step of the branch failed it
      out.message = branch.failure;
    } else {
      out.message = branch.failure;  // interrupted, or the end of the mission
    }
    absl::MutexLock lock(&mutex_);
    outcomes[b] = std::move(out);
    order.push_back(b);
    const Outcome& o = outcomes[b];
    // `all` is decided by the first branch that fails, `any` by the first
    // that achieves (or the last that fails); an end of the mission stops
    // every branch.
    const bool achieved = o.cause == "GOAL_ACHIEVED";
    const bool failed = !o.cause.empty() && !achieved;
    if ((parallel.any && achieved) || (!parallel.any && failed) ||
        (o.cause.empty() && o.flow != Flow::kInterrupted)) {
      parallels_[id] = true;
    }
  };
  std::vector<std::thread> threads;
  for (size_t b = 1; b < n; ++b) threads.emplace_back(run_branch, b);
  run_branch(0);
  for (auto& thread : threads) thread.join();
  t.resume_from.clear();
  {
    absl::MutexLock lock(&mutex_);
    parallels_.erase(id);
  }
  // The mission ends (quit, abort requested, or a failure with no step's
  // cause) or a parallel step around this one was decided.
  for (Flow end : {Flow::kQuit, Flow::kAbortRequested, Flow::kAbort, Flow::kInterrupted}) {
    for (size_t b : order) {
      const Outcome& o = outcomes[b];
      if (o.flow == end && o.cause.empty() && (end != Flow::kInterrupted || interrupted(t))) {
        *flow = end;
        if (end == Flow::kAbort) t.failure = o.message;
        t.failed_cause.clear();
        return std::nullopt;
      }
    }
  }
  const auto label = [&](size_t b) {
    const std::string& name = parallel.branches[b].name;
    return "branch " + std::to_string(b) + (name.empty() ? "" : " '" + name + "'");
  };
  size_t deciding = n;
  for (size_t b : order) {
    const Outcome& o = outcomes[b];
    const bool achieved = o.cause == "GOAL_ACHIEVED";
    if (parallel.any ? achieved : (!o.cause.empty() && !achieved)) {
      deciding = b;
      break;
    }
  }
  if (deciding == n && parallel.any) {
    // No branch achieved: every one failed; the last one's cause.
    for (size_t b : order) {
      if (!outcomes[b].cause.empty()) deciding = b;
    }
  }
  if (deciding == n) return "GOAL_ACHIEVED";  // all: every branch achieved
  const Outcome& o = outcomes[deciding];
  if (o.cause == "GOAL_ACHIEVED") {
    *message = label(deciding) + " achieved its steps";
    return o.cause;
  }
  *message = label(deciding) + ": " + o.message;
  return o.cause;
}

absl::StatusOr<google::protobuf::Struct> MissionRunner::withItems(
    const google::protobuf::Struct& parameters, const Track& t) {
  if (t.items.empty()) return parameters;
  google::protobuf::Value whole;
  *whole.mutable_struct_value() = parameters;
  const absl::Status s = substituteTokens(
      &whole, "each",
      [&t](const std::string& name) -> const google::protobuf::Value* {
        for (auto it = t.items.rbegin(); it != t.items.rend();
             ++it) {  // the innermost loop's first
          if (it->first == name) return &it->second;
        }
        return nullptr;
      },
      [](const std::string& name) { return "${each." + name + "} is no loop's item here"; });
  if (!s.ok()) return s;
  return whole.struct_value();
}

}  // namespace behaviorlib::coordinator
