#include "coordinator/registry/system_link.h"

#include <algorithm>
#include <cstdio>
#include <utility>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/reactor_order.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "coordinator/registry/health_check.h"

namespace behaviorlib::coordinator {

namespace {

constexpr std::chrono::milliseconds kInitialBackoff(100);
// Events per message asked of a system's stream (WatchEventsRequest.max_events_per_message).
constexpr uint32_t kIntakeBatch = 256;
constexpr std::chrono::milliseconds kMaxBackoff(2000);
constexpr std::chrono::milliseconds kFailingProbePause(50);

using WallClock = std::chrono::system_clock;

void setTimestamp(google::protobuf::Timestamp* timestamp, WallClock::time_point time) {
  const auto since_epoch =
      std::chrono::duration_cast<std::chrono::nanoseconds>(time.time_since_epoch());
  const auto seconds = std::chrono::floor<std::chrono::seconds>(since_epoch);
  timestamp->set_seconds(seconds.count());
  timestamp->set_nanos(static_cast<int32_t>((since_epoch - seconds).count()));
}

std::string describeStatus(const grpc::Status& status) {
  if (status.ok()) return "ended by the system";
  return status.error_message().empty()
             ? "code " + std::to_string(static_cast<int>(status.error_code()))
             : status.error_message();
}

std::string secondsText(std::chrono::nanoseconds d) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.1f s", std::chrono::duration<double>(d).count());
  return text;
}

void logLine(const std::string& line) { std::fprintf(stderr, "coordinator: %s\n", line.c_str()); }

v1::FleetEvent behaviorFleetEvent(v1::BehaviorEvent event, bool synthesized) {
  v1::FleetEvent out;
  out.set_synthesized(synthesized);
  *out.mutable_behavior_event() = std::move(event);
  return out;
}

}  // namespace

grpc::ChannelArguments fastReconnectArguments() {
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, static_cast<int>(kInitialBackoff.count()));
  // gRPC gives each connection attempt at least this long (its "minimum
  // connect timeout"); a refused attempt is still retried after the initial
  // backoff. At 100 ms, a server slow to send its HTTP/2 settings on a loaded
  // machine failed the call.
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 5000);
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, static_cast<int>(kMaxBackoff.count()));
  return args;
}

SystemLink::SystemLink(LinkIdentity identity, FleetEventLog& log, CoordinatorMetrics& metrics,
                       LinkOptions options, std::function<void(SystemLink*)> on_retired)
    : identity_(std::move(identity)),
      robot_id_(identity_.robot_id),
      source_(identity_.source),
      log_(log),
      metrics_(metrics),
      options_(options),
      on_retired_(std::move(on_retired)),
      tracker_(identity_.robot_id, identity_.system),
      supervision_(options.grace) {
  rebuildChannelLocked();
}

SystemLink::~SystemLink() { stop(); }

void SystemLink::start() {
  thread_ = std::thread([this] { run(); });
  watch_thread_ = std::thread([this] { watch(); });
}

void SystemLink::stop() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
    if (stream_call_ != nullptr) stream_call_->TryCancel();
    if (call_ != nullptr) call_->TryCancel();
    if (watch_call_ != nullptr) watch_call_->TryCancel();
  }
  if (thread_.joinable() && thread_.get_id() != std::this_thread::get_id()) thread_.join();
  if (watch_thread_.joinable() && watch_thread_.get_id() != std::this_thread::get_id()) {
    watch_thread_.join();
  }
}

void SystemLink::rebuildChannelLocked() {
  channel_ = behaviorlib::server_kit::makeChannel(identity_.address, fastReconnectArguments());
  stub_ = v1::BehaviorSystem::NewStub(channel_);
}

void SystemLink::setStreamCall(grpc::ClientContext* context) {
  absl::MutexLock lock(&mutex_);
  stream_call_ = context;
  if (context != nullptr && (stopping_ || poked_)) context->TryCancel();
}

void SystemLink::setCall(grpc::ClientContext* context) {
  absl::MutexLock lock(&mutex_);
  call_ = context;
  if (context != nullptr && (stopping_ || poked_)) context->TryCancel();
}

