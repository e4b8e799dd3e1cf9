#include "coordinator/catalog/planner.h"

#include <algorithm>
#include <map>
#include <sstream>
#include <thread>

#include "behaviorlib/error_details.h"

namespace behaviorlib::coordinator {
namespace {

template <typename... Args>
std::string cat(const Args&... args) {
  std::ostringstream out;
  (out << ... << args);
  return out.str();
}

const std::vector<std::string>& noNames() {
  static const std::vector<std::string> empty;
  return empty;
}

bool contains(const std::vector<std::string>& v, const std::string& x) {
  return std::find(v.begin(), v.end(), x) != v.end();
}

// The catalog's view of a behavior (an unlisted behavior has no rules).
struct Rules {
  const Catalog& catalog;
  const std::vector<std::string>& provides(const std::string& b) const {
    const CatalogBehavior* e = catalog.find(b);
    return e ? e->provides : noNames();
  }
  const std::vector<std::string>& requires_(const std::string& b) const {
    const CatalogBehavior* e = catalog.find(b);
    return e ? e->requires_ : noNames();
  }
  const std::vector<std::string>& holds(const std::string& b) const {
    const CatalogBehavior* e = catalog.find(b);
    return e ? e->holds : noNames();
  }
};

class Planner {
 public:
  Planner(const Catalog& catalog, const PlanRequest& request)
      : rules_{catalog}, catalog_(catalog), request_(request) {}

  absl::StatusOr<Plan> run() {
    const std::string& target = request_.target;
    if (!request_.available.count(target)) {
      return errors::withReason(absl::NotFoundError(cat("no registered behavior system of robot '",
                                                        request_.robot_id, "' hosts ", target)),
                                v1::UNKNOWN_BEHAVIOR,
                                {{"robot", request_.robot_id}, {"behavior", target}});
    }
    if (request_.active.count(target)) {
      return errors::withReason(
          absl::FailedPreconditionError(
              cat(target, " is already active on robot '", request_.robot_id,
                  "': deactivate it first, or change its parameters with Modify")),
          v1::BEHAVIOR_ALREADY_ACTIVE, {{"robot", request_.robot_id}, {"behavior", target}});
    }
    // Iterate to a fixed point: a deactivation can remove a provider, which
    // adds a requirement activation, which can add a conflict.
    for (int round = 0; round < 64; ++round) {
      if (auto s = resolveRequirements(); !s.ok()) return s;
      const size_t before = deactivate_.size();
      if (auto s = findConflicts(); !s.ok()) return s;
      findOrphans();
      if (deactivate_.size() == before) return build();
    }
    return absl::InternalError("the activation plan did not converge");
  }

 private:
  bool stillActive(const std::string& b) const {
    return request_.active.count(b) && !deactivate_reason_.count(b);
  }

  bool providedBy(const std::string& capability, const std::vector<std::string>& planned) const {
    for (const auto& b : request_.active) {
      if (stillActive(b) && contains(rules_.provides(b), capability)) return true;
    }
    for (const auto& b : planned) {
      if (contains(rules_.provides(b), capability)) return true;
    }
    return false;
  }

  // Orders the target and the default providers of its missing requirements,
  // requirements first.
  absl::Status resolveRequirements() {
    order_.clear();
    reasons_.clear();
    return visit(request_.target, "the target");
  }

  absl::Status visit(const std::string& b, const std::string& reason) {
    if (contains(order_, b)) return absl::OkStatus();
    for (const auto& cap : rules_.requires_(b)) {
      if (contains(rules_.provides(b), cap)) continue;
      std::vector<std::string> planned = order_;
      if (providedBy(cap, planned)) continue;
      const Capability* c = catalog_.capability(cap);
      const errors::Metadata about = {{"robot", request_.robot_id}, {"behavior", b}};
      if (c == nullptr || c->default_provider.empty()) {
        return errors::withReason(
            absl::FailedPreconditionError(
                cat(b, " requires ", cap, ", which no active behavior of robot '",
                    request_.robot_id, "' provides and the catalog names no default for")),
            v1::REQUIREMENT_NOT_MET, about);
      }
      if (!request_.available.count(c->default_provider)) {
        return errors::withReason(
            absl::FailedPreconditionError(
                cat(b, " requires ", cap, "; its default provider ", c->default_provider,
                    " is not hosted by any registered behavior system of robot '",
                    request_.robot_id, "'")),
            v1::REQUIREMENT_NOT_MET, about);
      }
      if (request_.active.count(c->default_provider)) {
        return errors::withReason(
            absl::FailedPreconditionError(
                cat(b, " requires ", cap, ", but its default provider ", c->default_provider,
                    " must be deactivated: ", deactivate_reason_.at(c->default_provider))),
            v1::REQUIREMENT_NOT_MET, about);
      }
      if (auto s = visit(c->default_provider, cat("provides ", cap, " required by ", b)); !s.ok()) {
        return s;
      }
    }
    order_.push_back(b);
    reasons_[b] = reason;
    return absl::OkStatus();
  }

