// behaviorctl record and replay: the flight recorder (decision 36).
//
//   behaviorctl --coordinator C --channel B record FILE [--topics a,b] [--duration-s S]
//   behaviorctl --channel B replay FILE [--speed X] [--topic-prefix P]
//
// record follows the coordinator and the data channel into FILE (MCAP)
// until SIGINT or SIGTERM (or --duration-s), then closes it with its
// summary; it hands what it has to the operating system every second, so a
// recorder that is killed leaves a file readable up to then. Both print one
// JSON line of what they did.

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <thread>

#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/recorder/recorder.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "clients/behaviorctl/behaviorctl_commands.h"

namespace behaviorlib::behaviorctl {

namespace {

std::atomic<bool> g_stop{false};

void onSignal(int) { g_stop = true; }

// One JSON line on stdout.
void printJson(const google::protobuf::Struct& line) {
  std::string out;
  (void)google::protobuf::util::MessageToJsonString(line, &out);
  std::printf("%s\n", out.c_str());
  std::fflush(stdout);
}

google::protobuf::Value counts(const std::map<std::string, uint64_t>& by_topic) {
  google::protobuf::Value value;
  auto* fields = value.mutable_struct_value()->mutable_fields();
  for (const auto& [topic, count] : by_topic) {
    (*fields)[topic].set_number_value(static_cast<double>(count));
  }
  return value;
}

int failWith(const absl::Status& status) {
  std::fprintf(stderr, "behaviorctl: %s\n", status.ToString().c_str());
  return 1;
}

}  // namespace

int runRecord(const CtlOptions& options) {
  if (options.args.size() != 2 || options.coordinator.empty()) {
    std::fputs("behaviorctl: record FILE needs --coordinator (and --channel for samples)\n",
               stderr);
    return 2;
  }
  recorder::RecorderOptions recorder_options;
  recorder_options.path = options.args[1];
  if (!options.channel.empty()) {
    recorder_options.data_channel = server_kit::makeChannel(options.channel);
  }
  if (!options.topics.empty()) {
    recorder_options.topics = absl::StrSplit(options.topics, ',', absl::SkipEmpty());
  }
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  auto recording =
      recorder::Recorder::start(server_kit::makeChannel(options.coordinator), recorder_options);
  if (!recording.ok()) return failWith(recording.status());
  std::fprintf(stderr, "behaviorctl: recording into %s (topics %s) until interrupted\n",
               recorder_options.path.c_str(), absl::StrJoin(recorder_options.topics, ",").c_str());
  const auto started = std::chrono::steady_clock::now();
  auto flushed = started;
  while (!g_stop) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    const auto now = std::chrono::steady_clock::now();
    if (options.duration_s > 0 &&
        now - started >= std::chrono::duration<double>(options.duration_s)) {
      break;
    }
    if (now - flushed >= std::chrono::seconds(1)) {
      flushed = now;
      if (absl::Status s = (*recording)->flush(); !s.ok()) return failWith(s);
    }
  }
  const absl::Status stopped = (*recording)->stop();
  const recorder::RecorderStats stats = (*recording)->stats();
  google::protobuf::Struct line;
  auto& fields = *line.mutable_fields();
  fields["file"].set_string_value(recorder_options.path);
  fields["bytes"].set_number_value(static_cast<double>(stats.bytes));
  fields["dropped"].set_number_value(static_cast<double>(stats.dropped));
  fields["drained"].set_bool_value(stats.drained);
  fields["messages"] = counts(stats.messages);
  printJson(line);
  return stopped.ok() ? 0 : failWith(stopped);
}

int runReplay(const CtlOptions& options) {
  if (options.args.size() != 2 || options.channel.empty()) {
    std::fputs("behaviorctl: replay FILE needs --channel (the broker to publish into)\n", stderr);
    return 2;
  }
  recorder::ReplayOptions replay_options;
  replay_options.speed = options.speed;
  replay_options.topic_prefix = options.topic_prefix;
  auto broker = v1::DataChannel::NewStub(server_kit::makeChannel(options.channel));
  const auto stats = recorder::replay(options.args[1], broker.get(), replay_options);
  if (!stats.ok()) return failWith(stats.status());
  google::protobuf::Struct line;
  auto& fields = *line.mutable_fields();
  fields["file"].set_string_value(options.args[1]);
  fields["published"].set_number_value(static_cast<double>(stats->published));
  fields["skipped"].set_number_value(static_cast<double>(stats->skipped));
  fields["complete"].set_bool_value(stats->complete);
  fields["topics"] = counts(stats->topics);
  printJson(line);
  return 0;
}

}  // namespace behaviorlib::behaviorctl