void SystemLink::setWatchCall(grpc::ClientContext* context) {
  absl::MutexLock lock(&mutex_);
  watch_call_ = context;
  if (context != nullptr && stopping_) context->TryCancel();
}

void SystemLink::pokeLocked() {
  poked_ = true;
  if (stream_call_ != nullptr) stream_call_->TryCancel();
  if (call_ != nullptr) call_->TryCancel();
}

void SystemLink::waitFor(std::chrono::milliseconds duration) {
  absl::MutexLock lock(&mutex_);
  auto ready = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) { return stopping_ || poked_; };
  mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(duration));
}

std::string SystemLink::nameLocked() const {
  const std::string system = identity_.system.empty() ? "the system" : "system " + identity_.system;
  return system + " of robot " + identity_.robot_id + " at " + identity_.address;
}

std::optional<v1::FleetEvent> SystemLink::setStateLocked(v1::SystemState state,
                                                         std::string message) {
  const v1::SystemState previous = state_;
  state_message_ = std::move(message);
  if (state == previous) return std::nullopt;
  if (previous == v1::SYSTEM_STATE_UP) metrics_.systems_up.Decrement();
  if (state == v1::SYSTEM_STATE_UP) metrics_.systems_up.Increment();
  state_ = state;
  state_time_ = WallClock::now();
  logLine(nameLocked() + ": " + v1::SystemState_Name(state) + " (" + state_message_ + ")");
  v1::FleetEvent event;
  auto* changed = event.mutable_system_state_changed();
  *changed->mutable_system() = infoLocked();
  changed->set_previous_state(previous);
  return event;
}

void SystemLink::append(std::vector<v1::FleetEvent> events) {
  for (auto& event : events) log_.append(std::move(event));
}

// ---------------------------------------------------------------------------
// The intake thread

void SystemLink::run() {
  {
    std::optional<v1::FleetEvent> event;
    {
      absl::MutexLock lock(&mutex_);
      event =
          setStateLocked(v1::SYSTEM_STATE_CONNECTING, identity_.source == v1::SYSTEM_SOURCE_CONFIG
                                                          ? "listed in --systems; contacting it"
                                                          : "registered; opening its event stream");
    }
    if (event) log_.append(std::move(*event));
  }
  std::chrono::milliseconds backoff = kInitialBackoff;
  while (true) {
    std::shared_ptr<grpc::Channel> channel;
    std::shared_ptr<v1::BehaviorSystem::Stub> stub;
    v1::WatchEventsRequest request;
    bool leaving = false;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      poked_ = false;
      leaving = leaving_;
      channel = channel_;
      stub = stub_;
      request.set_since_seq(tracker_.lastSeq());
      request.set_incarnation(tracker_.incarnation());
      // What the system has queued for us, in one message.
      request.set_max_events_per_message(kIntakeBatch);
    }
    if (leaving) {
      if (!finishLeaving()) return;
      continue;
    }

    const StreamEnd end = readStream(*stub, request);
    if (end.got_start) backoff = kInitialBackoff;
    bool poked = false;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      if (leaving_) continue;
      // A stream the watchdog broke is handled as broken even if poked.
      poked = poked_ && !stalled_;
    }
    // Poked: the address or the registration changed; reconnect at once.
    if (poked) continue;
    std::string stall_detail;
    if (onBroken(end.reason, &stall_detail)) {
      // The watchdog's probes have failed for the grace period already.
      declareDown(stall_detail, /*stopped_answering=*/true);
    }

    // Probe the system's health until it answers, it is re-registered, or
    // the coordinator stops.
    while (true) {
      {
        absl::MutexLock lock(&mutex_);
        if (stopping_ || poked_ || leaving_) break;
      }
      const HealthResult health = checkHealth(channel, "", options_.health_timeout,
                                              [this](grpc::ClientContext* c) { setCall(c); });
      if (health.serving) {
        waitFor(backoff);
        backoff = std::min(backoff * 2, kMaxBackoff);
        break;
      }
      declareDown(health.detail);
      bool idle = false;
      {
        absl::MutexLock lock(&mutex_);
        idle = supervision_.down() || state_ == v1::SYSTEM_STATE_UNREGISTERED;
      }
      waitFor(idle ? options_.idle_probe_interval : options_.probe_interval);
    }
  }
}

