#include "coordinator/control/mission_manager.h"

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <cstdio>
#include <iterator>
#include <limits>
#include <memory>
#include <random>
#include <set>
#include <utility>

#include "absl/strings/str_cat.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/transport_security.h"

namespace behaviorlib::coordinator {

namespace {

// A mission text's name (its file on the client) appears in every status.
constexpr size_t kMaxSourceNameBytes = 256;

std::string newMissionId(const std::string& name) {
  ABSL_CONST_INIT static absl::Mutex mutex(absl::kConstInit);
  static std::mt19937_64 rng ABSL_GUARDED_BY(mutex){std::random_device{}()};
  absl::MutexLock lock(&mutex);
  char suffix[9];
  std::snprintf(suffix, sizeof(suffix), "%08x", static_cast<unsigned>(rng() & 0xffffffffu));
  return absl::StrCat(name.empty() ? "mission" : name, "-", suffix);
}

// The behaviors of `steps` by robot (a step that names none: `robot`),
// calls', loops' and branches' steps and fallbacks included.
using RobotBehaviors = std::map<std::string, std::set<std::string>>;
void collectBehaviors(const std::vector<MissionStep>& steps, const std::string& robot,
                      RobotBehaviors* out) {
  forEachStep(steps, [&](const MissionStep& step) {
    if (!step.behavior.empty())
      (*out)[step.robot.empty() ? robot : step.robot].insert(step.behavior);
  });
}

// Whether the mission commands `robot` (its robot, or one of a fleet
// mission's; a status journaled before robot_ids has only robot_id).
bool commands(const v1::MissionStatus& status, const std::string& robot) {
  if (status.robot_id() == robot) return true;
  return std::find(status.robot_ids().begin(), status.robot_ids().end(), robot) !=
         status.robot_ids().end();
}

absl::Status unknownMission(const std::string& mission_id) {
  return errors::withReason(
      absl::NotFoundError(absl::StrCat("no mission '", mission_id, "' (ListMissions lists them)")),
      v1::MISSION_NOT_FOUND, {{"mission_id", mission_id}});
}

absl::Status shuttingDown() {
  return errors::withReason(absl::UnavailableError("the coordinator is shutting down"),
                            v1::SHUTTING_DOWN);
}

RobotBehaviors behaviorsOf(const MissionSpec& spec, const std::string& robot_id) {
  RobotBehaviors names;
  for (const auto* list : {&spec.recurrent, &spec.safety, &spec.steps}) {
    collectBehaviors(*list, robot_id, &names);
  }
  return names;
}

// The newest event seq of the behavior system at `address` (the start
// message of its WatchEvents, asked for events after the largest seq: nothing
// is replayed); nullopt when it cannot be asked.
std::optional<uint64_t> latestSeqOf(const std::string& address) {
  auto stub = v1::BehaviorSystem::NewStub(behaviorlib::server_kit::makeChannel(address));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(2));
  v1::WatchEventsRequest request;
  request.set_since_seq(std::numeric_limits<uint64_t>::max() - 1);
  auto reader = stub->WatchEvents(&context, request);
  v1::WatchEventsResponse message;
  std::optional<uint64_t> latest;
  if (reader->Read(&message) && message.has_start()) latest = message.start().latest_seq();
  context.TryCancel();
  (void)reader->Finish();
  return latest;
}

// True when every system hosting one of `behaviors` on the robot is UP and
// the coordinator has received every event it had emitted: the registry then
// knows what is active there, so that a resumed mission's plans see the robot
// as it is (its repeated activations are replays, not conflicts).
bool systemsCaughtUp(const Registry& registry, const std::set<std::string>& behaviors,
                     const std::string& robot_id, std::string* lagging) {
  std::set<std::string> systems;
  for (const auto& behavior : behaviors) {
    Registry::Route route;
    if (registry.route(robot_id, behavior, &route).ok()) systems.insert(route.system);
  }
  v1::ListSystemsResponse list;
  registry.listSystems(robot_id, &list);
  for (const auto& s : list.systems()) {
    if (!systems.contains(s.system())) continue;
    if (s.state() != v1::SYSTEM_STATE_UP) {
      *lagging = absl::StrCat("system ", s.system(), " (", v1::SystemState_Name(s.state()), ")");
      return false;
    }
    const std::optional<uint64_t> latest = latestSeqOf(s.address());
    if (!latest || s.last_event_seq() < *latest) {
      *lagging = absl::StrCat("system ", s.system(), " (its event replay is not complete)");
      return false;
    }
  }
  return true;
}

}  // namespace

