#include "coordinator/registry/registry.h"

#include <algorithm>
#include <set>
#include <tuple>

#include "behaviorlib/error_details.h"

namespace behaviorlib::coordinator {

namespace {

bool usable(v1::SystemState state) {
  return state != v1::SYSTEM_STATE_DOWN && state != v1::SYSTEM_STATE_UNREGISTERED;
}

std::string join(const std::set<std::string>& names) {
  std::string out;
  for (const auto& n : names) out += (out.empty() ? "" : ", ") + n;
  return out.empty() ? "none" : out;
}

// INVALID_ARGUMENT for an empty request field, naming it.
grpc::Status missingField(const std::string& field, const std::string& message) {
  return errors::toGrpc(errors::withFieldViolation(
      errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST), field,
      message));
}

}  // namespace

Registry::Registry(FleetEventLog& log, CoordinatorMetrics& metrics, RegistryOptions options)
    : log_(log), metrics_(metrics), options_(options) {}

Registry::~Registry() { stop(); }

void Registry::stop() {
  std::vector<std::shared_ptr<SystemLink>> links;
  {
    absl::MutexLock lock(&mutex_);
    stopped_ = true;
    links = std::move(links_);
    links.insert(links.end(), retired_.begin(), retired_.end());
    links_.clear();
    retired_.clear();
  }
  // Outside the lock: a link thread may be waiting for it in onRetired.
  for (auto& link : links) link->stop();
}

void Registry::addConfigured(const ConfiguredSystem& system) {
  LinkIdentity identity;
  identity.robot_id = system.robot_id;
  identity.address = system.address;
  identity.source = v1::SYSTEM_SOURCE_CONFIG;
  auto link = std::make_shared<SystemLink>(std::move(identity), log_, metrics_, options_.link,
                                           [this](SystemLink* l) { onRetired(l); });
  absl::MutexLock lock(&mutex_);
  if (stopped_) return;
  link->start();
  links_.push_back(std::move(link));
  updateGaugeLocked();
}

std::shared_ptr<SystemLink> Registry::findLocked(const std::string& robot_id,
                                                 const std::string& system,
                                                 const std::string& address) const {
  for (const auto& link : links_) {
    if (link->robotId() != robot_id || link->retired()) continue;
    const std::string link_system = link->system();
    const bool same = (!system.empty() && link_system == system) ||
                      (link_system.empty() && !address.empty() && link->address() == address);
    if (!same) continue;
    // A registered system on its way out is replaced by a new link.
    if (link->leaving() && link->source() != v1::SYSTEM_SOURCE_CONFIG) continue;
    return link;
  }
  return nullptr;
}

grpc::Status Registry::registerSystem(const v1::RegisterSystemRequest& request,
                                      const v1::ListBehaviorsResponse& description) {
  std::vector<std::shared_ptr<SystemLink>> reaped;
  grpc::Status status;
  {
    absl::MutexLock lock(&mutex_);
    // Links that ended are joined below, outside the lock.
    reaped = std::move(retired_);
    retired_.clear();
    if (stopped_) {
      return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                               "the coordinator is shutting down");
    }
    auto existing = findLocked(request.robot_id(), request.system(), request.address());
    // One robot's behavior names must be unique, so that (robot, behavior)
    // names one behavior.
    for (const auto& link : links_) {
      if (link == existing || link->robotId() != request.robot_id() || link->retired() ||
          !usable(link->state()) || link->system() == request.system()) {
        continue;
      }
      for (const auto& behavior : description.behaviors()) {
        if (link->hosts(behavior.name())) {
          return errors::grpcError(
              grpc::StatusCode::FAILED_PRECONDITION, v1::ALREADY_HOSTED,
              "behavior " + behavior.name() + " of robot " + request.robot_id() +
                  " is already hosted by system " + link->system() + " at " + link->address() +
                  "; the behaviors of one robot must have unique names across its systems",
              {{"robot", request.robot_id()},
               {"system", request.system()},
               {"behavior", behavior.name()},
               {"hosted_by", link->system()}});
        }
      }
    }
    if (existing) {
      existing->registered(request.address(), description);
    } else {
      LinkIdentity identity;
      identity.robot_id = request.robot_id();
      identity.system = request.system();
      identity.address = request.address();
      identity.source = v1::SYSTEM_SOURCE_REGISTRATION;
      auto link = std::make_shared<SystemLink>(std::move(identity), log_, metrics_, options_.link,
                                               [this](SystemLink* l) { onRetired(l); });
      link->registered(request.address(), description);
      link->start();
      links_.push_back(std::move(link));
      updateGaugeLocked();
    }
  }
  for (auto& link : reaped) link->stop();
  if (status.ok() && options_.on_membership) {
    durable::v1::SystemRecord record;
    record.set_robot_id(request.robot_id());
    record.set_system(request.system());
    record.set_address(request.address());
    options_.on_membership(record);
  }
  return status;
}

grpc::Status Registry::heartbeat(const v1::HeartbeatRequest& request) {
  absl::MutexLock lock(&mutex_);
  auto link = findLocked(request.robot_id(), request.system(), "");
  const std::string who = "robot " + request.robot_id() + " system " + request.system();
  const errors::Metadata about = {{"robot", request.robot_id()}, {"system", request.system()}};
  if (!link) {
    return errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_SYSTEM,
                             who +
                                 " is not registered (the coordinator restarted, or the system "
                                 "unregistered); register again",
                             about);
  }
  if (link->heartbeat(request.incarnation())) return grpc::Status::OK;
  if (link->state() == v1::SYSTEM_STATE_UP) {
    return errors::grpcError(grpc::StatusCode::FAILED_PRECONDITION, v1::UNKNOWN_SYSTEM,
                             who + " is now served by incarnation " +
                                 link->registeredIncarnation() + " at " + link->address() +
                                 ", not by incarnation " + request.incarnation() +
                                 "; two processes claim the same robot and system",
                             about);
  }
  return errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_SYSTEM,
                           "incarnation " + request.incarnation() + " of " + who +
                               " is not the registered one; register again",
                           about);
}