void SystemLink::watch() {
  while (true) {
    std::shared_ptr<grpc::Channel> channel;
    uint64_t generation = 0;
    std::string trigger;
    {
      absl::MutexLock lock(&mutex_);
      // While probes fail, probe again soon: a failed probe already took its
      // whole deadline, and the grace period counts from the first one.
      const auto pause = supervision_.streamIsUp() && supervision_.failingSince()
                             ? std::min(options_.stall_probe_interval, kFailingProbePause)
                             : options_.stall_probe_interval;
      mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(pause));
      if (stopping_) return;
      // Only a stream that is up can hide a frozen process; otherwise the
      // intake thread probes health itself.
      if (state_ != v1::SYSTEM_STATE_UP || !supervision_.streamIsUp() || stalled_ || leaving_) {
        continue;
      }
      const auto now = std::chrono::steady_clock::now();
      const auto silent = now - last_activity_;
      std::optional<std::chrono::nanoseconds> heartbeat_age;
      if (identity_.source == v1::SYSTEM_SOURCE_REGISTRATION && last_heartbeat_) {
        heartbeat_age = WallClock::now() - *last_heartbeat_;
      }
      // A silent stream is normal for an idle system: while its heartbeats
      // come, it is probed only when it runs behaviors (a frozen controller
      // must be noticed within the grace period); without heartbeats (a
      // --systems entry), at most once a heartbeat interval.
      const bool busy = !tracker_.active().empty();
      const bool probe_silence =
          busy || (!heartbeat_age && now - last_silence_probe_ >= options_.heartbeat_interval);
      if (heartbeat_age && *heartbeat_age > 2 * options_.heartbeat_interval) {
        trigger = "no heartbeat for " + secondsText(*heartbeat_age);
      } else if (silent >= options_.silence && probe_silence) {
        trigger = "its event stream was silent for " + secondsText(silent);
        last_silence_probe_ = now;
      } else {
        // The stream carries messages: the process answers.
        supervision_.healthChecked(true, now);
        continue;
      }
      channel = channel_;
      generation = stream_generation_;
    }
    const auto probed = std::chrono::steady_clock::now();
    const HealthResult health = checkHealth(channel, "", options_.stall_probe_timeout,
                                            [this](grpc::ClientContext* c) { setWatchCall(c); });
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    // The stream changed meanwhile: this probe says nothing about it.
    if (generation != stream_generation_ || state_ != v1::SYSTEM_STATE_UP ||
        !supervision_.streamIsUp() || stalled_) {
      continue;
    }
    supervision_.healthChecked(health.serving, probed);
    if (!supervision_.unanswered(std::chrono::steady_clock::now())) continue;
    // Frozen: break the stream; the intake thread declares the system down.
    stalled_ = true;
    stall_detail_ = trigger + "; " + health.detail;
    logLine(nameLocked() + ": stopped answering (" + stall_detail_ + "); breaking its stream");
    if (stream_call_ != nullptr) stream_call_->TryCancel();
  }
}

SystemLink::StreamEnd SystemLink::readStream(v1::BehaviorSystem::Stub& stub,
                                             const v1::WatchEventsRequest& request) {
  grpc::ClientContext context;
  setStreamCall(&context);
  auto reader = stub.WatchEvents(&context, request);
  v1::WatchEventsResponse message;
  StreamEnd end;
  bool refused = false;
  if (reader->Read(&message) && message.has_start()) {
    end.got_start = true;
    if (onStart(message.start(), stub)) {
      while (reader->Read(&message)) {
        {
          absl::MutexLock lock(&mutex_);
          last_activity_ = std::chrono::steady_clock::now();
        }
        if (message.has_event()) {
          onEvents({&message.event()}, context);
        } else if (message.has_events()) {
          std::vector<const v1::BehaviorEvent*> events;
          events.reserve(static_cast<size_t>(message.events().events_size()));
          for (const v1::BehaviorEvent& event : message.events().events()) events.push_back(&event);
          onEvents(events, context);
        }
      }
    } else {
      refused = true;
      context.TryCancel();
      while (reader->Read(&message)) {
      }
    }
  }
  const grpc::Status status = reader->Finish();
  setStreamCall(nullptr);
  if (refused) {
    absl::MutexLock lock(&mutex_);
    end.reason = start_failure_;
  } else {
    end.reason = describeStatus(status);
  }
  return end;
}