MissionManager::MissionManager(FleetControl& fleet, Registry& registry, BeliefStore& beliefs,
                               Journal* journal, MissionManagerOptions options)
    : fleet_(fleet), registry_(registry), beliefs_(beliefs), journal_(journal), options_(options) {}

MissionManager::~MissionManager() { stop(); }

bool MissionManager::ended(const v1::MissionStatus& status) {
  return status.has_end_time() || status.state() == v1::MISSION_STATE_SUCCEEDED;
}

void MissionManager::stop() {
  std::vector<std::shared_ptr<MissionRunner>> runners;
  std::vector<std::thread> resumers;
  {
    absl::MutexLock lock(&mutex_);
    stopped_ = true;
    for (auto& [id, entry] : missions_) {
      if (entry.runner) runners.push_back(std::move(entry.runner));
    }
    runners.insert(runners.end(), std::make_move_iterator(finished_.begin()),
                   std::make_move_iterator(finished_.end()));
    finished_.clear();
    resumers.swap(resumers_);
  }
  for (auto& t : resumers) t.join();
  runners.clear();  // joins their threads; onChange may still run meanwhile
}

void MissionManager::restore(const v1::MissionStatus& status) {
  absl::MutexLock lock(&mutex_);
  Entry& entry = missions_[status.mission_id()];
  if (entry.order == 0) entry.order = next_order_++;
  entry.status = status;
}

void MissionManager::pruneLocked(std::vector<Entry>* pruned) {
  const google::protobuf::Timestamp now =
      options_.now ? options_.now() : google::protobuf::util::TimeUtil::GetCurrentTime();
  const int64_t oldest_end_s = now.seconds() - options_.max_ended_age.count();
  std::vector<std::pair<uint64_t, std::string>> kept;  // ended, by start order
  for (auto it = missions_.begin(); it != missions_.end();) {
    const Entry& entry = it->second;
    if (!ended(entry.status)) {
      ++it;
      continue;
    }
    if (entry.status.has_end_time() && entry.status.end_time().seconds() < oldest_end_s) {
      pruned->push_back(std::move(it->second));
      it = missions_.erase(it);
      continue;
    }
    kept.emplace_back(entry.order, it->first);
    ++it;
  }
  if (kept.size() <= options_.max_ended_missions) return;
  std::sort(kept.begin(), kept.end());
  for (size_t i = 0; i + options_.max_ended_missions < kept.size(); ++i) {
    auto it = missions_.find(kept[i].second);
    pruned->push_back(std::move(it->second));
    missions_.erase(it);
  }
}

void MissionManager::countLocked() const {
  if (options_.metrics == nullptr) return;
  size_t runners = finished_.size();
  for (const auto& [id, entry] : missions_) runners += entry.runner != nullptr;
  options_.metrics->missions_retained.Set(static_cast<double>(missions_.size()));
  options_.metrics->mission_runners.Set(static_cast<double>(runners));
}

void MissionManager::resumeRestored() {
  std::vector<Entry> pruned;
  absl::MutexLock lock(&mutex_);
  pruneLocked(&pruned);
  countLocked();
  for (const auto& [id, entry] : missions_) {
    if (ended(entry.status) || entry.runner) continue;
    resumers_.emplace_back([this, id = id] { resumeOne(id); });
  }
}

bool MissionManager::behaviorsRoutable(const MissionSpec& spec, const std::string& robot_id,
                                       std::string* missing) const {
  for (const auto& [robot, behaviors] : behaviorsOf(spec, robot_id)) {
    for (const auto& behavior : behaviors) {
      Registry::Route route;
      if (!registry_.route(robot, behavior, &route).ok()) {
        *missing = absl::StrCat(behavior, " on robot '", robot, "'");
        return false;
      }
    }
    if (!systemsCaughtUp(registry_, behaviors, robot, missing)) return false;
  }
  return true;
}