  absl::Status findConflicts() {
    std::map<std::string, std::string> holder;  // resource -> planned behavior
    for (const auto& b : order_) {
      for (const auto& r : rules_.holds(b)) {
        if (auto it = holder.find(r); it != holder.end()) {
          return errors::withReason(
              absl::InvalidArgumentError(cat("the catalog makes ", b, " and ", it->second,
                                             " both hold ", r, ", but ", request_.target,
                                             " needs both (", catalog_.fileName(), ")")),
              v1::RESOURCE_CONFLICT, {{"robot", request_.robot_id}});
        }
        holder[r] = b;
      }
    }
    for (const auto& a : request_.active) {
      if (!stillActive(a)) continue;
      for (const auto& r : rules_.holds(a)) {
        if (auto it = holder.find(r); it != holder.end()) {
          markDeactivate(a, cat("holds ", r, ", which ", it->second, " needs"));
          break;
        }
      }
    }
    return absl::OkStatus();
  }

  // Active behaviors whose requirement nothing would provide any more.
  void findOrphans() {
    bool changed = true;
    while (changed) {
      changed = false;
      for (const auto& a : request_.active) {
        if (!stillActive(a)) continue;
        for (const auto& cap : rules_.requires_(a)) {
          if (contains(rules_.provides(a), cap) || providedBy(cap, order_)) continue;
          markDeactivate(a, cat("would lose ", cap, ", which it requires"));
          changed = true;
          break;
        }
      }
    }
  }

  void markDeactivate(const std::string& b, const std::string& reason) {
    if (deactivate_reason_.emplace(b, reason).second) deactivate_.push_back(b);
  }

  Plan build() const {
    Plan plan;
    plan.robot_id = request_.robot_id;
    plan.target = request_.target;
    // Users before what they use: a behavior is deactivated once no other
    // behavior still to be deactivated requires a capability it provides.
    std::vector<std::string> pending = deactivate_;
    while (!pending.empty()) {
      auto next = std::find_if(pending.begin(), pending.end(), [&](const std::string& x) {
        return std::none_of(pending.begin(), pending.end(), [&](const std::string& y) {
          if (y == x) return false;
          for (const auto& cap : rules_.requires_(y)) {
            if (contains(rules_.provides(x), cap)) return true;
          }
          return false;
        });
      });
      if (next == pending.end()) next = pending.begin();  // a cycle: keep discovery order
      plan.steps.push_back({StepKind::kDeactivate, *next, {}, deactivate_reason_.at(*next)});
      pending.erase(next);
    }
    for (const auto& b : order_) {
      plan.steps.push_back({StepKind::kCheckSituation, b, {}, reasons_.at(b)});
      PlanStep activate{StepKind::kActivate, b, {}, reasons_.at(b)};
      if (b == request_.target) {
        activate.parameters = request_.parameters;
      } else if (const CatalogBehavior* e = catalog_.find(b)) {
        activate.parameters = e->defaults;
      }
      plan.steps.push_back(std::move(activate));
    }
    return plan;
  }