bool SystemLink::onStart(const v1::WatchEventsStart& start, v1::BehaviorSystem::Stub& stub) {
  bool need_description = false;
  {
    absl::MutexLock lock(&mutex_);
    // After a clean exit, only a new run of the system brings it back.
    if (state_ == v1::SYSTEM_STATE_UNREGISTERED && start.incarnation() == tracker_.incarnation()) {
      start_failure_ = "the unregistered run is still serving";
      return false;
    }
    need_description = description_.incarnation() != start.incarnation();
  }
  if (need_description) {
    grpc::ClientContext context;
    context.set_deadline(WallClock::now() + options_.call_timeout);
    setCall(&context);
    v1::ListBehaviorsRequest request;
    request.set_page_size(kMaxBehaviorsPerSystem);
    v1::ListBehaviorsResponse description;
    const grpc::Status status = stub.ListBehaviors(&context, request, &description);
    setCall(nullptr);
    absl::MutexLock lock(&mutex_);
    if (!status.ok()) {
      start_failure_ = "ListBehaviors failed: " + describeStatus(status);
      return false;
    }
    if (!description.next_page_token().empty()) {
      start_failure_ = "it hosts more than " + std::to_string(kMaxBehaviorsPerSystem) +
                       " behaviors, the most a coordinator registers per system";
      return false;
    }
    // Raced with another restart: the next attempt sees the newest one.
    if (description.incarnation() != start.incarnation()) {
      start_failure_ = "it restarted while being described";
      return false;
    }
    if (description.robot_id() != identity_.robot_id) {
      start_failure_ = identity_.address + " serves robot '" + description.robot_id() +
                       "', not robot '" + identity_.robot_id + "'";
      logLine(nameLocked() + ": " + start_failure_);
      return false;
    }
    description_ = std::move(description);
    identity_.system = description_.system();
    tracker_.setSystem(identity_.system);
    registered_incarnation_ = description_.incarnation();
  }

  std::vector<v1::FleetEvent> out;
  bool fence_now = false;
  {
    absl::MutexLock lock(&mutex_);
    const std::string previous = tracker_.incarnation();
    if (!previous.empty() && previous != start.incarnation()) {
      // The process restarted: what ran in the old one ended with it.
      for (auto& e : tracker_.finishAll(nameLocked() + " restarted (incarnation " + previous +
                                            " ended, " + start.incarnation() +
                                            " started) while the activation was running",
                                        WallClock::now(), /*fence=*/false)) {
        out.push_back(behaviorFleetEvent(std::move(e), /*synthesized=*/true));
      }
      metrics_.events_synthesized.Increment(static_cast<double>(out.size()));
    }
    tracker_.startIncarnation(start.incarnation());
    if (had_stream_) metrics_.stream_reconnects.Increment();
    had_stream_ = true;
    ++stream_generation_;
    last_activity_ = std::chrono::steady_clock::now();
    stalled_ = false;
    supervision_.streamUp();
    if (auto event = setStateLocked(v1::SYSTEM_STATE_UP, "event stream established (incarnation " +
                                                             start.incarnation() + ")")) {
      out.push_back(std::move(*event));
    }
    replay_end_seq_ = start.latest_seq();
    fence_check_pending_ = true;
    fence_now = tracker_.lastSeq() >= replay_end_seq_;
    if (start.events_dropped()) {
      metrics_.events_lost.Increment(static_cast<double>(start.dropped_count()));
      logLine(nameLocked() + ": " + std::to_string(start.dropped_count()) + " events after seq " +
              std::to_string(tracker_.lastSeq()) + " were no longer retained by the system");
    }
  }
  append(std::move(out));
  if (fence_now) deactivateFenced();
  return true;
}