void MissionManager::resumeOne(const std::string& mission_id) {
  v1::MissionStatus status;
  {
    absl::MutexLock lock(&mutex_);
    status = missions_.at(mission_id).status;
  }
  auto fail = [&](const std::string& why) {
    status.set_state(v1::MISSION_STATE_FAILED);
    status.set_message(why);
    *status.mutable_end_time() = google::protobuf::util::TimeUtil::GetCurrentTime();
    onChange(status);
  };
  // The imported files as they were when it started (journaled with it).
  const std::map<std::string, std::string> imported(status.imports().begin(),
                                                    status.imports().end());
  auto spec = parseMission(status.source(), status.file(),
                           [&imported](const std::string& path) -> absl::StatusOr<std::string> {
                             const auto it = imported.find(path);
                             if (it == imported.end()) {
                               return absl::NotFoundError("not journaled with the mission");
                             }
                             return it->second;
                           });
  if (!spec.ok()) {
    fail(absl::StrCat("cannot resume after a coordinator restart: ", spec.status().message()));
    return;
  }
  // Wait until every behavior the mission names is served again (the
  // systems register with the new coordinator within a heartbeat).
  const auto deadline = std::chrono::steady_clock::now() + options_.resume_wait;
  std::string missing;
  for (;;) {
    if (behaviorsRoutable(*spec, status.robot_id(), &missing)) break;
    {
      absl::MutexLock lock(&mutex_);
      mutex_.AwaitWithTimeout(absl::Condition(&stopped_),
                              absl::FromChrono(std::chrono::milliseconds(100)));
      if (stopped_) return;
    }
    if (std::chrono::steady_clock::now() > deadline) {
      fail(absl::StrCat("cannot resume after a coordinator restart: ", missing,
                        " was not served again within ", options_.resume_wait.count(), " ms"));
      return;
    }
  }
  absl::MutexLock lock(&mutex_);
  if (stopped_) return;
  std::fprintf(stderr, "coordinator: resuming mission %s (%s) on robot %s\n", mission_id.c_str(),
               v1::MissionState_Name(status.state()).c_str(), status.robot_id().c_str());
  Entry& entry = missions_.at(mission_id);
  entry.geofence = spec->geofence;
  entry.runner = std::make_shared<MissionRunner>(
      std::move(*spec), status, fleet_, beliefs_,
      [this](const v1::MissionStatus& s) { onChange(s); },
      MissionRunner::Options{.clock = options_.clock, .vehicles = options_.vehicles});
  countLocked();
  entry.runner->start();
}

void MissionManager::onChange(const v1::MissionStatus& status) {
  if (journal_ != nullptr) {
    durable::v1::JournalRecord record;
    *record.mutable_mission() = status;
    if (auto s = journal_->append(record); !s.ok()) {
      std::fprintf(stderr, "coordinator: mission %s: cannot journal its status: %s\n",
                   status.mission_id().c_str(), std::string(s.message()).c_str());
    }
  }
  std::vector<Listener> listeners;
  bool now_ended = false;
  {
    absl::MutexLock lock(&mutex_);
    auto it = missions_.find(status.mission_id());
    if (it != missions_.end()) {
      now_ended = !ended(it->second.status) && ended(status);
      it->second.status = status;
      // Called from the runner's own thread: it cannot be joined here.
      if (now_ended && it->second.runner) finished_.push_back(std::move(it->second.runner));
      countLocked();
    }
    for (const auto& [token, listener] : listeners_) {
      if (listener.first == status.mission_id()) listeners.push_back(listener.second);
    }
  }
  if (now_ended && options_.metrics != nullptr) options_.metrics->missionEnded(status);
  for (const auto& listener : listeners) listener(status);
}