grpc::Status Registry::unregister(const v1::UnregisterSystemRequest& request) {
  durable::v1::SystemRecord record;
  {
    absl::MutexLock lock(&mutex_);
    auto link = findLocked(request.robot_id(), request.system(), "");
    if (!link || !link->unregister(request.incarnation(), request.final_seq())) {
      return errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_SYSTEM,
                               "incarnation " + request.incarnation() + " of robot " +
                                   request.robot_id() + " system " + request.system() +
                                   " is not registered",
                               {{"robot", request.robot_id()}, {"system", request.system()}});
    }
    record.set_address(link->address());
  }
  if (options_.on_membership) {
    record.set_robot_id(request.robot_id());
    record.set_system(request.system());
    record.set_unregistered(true);
    options_.on_membership(record);
  }
  return grpc::Status::OK;
}

void Registry::onRetired(SystemLink* link) {
  absl::MutexLock lock(&mutex_);
  auto it = std::find_if(links_.begin(), links_.end(),
                         [link](const std::shared_ptr<SystemLink>& l) { return l.get() == link; });
  if (it == links_.end()) return;
  retired_.push_back(std::move(*it));
  links_.erase(it);
  updateGaugeLocked();
}

void Registry::updateGaugeLocked() {
  metrics_.systems_registered.Set(static_cast<double>(links_.size()));
}

void Registry::listSystems(const std::string& robot_id, v1::ListSystemsResponse* response) const {
  std::vector<v1::SystemInfo> infos;
  {
    absl::MutexLock lock(&mutex_);
    for (const auto& link : links_) {
      if (link->retired() || (!robot_id.empty() && link->robotId() != robot_id)) continue;
      infos.push_back(link->info());
    }
  }
  std::sort(infos.begin(), infos.end(), [](const v1::SystemInfo& a, const v1::SystemInfo& b) {
    return std::tie(a.robot_id(), a.system(), a.address()) <
           std::tie(b.robot_id(), b.system(), b.address());
  });
  for (auto& info : infos) *response->add_systems() = std::move(info);
}

void Registry::listBehaviors(const std::string& robot_id, const std::string& behavior,
                             v1::ListFleetBehaviorsResponse* response) const {
  {
    absl::MutexLock lock(&mutex_);
    for (const auto& link : links_) {
      if (link->retired() || (!robot_id.empty() && link->robotId() != robot_id)) continue;
      link->describeBehaviors(behavior, response->mutable_behaviors());
    }
  }
  auto* behaviors = response->mutable_behaviors();
  std::sort(behaviors->begin(), behaviors->end(),
            [](const v1::FleetBehavior& a, const v1::FleetBehavior& b) {
              return std::tie(a.robot_id(), a.description().name(), a.system()) <
                     std::tie(b.robot_id(), b.description().name(), b.system());
            });
}

std::vector<SystemLink::BehaviorView> Registry::robotBehaviors(const std::string& robot_id) const {
  std::vector<SystemLink::BehaviorView> views;
  absl::MutexLock lock(&mutex_);
  for (const auto& link : links_) {
    if (link->retired() || link->robotId() != robot_id) continue;
    link->viewBehaviors(&views);
  }
  return views;
}

grpc::Status Registry::route(const std::string& robot_id, const std::string& behavior,
                             Route* out) const {
  if (robot_id.empty()) {
    return missingField("robot_id", "robot_id is empty: name the robot");
  }
  if (behavior.empty()) {
    return missingField("behavior", "behavior is empty: name the behavior, e.g. WAIT");
  }
  absl::MutexLock lock(&mutex_);
  std::set<std::string> robots;
  std::set<std::string> hosted;
  std::vector<std::shared_ptr<SystemLink>> candidates;
  std::string unreached;
  for (const auto& link : links_) {
    if (link->retired()) continue;
    robots.insert(link->robotId());
    if (link->robotId() != robot_id) continue;
    const auto names = link->behaviorNames();
    if (names.empty() && link->system().empty()) unreached = link->address();
    hosted.insert(names.begin(), names.end());
    if (link->hosts(behavior)) candidates.push_back(link);
  }
  if (!robots.contains(robot_id)) {
    return errors::grpcError(
        grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_ROBOT,
        "unknown robot '" + robot_id +
            "': no behavior system of it is registered; known robots: " + join(robots),
        {{"robot", robot_id}});
  }
  if (candidates.empty()) {
    if (!unreached.empty()) {
      return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SYSTEM_UNAVAILABLE,
                               "robot " + robot_id + " has a system at " + unreached +
                                   " that has not been reached yet, and no other system hosting '" +
                                   behavior + "'; retry later",
                               {{"robot", robot_id}, {"behavior", behavior}});
    }
    return errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_BEHAVIOR,
                             "robot " + robot_id + " has no behavior '" + behavior +
                                 "'; its systems host: " + join(hosted),
                             {{"robot", robot_id}, {"behavior", behavior}});
  }
  grpc::Status status;
  for (const auto& link : candidates) {
    if (auto stub = link->stubForCall(&status)) {
      out->stub = std::move(stub);
      out->robot_id = robot_id;
      out->system = link->system();
      out->address = link->address();
      return grpc::Status::OK;
    }
  }
  return status;
}

}  // namespace behaviorlib::coordinator