void SystemLink::onEvents(const std::vector<const v1::BehaviorEvent*>& events,
                          grpc::ClientContext& context) {
  std::vector<v1::FleetEvent> forward;
  forward.reserve(events.size());
  size_t duplicates = 0;
  bool fence_now = false;
  bool leaving_done = false;
  {
    absl::MutexLock lock(&mutex_);
    for (const v1::BehaviorEvent* event : events) {
      if (tracker_.accept(*event) == ActivationTracker::Verdict::kForward) {
        forward.push_back(behaviorFleetEvent(*event, /*synthesized=*/false));
      } else {
        ++duplicates;
      }
    }
    fence_now = fence_check_pending_ && tracker_.lastSeq() >= replay_end_seq_;
    leaving_done = leaving_ && tracker_.lastSeq() >= final_seq_;
  }
  const size_t forwarded = forward.size();
  log_.appendAll(std::move(forward));
  metrics_.events_received.Increment(static_cast<double>(forwarded));
  if (duplicates > 0) metrics_.events_dropped_duplicate.Increment(static_cast<double>(duplicates));
  if (fence_now) deactivateFenced();
  // Everything the leaving system emitted has arrived.
  if (leaving_done) context.TryCancel();
}

bool SystemLink::onBroken(const std::string& reason, std::string* detail) {
  std::optional<v1::FleetEvent> event;
  bool stalled = false;
  {
    absl::MutexLock lock(&mutex_);
    stalled = stalled_;
    stalled_ = false;
    if (stalled) *detail = stall_detail_;
    last_break_ = stalled ? "cancelled by the coordinator: the system stopped answering" : reason;
    supervision_.streamBroken(std::chrono::steady_clock::now());
    if (state_ == v1::SYSTEM_STATE_UP) {
      event = setStateLocked(v1::SYSTEM_STATE_RECONNECTING,
                             "event stream broke (" + last_break_ + "); reconnecting");
    } else if (state_ == v1::SYSTEM_STATE_CONNECTING) {
      state_message_ = "cannot open its event stream (" + last_break_ + "); retrying";
    }
  }
  if (event) log_.append(std::move(*event));
  return stalled;
}

void SystemLink::declareDown(const std::string& health_detail, bool stopped_answering) {
  std::vector<v1::FleetEvent> out;
  {
    absl::MutexLock lock(&mutex_);
    if (!supervision_.healthChecked(false, std::chrono::steady_clock::now())) return;
    if (state_ == v1::SYSTEM_STATE_UNREGISTERED) return;
    const std::string reason =
        stopped_answering
            ? "it stopped answering (frozen or hung: its connection stays open) and its health "
              "check has failed for " +
                  secondsText(supervision_.grace()) + " (" + health_detail + ")"
            : "its event stream broke (" + last_break_ + ") and its health check has failed for " +
                  secondsText(supervision_.grace()) + " (" + health_detail + ")";
    const std::string message = nameLocked() + " is down: " + reason;
    if (auto event = setStateLocked(v1::SYSTEM_STATE_DOWN, reason)) {
      out.push_back(std::move(*event));
    }
    for (auto& e : tracker_.finishAll(message, WallClock::now(), /*fence=*/true)) {
      out.push_back(behaviorFleetEvent(std::move(e), /*synthesized=*/true));
      metrics_.events_synthesized.Increment();
    }
    metrics_.systems_down.Increment();
  }
  append(std::move(out));
}

bool SystemLink::finishLeaving() {
  std::vector<v1::FleetEvent> out;
  bool retire = false;
  {
    absl::MutexLock lock(&mutex_);
    for (auto& e :
         tracker_.finishAll(nameLocked() + " unregistered before the coordinator received the "
                                           "end of this activation",
                            WallClock::now(), /*fence=*/false)) {
      out.push_back(behaviorFleetEvent(std::move(e), /*synthesized=*/true));
      metrics_.events_synthesized.Increment();
    }
    leaving_ = false;
    if (auto event = setStateLocked(
            v1::SYSTEM_STATE_UNREGISTERED,
            "unregistered (clean shutdown)" +
                std::string(identity_.source == v1::SYSTEM_SOURCE_CONFIG ? "; contacting it again"
                                                                         : ""))) {
      out.push_back(std::move(*event));
    }
    retire = identity_.source != v1::SYSTEM_SOURCE_CONFIG;
    retired_ = retire;
  }
  append(std::move(out));
  if (retire && on_retired_) on_retired_(this);
  return !retire;
}