MissionProblems MissionManager::problemsAgainstRegistry(const MissionSpec& spec,
                                                        const std::string& robot_id,
                                                        std::string* unregistered) const {
  std::map<std::string, std::map<std::string, v1::BehaviorDescription>> hosted;
  MissionProblems problems;
  for (const std::string& robot : missionRobots(spec, robot_id)) {
    v1::ListFleetBehaviorsResponse list;
    registry_.listBehaviors(robot, "", &list);
    auto& of_robot = hosted[robot];
    for (const auto& b : list.behaviors()) of_robot[b.description().name()] = b.description();
    if (of_robot.empty()) {
      if (unregistered->empty()) *unregistered = robot;
      problems.add(spec.file, robot == robot_id ? spec.robot_line : 0, "robot",
                   absl::StrCat("robot '", robot,
                                "' has no registered behavior system: start its systems first"));
    }
  }
  if (!unregistered->empty()) return problems;
  problems = checkMissionProblems(spec, [&](const std::string& robot, const std::string& behavior) {
    const auto& of_robot = hosted[robot.empty() ? robot_id : robot];
    auto it = of_robot.find(behavior);
    return it == of_robot.end() ? nullptr : &it->second;
  });
  unwrittenBeliefProblems(spec, robot_id, &problems);
  if (options_.vehicles == nullptr) {
    // `when:` reads the vehicles' topics, on the data channel.
    forEachStep(spec.steps, [&](const MissionStep& step) {
      if (step.when.empty()) return;
      problems.add(step.file.empty() ? spec.file : step.file, step.when.front().line,
                   step.path + ".when",
                   "conditions on the vehicle need the coordinator's --channel (it reads no "
                   "vehicle topics)");
    });
  }
  return problems;
}

void MissionManager::unwrittenBeliefProblems(const MissionSpec& spec, const std::string& robot_id,
                                             MissionProblems* problems) const {
  // What the mission provides: the keys its steps remember, the beliefs its
  // behaviors may write (their catalog entries' `writes`), and the beliefs
  // it waits for (something outside it writes those).
  std::set<std::string> exact;
  std::vector<std::string> prefixes;
  auto provide = [&](const std::string& key) {
    const size_t open = key.find("${");
    if (open != std::string::npos) {
      prefixes.push_back(key.substr(0, open));  // a loop's item completes it
    } else if (!key.empty() && key.back() == '*') {
      prefixes.push_back(key.substr(0, key.size() - 1));
    } else {
      exact.insert(key);
    }
  };
  const Catalog* catalog = fleet_.catalog();
  const auto provided_by = [&](const MissionStep& step) {
    const std::string& robot = step.robot.empty() ? robot_id : step.robot;
    if (const CatalogBehavior* b =
            catalog != nullptr && !step.behavior.empty() ? catalog->find(step.behavior) : nullptr) {
      for (const std::string& pattern : b->writes) {
        if (auto key = instantiateBeliefPattern(pattern, robot, step.parameters)) provide(*key);
      }
    }
    for (const auto& [key, value] : step.remember.fields()) provide(key);
    if (step.wait && step.wait->belief) provide(step.wait->belief->key);
  };
  for (const auto* list : {&spec.recurrent, &spec.steps, &spec.safety}) {
    forEachStep(*list, provided_by);
  }
  auto known = [&](const std::string& key) {
    if (exact.contains(key) || beliefs_.get(key).has_value()) return true;
    for (const std::string& prefix : prefixes) {
      if (key.rfind(prefix, 0) == 0) return true;
    }
    return false;
  };
  const auto check = [&](const MissionStep& step) {
    std::vector<std::pair<std::string, std::string>> bound;  // key, field
    auto bindings = [&](const google::protobuf::Struct& values, const std::string& field) {
      for (const auto& entry : values.fields()) {
        const std::string& name = entry.first;  // (a lambda cannot capture a structured binding)
        (void)forEachString(entry.second, [&](const std::string& text) {
          if (text.find("${each.") != std::string::npos) return absl::OkStatus();
          if (auto keys = BeliefStore::bindingsIn(text); keys.ok()) {
            for (const std::string& key : *keys) bound.emplace_back(key, field + "." + name);
          }
          return absl::OkStatus();
        });
      }
    };
    bindings(step.parameters, step.path + ".parameters");
    bindings(step.with, step.path + ".with");
    bindings(step.remember, step.path + ".remember");
    if (step.loop && !step.loop->belief.empty()) {
      bound.emplace_back(step.loop->belief, step.path + ".for_each.in");
    }
    for (const auto& [key, field] : bound) {
      // A step that runs only if the belief exists guards its own binding.
      if (step.condition && step.condition->key == key) continue;
      if (known(key)) continue;
      const auto line_it = step.parameter_lines.find(field.substr(field.rfind('.') + 1));
      problems->add(step.file.empty() ? spec.file : step.file,
                    line_it == step.parameter_lines.end() ? step.line : line_it->second, field,
                    absl::StrCat("${belief.", key, "}: belief '", key,
                                 "' is not in memory, and no step of the mission writes it (its "
                                 "`remember`, or a behavior whose catalog entry lists it under "
                                 "`writes`) or waits for it"));
    }
  };
  for (const auto* list : {&spec.recurrent, &spec.steps, &spec.safety}) forEachStep(*list, check);
}