  Rules rules_;
  const Catalog& catalog_;
  const PlanRequest& request_;
  std::vector<std::string> order_;
  std::map<std::string, std::string> reasons_;
  std::vector<std::string> deactivate_;
  std::map<std::string, std::string> deactivate_reason_;
};

}  // namespace

const char* stepKindName(StepKind kind) {
  switch (kind) {
    case StepKind::kDeactivate:
      return "deactivate";
    case StepKind::kCheckSituation:
      return "check_situation";
    case StepKind::kActivate:
      return "activate";
  }
  return "?";
}

void planToProto(const Plan& plan,
                 google::protobuf::RepeatedPtrField<v1::ActivationPlanStep>* out) {
  for (const PlanStep& step : plan.steps) {
    v1::ActivationPlanStep* added = out->Add();
    added->set_kind(step.kind == StepKind::kDeactivate ? v1::ActivationPlanStep::KIND_DEACTIVATE
                    : step.kind == StepKind::kCheckSituation
                        ? v1::ActivationPlanStep::KIND_CHECK_SITUATION
                        : v1::ActivationPlanStep::KIND_ACTIVATE);
    added->set_behavior(step.behavior);
    *added->mutable_parameters() = step.parameters;
    added->set_reason(step.reason);
  }
}

void applyToActive(const Plan& plan, std::set<std::string>* active) {
  for (const PlanStep& step : plan.steps) {
    if (step.kind == StepKind::kDeactivate) active->erase(step.behavior);
    if (step.kind == StepKind::kActivate) active->insert(step.behavior);
  }
}

absl::StatusOr<Plan> makePlan(const Catalog& catalog, const PlanRequest& request) {
  return Planner(catalog, request).run();
}

absl::StatusOr<PlanResult> applyPlan(const Plan& plan, PlanActions& actions,
                                     const ApplyOptions& options) {
  PlanResult result;
  auto sleep = options.sleep ? options.sleep
                             : [](std::chrono::milliseconds d) { std::this_thread::sleep_for(d); };
  auto fail = [&](size_t index, const absl::Status& status) -> absl::Status {
    // Stop what this plan started, newest first; report the original error.
    std::string rollback;
    for (auto it = result.activated.rbegin(); it != result.activated.rend(); ++it) {
      if (absl::Status s = actions.deactivate(it->first); !s.ok()) {
        rollback += cat("; rolling back ", it->first, " failed too: ", s.message());
      }
    }
    const PlanStep& step = plan.steps[index];
    // The step's error details (a system's reason and field violations)
    // stay with the reworded error.
    return errors::withMetadata(
        errors::rewrap(
            status,
            cat("step ", index + 1, " of ", plan.steps.size(), " (", stepKindName(step.kind), " ",
                step.behavior, ") on robot '", plan.robot_id, "' failed: ", status.message(),
                result.activated.empty() ? "" : "; what the plan activated was stopped", rollback)),
        {{"robot", plan.robot_id}, {"behavior", step.behavior}});
  };
  for (size_t i = 0; i < plan.steps.size(); ++i) {
    const PlanStep& step = plan.steps[i];
    switch (step.kind) {
      case StepKind::kDeactivate:
        if (absl::Status s = actions.deactivate(step.behavior); !s.ok()) {
          // FAILED_PRECONDITION: it is not active. It finished on its own
          // between the plan and this step (the plan reads streamed state;
          // a safety action may have just stopped it): nothing to stop.
          if (s.code() != absl::StatusCode::kFailedPrecondition) return fail(i, s);
        } else {
          result.deactivated.push_back(step.behavior);
        }
        break;
      case StepKind::kCheckSituation: {
        absl::Status s = actions.checkSituation(step.behavior);
        const auto window = result.activated.empty() ? options.lag_timeout : options.settle_timeout;
        if (!s.ok() && options.settle_poll.count() > 0) {
          for (auto waited = std::chrono::milliseconds(0); !s.ok() && waited < window;
               waited += options.settle_poll) {
            sleep(options.settle_poll);
            s = actions.checkSituation(step.behavior);
          }
        }
        if (!s.ok()) return fail(i, s);
        break;
      }
      case StepKind::kActivate: {
        absl::StatusOr<std::string> id = actions.activate(step.behavior, step.parameters);
        if (!id.ok()) return fail(i, id.status());
        result.activated.emplace_back(step.behavior, *id);
        if (step.behavior == plan.target) result.activation_id = *id;
        break;
      }
    }
  }
  return result;
}

}  // namespace behaviorlib::coordinator