void SystemLink::deactivateFenced() {
  std::vector<ActivationTracker::Activation> running;
  std::string name;
  std::shared_ptr<v1::BehaviorSystem::Stub> stub;
  {
    absl::MutexLock lock(&mutex_);
    fence_check_pending_ = false;
    running = tracker_.fencedStillRunning();
    name = nameLocked();
    stub = stub_;
  }
  for (const auto& activation : running) {
    // The coordinator reported this activation finished (PROCESS_FAILURE)
    // while the system was unreachable; it must not go on unseen. Its
    // INTERRUPTED event is dropped as fenced.
    logLine(name + ": deactivating " + activation.behavior + " activation " +
            activation.activation_id +
            ", reported finished while the system was unreachable but still running there");
    struct Call {
      std::shared_ptr<v1::BehaviorSystem::Stub> stub;
      grpc::ClientContext context;
      v1::DeactivateBehaviorRequest request;
      v1::DeactivateResponse response;
    };
    auto* call = new Call();
    call->stub = stub;
    call->context.set_deadline(WallClock::now() + options_.call_timeout);
    call->request.set_behavior(activation.behavior);
    call->request.set_activation_id(activation.activation_id);
    call->stub->async()->DeactivateBehavior(
        &call->context, &call->request, &call->response,
        server_kit::orderedCallback([call, name](grpc::Status status) {
          if (!status.ok()) {
            logLine(name + ": deactivating " + call->request.behavior() +
                    " failed: " + status.error_message());
          }
          delete call;
        }));
  }
}

// ---------------------------------------------------------------------------
// Called by the registry (RPC threads)

void SystemLink::registered(const std::string& address,
                            const v1::ListBehaviorsResponse& description) {
  absl::MutexLock lock(&mutex_);
  bool poke = false;
  if (address != identity_.address) {
    identity_.address = address;
    rebuildChannelLocked();
    poke = true;
  }
  if (description.incarnation() != tracker_.incarnation()) {
    // A new run: reconnect now instead of after the next failed probe, and
    // stop waiting for the old run's last events.
    poke = true;
    leaving_ = false;
  }
  description_ = description;
  identity_.system = description.system();
  tracker_.setSystem(identity_.system);
  registered_incarnation_ = description.incarnation();
  last_heartbeat_ = WallClock::now();
  if (poke) pokeLocked();
}

bool SystemLink::heartbeat(const std::string& incarnation) {
  absl::MutexLock lock(&mutex_);
  if (incarnation != registered_incarnation_) return false;
  last_heartbeat_ = WallClock::now();
  return true;
}

bool SystemLink::unregister(const std::string& incarnation, uint64_t final_seq) {
  absl::MutexLock lock(&mutex_);
  if (incarnation != registered_incarnation_) return false;
  leaving_ = true;
  final_seq_ = final_seq;
  if (tracker_.incarnation() != incarnation || tracker_.lastSeq() >= final_seq ||
      state_ != v1::SYSTEM_STATE_UP) {
    pokeLocked();
  }
  return true;
}

std::string SystemLink::system() const {
  absl::MutexLock lock(&mutex_);
  return identity_.system;
}

std::string SystemLink::address() const {
  absl::MutexLock lock(&mutex_);
  return identity_.address;
}

std::string SystemLink::registeredIncarnation() const {
  absl::MutexLock lock(&mutex_);
  return registered_incarnation_;
}

v1::SystemState SystemLink::state() const {
  absl::MutexLock lock(&mutex_);
  return state_;
}

bool SystemLink::retired() const {
  absl::MutexLock lock(&mutex_);
  return retired_;
}

bool SystemLink::leaving() const {
  absl::MutexLock lock(&mutex_);
  return leaving_;
}