absl::Status MissionManager::checkAgainstRegistry(const MissionSpec& spec,
                                                  const std::string& robot_id) const {
  std::string unregistered;
  MissionProblems problems = problemsAgainstRegistry(spec, robot_id, &unregistered);
  if (!unregistered.empty()) {
    return errors::withReason(
        absl::FailedPreconditionError(absl::StrCat("robot '", unregistered,
                                                   "' has no registered behavior system: start "
                                                   "its systems first")),
        v1::UNKNOWN_ROBOT, {{"robot", unregistered}});
  }
  return problems.status();
}

template <class Request>
absl::StatusOr<MissionManager::Source> MissionManager::readSource(const Request& request) const {
  Source source;
  if (request.has_file_path()) {
    source.file = request.file_path();
    absl::StatusOr<std::string> read = options_.mission_files.read(source.file);
    if (!read.ok()) return read.status();
    source.text = std::move(*read);
    return source;
  }
  if (!request.has_text()) {
    return errors::withReason(
        absl::InvalidArgumentError("no mission: set file_path (a mission file in the coordinator's "
                                   "--mission-dir) or text"),
        v1::INVALID_REQUEST);
  }
  if (request.text().size() > options_.max_mission_bytes) {
    return errors::withReason(
        absl::InvalidArgumentError(absl::StrCat("the mission text is ", request.text().size(),
                                                " bytes, more than the ",
                                                options_.max_mission_bytes, " allowed")),
        v1::LIMIT_EXCEEDED, {{"limit", std::to_string(options_.max_mission_bytes)}});
  }
  if (request.source_name().size() > kMaxSourceNameBytes) {
    return errors::withReason(absl::InvalidArgumentError(absl::StrCat(
                                  "source_name is longer than ", kMaxSourceNameBytes, " bytes")),
                              v1::LIMIT_EXCEEDED, {{"limit", std::to_string(kMaxSourceNameBytes)}});
  }
  source.file = request.source_name().empty() ? "<mission text>" : request.source_name();
  source.text = request.text();
  return source;
}

ImportReader MissionManager::importReader() const {
  if (!options_.mission_files.enabled()) return nullptr;
  return [this](const std::string& path) { return options_.mission_files.read(path); };
}

