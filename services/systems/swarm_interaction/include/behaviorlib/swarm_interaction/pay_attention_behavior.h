#pragma once

// PAY_ATTENTION_TO_ROBOT_MESSAGES (recurrent): keeps what other robots tell
// this one in the coordinator's belief memory.
//
//   robots/swarm/messages   SwarmMessage, queued  -> {id}/swarm/messages/{n},
//                                                    {id}/swarm/message_count
//   robots/swarm/positions  SwarmPosition, queued -> {id}/swarm/{other}/position
//   malformed samples (counted, skipped)          -> {id}/swarm/malformed_count
//
// Only samples of other robots addressed to this robot (or to all) count.
// Samples arrive on the behavior's worker (onWorker) and are queued there;
// the writes to belief memory run as background jobs (inBackground), one
// batch at a time, so a slow coordinator never blocks the channel or the
// monitoring. Positions are written at most every write_period_s (wall
// time; the latest of each robot wins); messages all, in order. n goes on
// from the message_count found in belief memory at activation.
//
//   checkSituation  a data channel and a coordinator
//   checkProcesses  a subscription disconnected from the broker for
//                   channel_timeout_s, no position of another robot for
//                   max_silence_s (when set), or belief memory failing for
//                   channel_timeout_s -> PROCESS_FAILURE
//
// Config (defaults): channel_timeout_s [2], write_period_s [0.1].

#include <chrono>
#include <deque>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/swarm_interaction.pb.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::swarm {

class PayAttentionToRobotMessagesBehavior final
    : public Behavior<v1::PayAttentionToRobotMessagesParameters,
                      config::v1::PayAttentionToRobotMessagesConfig> {
 public:
  /// `channel` or `beliefs` may be null: the behavior then reports itself
  /// infeasible.
  PayAttentionToRobotMessagesBehavior(channel::ChannelClient* channel,
                                      const server::BeliefClient* beliefs);
  ~PayAttentionToRobotMessagesBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::PayAttentionToRobotMessagesConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  void onExecute() override;

  Situation checkSituation() override;
  Verdict checkProcesses() override;

 private:
  // What one background job writes, and what it did.
  struct Batch {
    std::string prefix, writer;
    std::map<std::string, v1::SwarmPosition> positions;
    std::deque<v1::SwarmMessage> messages;
    uint64_t malformed = 0;
    bool malformed_changed = false;
    uint64_t count = 0;  // messages numbered so far
  };
  struct WriteOutcome {
    bool failing = false;  // the last write failed
    std::string error;     // the first failure of the last run of failures
  };
  struct BatchResult {
    uint64_t count = 0;
    std::deque<v1::SwarmMessage> unwritten;
    uint64_t malformed = 0;
    bool malformed_written = false;
    WriteOutcome outcome;
  };

  void onMessage(const v1::SubscribeResponse& sample);
  void onPosition(const v1::SubscribeResponse& sample);
  void countMalformed(const std::string& why);
  // Starts the next background job when none runs and one is due.
  void startWrites();
  void recordWrites(const WriteOutcome& outcome);
  // The background job: writes a batch to belief memory.
  static BatchResult writeBatch(const server::BeliefClient& beliefs, Batch batch);
  void stop();

  channel::ChannelClient* channel_;
  const server::BeliefClient* beliefs_;
  Duration channel_timeout_ = std::chrono::seconds(2);
  double write_period_s_ = 0.1;

  std::unique_ptr<channel::Subscription> messages_sub_, positions_sub_;

  // Worker thread only (samples and job results arrive there).
  bool recording_ = false;
  std::map<std::string, v1::SwarmPosition> pending_positions_;
  std::deque<v1::SwarmMessage> pending_messages_;
  uint64_t malformed_ = 0, malformed_written_ = 0;
  uint64_t positions_received_ = 0;
  std::string last_malformed_;
  // Belief memory: the first failure of the current run of failures.
  std::optional<std::string> write_error_;
  bool write_failing_ = false;
  std::optional<uint64_t> count_;  // message_count, once read
  bool writing_ = false;           // a background job runs
  std::chrono::steady_clock::time_point next_write_{};
  bool active_ = false;
  TimePoint activated_at_{};
  std::optional<TimePoint> disconnected_since_, failing_since_;
  uint64_t positions_seen_ = 0;
  TimePoint last_position_at_{};
};

}  // namespace behaviorlib::swarm