v1::SystemInfo SystemLink::info() const {
  absl::MutexLock lock(&mutex_);
  return infoLocked();
}

v1::SystemInfo SystemLink::infoLocked() const {
  v1::SystemInfo info;
  info.set_robot_id(identity_.robot_id);
  info.set_system(identity_.system);
  info.set_address(identity_.address);
  info.set_incarnation(tracker_.incarnation().empty() ? registered_incarnation_
                                                      : tracker_.incarnation());
  info.set_state(state_);
  info.set_source(identity_.source);
  info.set_state_message(state_message_);
  if (state_ != v1::SYSTEM_STATE_UNSPECIFIED) setTimestamp(info.mutable_state_time(), state_time_);
  if (last_heartbeat_) setTimestamp(info.mutable_last_heartbeat_time(), *last_heartbeat_);
  info.set_last_event_seq(tracker_.lastSeq());
  for (const auto& b : description_.behaviors()) info.add_behaviors(b.name());
  return info;
}

std::vector<std::string> SystemLink::behaviorNames() const {
  absl::MutexLock lock(&mutex_);
  std::vector<std::string> names;
  for (const auto& b : description_.behaviors()) names.push_back(b.name());
  return names;
}

bool SystemLink::hosts(const std::string& behavior) const {
  absl::MutexLock lock(&mutex_);
  return std::any_of(description_.behaviors().begin(), description_.behaviors().end(),
                     [&](const v1::BehaviorDescription& b) { return b.name() == behavior; });
}

void SystemLink::viewBehaviors(std::vector<BehaviorView>* out) const {
  absl::MutexLock lock(&mutex_);
  const bool tracked = state_ == v1::SYSTEM_STATE_UP || state_ == v1::SYSTEM_STATE_RECONNECTING;
  const auto& active = tracker_.active();
  for (const auto& description : description_.behaviors()) {
    BehaviorView view;
    view.name = description.name();
    view.system_up = state_ == v1::SYSTEM_STATE_UP;
    if (tracked) {
      view.state = v1::BEHAVIOR_STATE_INACTIVE;
      if (auto it = active.find(description.name()); it != active.end()) {
        view.state = it->second.state;
        view.activation_id = it->second.activation_id;
      }
    }
    out->push_back(std::move(view));
  }
}

void SystemLink::describeBehaviors(
    const std::string& behavior, google::protobuf::RepeatedPtrField<v1::FleetBehavior>* out) const {
  absl::MutexLock lock(&mutex_);
  const bool tracked = state_ == v1::SYSTEM_STATE_UP || state_ == v1::SYSTEM_STATE_RECONNECTING;
  for (const auto& description : description_.behaviors()) {
    if (!behavior.empty() && description.name() != behavior) continue;
    auto* b = out->Add();
    b->set_robot_id(identity_.robot_id);
    b->set_system(identity_.system);
    b->set_address(identity_.address);
    b->set_system_state(state_);
    *b->mutable_description() = description;
    b->mutable_description()->set_state(v1::BEHAVIOR_STATE_UNSPECIFIED);
    if (!tracked) continue;
    const auto& active = tracker_.active();
    if (auto it = active.find(description.name()); it != active.end()) {
      b->mutable_description()->set_state(it->second.state);
      b->set_activation_id(it->second.activation_id);
    } else {
      b->mutable_description()->set_state(v1::BEHAVIOR_STATE_INACTIVE);
    }
  }
}

std::shared_ptr<v1::BehaviorSystem::Stub> SystemLink::stubForCall(grpc::Status* status) const {
  absl::MutexLock lock(&mutex_);
  if (state_ == v1::SYSTEM_STATE_DOWN || state_ == v1::SYSTEM_STATE_UNREGISTERED) {
    *status = errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SYSTEM_UNAVAILABLE,
                                nameLocked() + " is " +
                                    (state_ == v1::SYSTEM_STATE_DOWN ? "down" : "unregistered") +
                                    " (" + state_message_ + "); retry when it is back",
                                {{"robot", identity_.robot_id}, {"system", identity_.system}});
    return nullptr;
  }
  return stub_;
}

}  // namespace behaviorlib::coordinator