absl::StatusOr<v1::CheckMissionResponse> MissionManager::check(
    const v1::CheckMissionRequest& request) const {
  absl::StatusOr<Source> source = readSource(request);
  if (!source.ok()) return source.status();
  v1::CheckMissionResponse response;
  MissionProblems problems;
  absl::StatusOr<MissionSpec> spec = parseMission(source->text, source->file, importReader());
  const std::string robot_id = !request.robot_id().empty() ? request.robot_id()
                               : spec.ok()                 ? spec->robot_id
                                                           : "";
  response.set_robot_id(robot_id);
  if (!spec.ok()) {
    problems.addStatus(spec.status(), source->file);
  } else {
    response.set_name(spec->name);
    std::string unregistered;
    if (robot_id.empty()) {
      problems.add(source->file, 0, "robot",
                   "no robot: give `robot:` in the mission file or robot_id in the request");
    } else {
      problems = problemsAgainstRegistry(*spec, robot_id, &unregistered);
      if (unregistered.empty()) planSteps(*spec, robot_id, &response);
    }
  }
  for (const MissionProblem& p : problems.list) {
    v1::MissionProblem* out = response.add_problems();
    out->set_file(p.file);
    out->set_line(static_cast<uint32_t>(std::max(p.line, 0)));
    out->set_field(p.field);
    out->set_description(p.description);
  }
  response.set_problems_left_out(static_cast<uint32_t>(problems.left_out));
  return response;
}

void MissionManager::planSteps(const MissionSpec& spec, const std::string& robot_id,
                               v1::CheckMissionResponse* response) const {
  const Catalog* catalog = fleet_.catalog();
  // Each robot's view, and what is active on each robot as the plans go.
  std::map<std::string, PlanRequest> views;
  using Active = std::map<std::string, std::set<std::string>>;
  auto view_of = [&](const std::string& robot) -> const PlanRequest& {
    auto it = views.find(robot);
    if (it == views.end()) it = views.emplace(robot, fleet_.planningView(robot)).first;
    return it->second;
  };
  auto active_on = [&](Active* active, const std::string& robot) -> std::set<std::string>& {
    auto it = active->find(robot);
    if (it == active->end()) it = active->emplace(robot, view_of(robot).active).first;
    return it->second;
  };
  // Plans `steps` one after another from `active`, which receives what they
  // leave active (a step's target ends with its step unless `stays`); a
  // parallel step's branches are planned one after the other.
  std::function<void(const std::vector<MissionStep>&, const std::string&, bool, Active*)>
      plan_list = [&](const std::vector<MissionStep>& steps, const std::string& prefix, bool stays,
                      Active* active) {
        for (size_t i = 0; i < steps.size(); ++i) {
          const MissionStep& step = steps[i];
          const std::string node = absl::StrCat(prefix, "/", i);
          const std::string& robot = step.robot.empty() ? robot_id : step.robot;
          if (!step.behavior.empty()) {
            v1::MissionStepPlan* out = response->add_plans();
            out->set_node(node);
            out->set_name(step.name);
            out->set_behavior(step.behavior);
            out->set_line(static_cast<uint32_t>(std::max(step.line, 0)));
            absl::StatusOr<google::protobuf::Struct> parameters = beliefs_.resolve(step.parameters);
            if (!parameters.ok()) {
              out->set_no_plan(absl::StrCat(
                  "its parameters are bound to beliefs that resolve when the step starts: ",
                  parameters.status().message()));
            } else if (catalog == nullptr) {
              out->set_no_plan("the coordinator has no catalog");
            } else {
              std::set<std::string>& on_robot = active_on(active, robot);
              PlanRequest request = view_of(robot);
              request.active = on_robot;
              request.target = step.behavior;
              request.parameters = std::move(*parameters);
              absl::StatusOr<Plan> plan = makePlan(*catalog, request);
              if (plan.ok()) {
                planToProto(*plan, out->mutable_plan());
                applyToActive(*plan, &on_robot);
                if (!stays) on_robot.erase(step.behavior);
              } else {
                out->set_no_plan(std::string(plan.status().message()));
              }
            }
          }
          // A call's steps, planned where it stands.
          if (!step.call.empty()) {
            plan_list(step.body, node + "/attempt/1/call/steps", false, active);
          }
          // A loop's first iteration.
          if (step.loop) {
            plan_list(step.body, node + "/attempt/1/iteration/0/steps", false, active);
          }
          if (step.parallel) {
            for (size_t b = 0; b < step.parallel->branches.size(); ++b) {
              plan_list(step.parallel->branches[b].steps,
                        absl::StrCat(node, "/attempt/1/branch/", b, "/steps"), false, active);
            }
          }
          // A fallback starts from what the failed step left.
          for (const auto& [cause, action] : step.on) {
            for (const MissionAction* a = &action; a != nullptr; a = a->then.get()) {
              if (a->fallback.empty()) continue;
              Active after = *active;
              plan_list(a->fallback, node + "/fallback", false, &after);
            }
          }
        }
      };
  Active active;
  plan_list(spec.recurrent, "recurrent", true, &active);
  Active after_recurrent = active;
  plan_list(spec.steps, "steps", false, &active);
  plan_list(spec.safety, "safety", false, &after_recurrent);
}

absl::StatusOr<v1::MissionStatus> MissionManager::start(const v1::StartMissionRequest& request) {
  absl::StatusOr<Source> source = readSource(request);
  if (!source.ok()) return source.status();
  // The text is kept so that a restarted coordinator can parse it again.
  std::string text = std::move(source->text);
  const std::string file = std::move(source->file);
  absl::StatusOr<MissionSpec> spec = parseMission(text, file, importReader());
  if (!spec.ok()) return errors::withDefaultReason(spec.status(), v1::MISSION_INVALID);
  const std::string robot_id = request.robot_id().empty() ? spec->robot_id : request.robot_id();
  if (robot_id.empty()) {
    return errors::withReason(
        absl::InvalidArgumentError(absl::StrCat(
            file, ": no robot: give `robot:` in the mission file or robot_id in the request")),
        v1::MISSION_INVALID);
  }
  if (!request.mission_id().empty()) {
    if (auto existing = get(request.mission_id()); existing.ok()) return existing;
  }
  if (auto s = checkAgainstRegistry(*spec, robot_id); !s.ok()) return s;

  // Destroyed after the lock is released: the pruned missions, and the
  // runners of those that ended (joining their threads).
  std::vector<Entry> pruned;
  std::vector<std::shared_ptr<MissionRunner>> finished;
  absl::MutexLock lock(&mutex_);
  pruneLocked(&pruned);
  finished.swap(finished_);
  countLocked();
  if (stopped_) return shuttingDown();
  for (const std::string& robot : missionRobots(*spec, robot_id)) {
    for (const auto& [id, entry] : missions_) {
      if (commands(entry.status, robot) && !ended(entry.status)) {
        return errors::withReason(
            absl::FailedPreconditionError(
                absl::StrCat("robot '", robot, "' runs mission '", id, "' (",
                             v1::MissionState_Name(entry.status.state()), "): abort it first")),
            v1::MISSION_STATE_CONFLICT, {{"robot", robot}, {"mission_id", id}});
      }
    }
  }
  const std::string mission_id =
      request.mission_id().empty() ? newMissionId(spec->name) : request.mission_id();
  Entry& entry = missions_[mission_id];
  entry.order = next_order_++;
  entry.geofence = spec->geofence;
  entry.runner = std::make_shared<MissionRunner>(
      std::move(*spec), mission_id, robot_id, text, fleet_, beliefs_,
      [this](const v1::MissionStatus& s) { onChange(s); },
      MissionRunner::Options{.clock = options_.clock, .vehicles = options_.vehicles});
  entry.status = entry.runner->status();
  if (options_.metrics != nullptr)
    options_.metrics->missions_started.Add({{"robot", robot_id}}).Increment();
  countLocked();
  entry.runner->start();
  return entry.status;
}

absl::StatusOr<v1::MissionStatus> MissionManager::get(const std::string& mission_id) const {
  absl::MutexLock lock(&mutex_);
  auto it = missions_.find(mission_id);
  if (it == missions_.end()) return unknownMission(mission_id);
  return it->second.runner ? it->second.runner->status() : it->second.status;
}

std::vector<v1::MissionStatus> MissionManager::list() const {
  std::vector<std::pair<uint64_t, v1::MissionStatus>> all;
  {
    absl::MutexLock lock(&mutex_);
    for (const auto& [id, entry] : missions_) {
      all.emplace_back(entry.order, entry.runner ? entry.runner->status() : entry.status);
    }
  }
  std::sort(all.begin(), all.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
  std::vector<v1::MissionStatus> out;
  for (auto& [order, status] : all) out.push_back(std::move(status));
  return out;
}

std::optional<std::string> MissionManager::runningMissionOf(const std::string& robot_id) const {
  absl::MutexLock lock(&mutex_);
  for (const auto& [id, entry] : missions_) {
    if (commands(entry.status, robot_id) && !ended(entry.status)) return id;
  }
  return std::nullopt;
}

std::optional<std::pair<std::string, Geofence>> MissionManager::geofenceOf(
    const std::string& robot_id) const {
  absl::MutexLock lock(&mutex_);
  for (const auto& [id, entry] : missions_) {
    if (commands(entry.status, robot_id) && !ended(entry.status) && entry.geofence) {
      return std::make_pair(id, *entry.geofence);
    }
  }
  return std::nullopt;
}

absl::StatusOr<v1::MissionStatus> MissionManager::control(
    const std::string& mission_id, const std::function<absl::Status(MissionRunner&)>& request) {
  std::shared_ptr<MissionRunner> runner;
  {
    absl::MutexLock lock(&mutex_);
    auto it = missions_.find(mission_id);
    if (it == missions_.end()) return unknownMission(mission_id);  // mutex_ is held
    runner = it->second.runner;
    if (runner == nullptr) {
      const Entry& entry = it->second;
      const std::string state = v1::MissionState_Name(entry.status.state());
      return errors::withReason(
          absl::FailedPreconditionError(
              ended(entry.status)
                  ? absl::StrCat("mission '", mission_id, "' already ended (", state, ")")
                  : absl::StrCat("mission '", mission_id, "' is not running here (", state, ")")),
          v1::MISSION_STATE_CONFLICT, {{"mission_id", mission_id}});
    }
  }
  // The call is made without the lock; the shared pointer keeps the runner
  // alive through it even if the mission ends meanwhile. The runner refuses
  // a request its state does not allow (pause a finished mission) with
  // FAILED_PRECONDITION.
  if (auto s = request(*runner); !s.ok()) {
    if (s.code() == absl::StatusCode::kFailedPrecondition) {
      s = errors::withDefaultReason(std::move(s), v1::MISSION_STATE_CONFLICT);
    }
    return errors::withMetadata(std::move(s), {{"mission_id", mission_id}});
  }
  return runner->status();
}

absl::StatusOr<v1::MissionStatus> MissionManager::pause(const std::string& mission_id) {
  return control(mission_id, [](MissionRunner& r) { return r.pause(); });
}

absl::StatusOr<v1::MissionStatus> MissionManager::resume(const std::string& mission_id) {
  return control(mission_id, [](MissionRunner& r) { return r.resume(); });
}

absl::StatusOr<v1::MissionStatus> MissionManager::abort(const std::string& mission_id,
                                                        const std::string& reason, bool run_safety,
                                                        const std::string& robot) {
  return control(mission_id, [&](MissionRunner& r) { return r.abort(reason, run_safety, robot); });
}

absl::StatusOr<uint64_t> MissionManager::watch(const std::string& mission_id, Listener listener) {
  v1::MissionStatus now;
  uint64_t token = 0;
  {
    absl::MutexLock lock(&mutex_);
    auto it = missions_.find(mission_id);
    if (it == missions_.end()) return unknownMission(mission_id);
    now = it->second.runner ? it->second.runner->status() : it->second.status;
    token = next_token_++;
    listeners_[token] = {mission_id, listener};
  }
  listener(now);
  return token;
}

void MissionManager::unwatch(uint64_t token) {
  absl::MutexLock lock(&mutex_);
  listeners_.erase(token);
}

std::vector<durable::v1::JournalRecord> MissionManager::snapshot() const {
  std::vector<durable::v1::JournalRecord> records;
  absl::MutexLock lock(&mutex_);
  for (const auto& [id, entry] : missions_) {
    durable::v1::JournalRecord record;
    *record.mutable_mission() = entry.runner ? entry.runner->status() : entry.status;
    records.push_back(std::move(record));
  }
  return records;
}

}  // namespace behaviorlib::coordinator
