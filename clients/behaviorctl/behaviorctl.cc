// behaviorctl: a command-line client of a behavior-system process (the generic
// behaviorlib.v1.BehaviorSystem service) or of the coordinator
// (behaviorlib.v1.Coordinator), which routes by robot and behavior.
//
//   behaviorctl --target 127.0.0.1:50061 list
//   behaviorctl --target 127.0.0.1:50061 activate WAIT '{"duration_s": 2}'
//   behaviorctl --target 127.0.0.1:50061 watch [--since-seq N] [--until-finished WAIT]
//   behaviorctl --target 127.0.0.1:50061 deactivate WAIT [activation_id]
//   behaviorctl --target 127.0.0.1:50061 status WAIT
//
//   behaviorctl --coordinator 127.0.0.1:50060 systems
//   behaviorctl --coordinator 127.0.0.1:50060 list [--robot drone1]
//   behaviorctl --coordinator 127.0.0.1:50060 --robot drone1 activate WAIT '{"duration_s": 2}'
//   behaviorctl --coordinator 127.0.0.1:50060 watch [--robot drone1] [--behavior WAIT]
//   behaviorctl --coordinator 127.0.0.1:50060 --robot drone1 activate FOLLOW_PATH '{...}' --dry-run
//   behaviorctl --coordinator 127.0.0.1:50060 mission run deploy/missions/demo.yaml
//   behaviorctl --coordinator 127.0.0.1:50060 mission status|abort|pause|resume MISSION_ID
//   behaviorctl --coordinator 127.0.0.1:50060 --robot drone1 emergency-land
//   behaviorctl --coordinator 127.0.0.1:50060 --robot drone1 kill --confirm
//   behaviorctl --target 127.0.0.1:50061 health        (exit 0 when SERVING)
//   behaviorctl --coordinator 127.0.0.1:50060 --channel 127.0.0.1:50051 record flight.mcap
//   behaviorctl --channel 127.0.0.1:50051 replay flight.mcap [--speed 2]
//
//   behaviorctl --coordinator 127.0.0.1:50060 systems -o wide     (-o json, -o yaml)
//
// The listing commands print aligned tables; -o json gives the reply as one
// JSON object a line, so it can be piped into other tools.

#include <string>

#include "absl/flags/flag.h"
#include "behaviorlib/server_kit/flags.h"
#include "clients/behaviorctl/behaviorctl_commands.h"

ABSL_FLAG(std::string, target, "", "a behavior system's address host:port");
ABSL_FLAG(std::string, coordinator, "", "the coordinator's address host:port");
ABSL_FLAG(std::string, robot, "",
          "the robot (through the coordinator: required by activate, deactivate, status, "
          "situation, emergency-land, kill; a filter for list, systems, watch)");
ABSL_FLAG(std::string, behavior, "", "watch through the coordinator: only this behavior");
ABSL_FLAG(std::string, request_id, "", "activate: idempotency key");
ABSL_FLAG(uint64_t, since_seq, 0, "watch: resume after this event sequence number");
ABSL_FLAG(std::string, incarnation, "", "watch: the incarnation since_seq belongs to");
ABSL_FLAG(std::string, until_finished, "", "watch: stop after this behavior's finished event");
ABSL_FLAG(double, timeout_s, 0, "watch: give up after this many seconds; health: deadline (3)");
ABSL_FLAG(bool, dry_run, false, "activate through the coordinator: show the catalog's plan only");
ABSL_FLAG(bool, skip_plan, false, "activate through the coordinator: the behavior alone");
ABSL_FLAG(bool, detach, false, "mission run: start it and return");
ABSL_FLAG(bool, confirm, false, "kill: required");
ABSL_FLAG(std::string, mission_id, "", "mission run: the mission's id");
ABSL_FLAG(std::string, channel, "", "record, replay: the data channel's (broker's) address");
ABSL_FLAG(std::string, topics, "",
          "record: vehicle topics under robots/{id}/, comma-separated, each NAME (every "
          "sample) or NAME@HZ (at most HZ samples a second of wall time); default: poses and "
          "twist @30, flight state, marker detections, the map's occupied cells");
ABSL_FLAG(double, duration_s, 0, "record: stop after this many seconds (0: at SIGINT or SIGTERM)");
ABSL_FLAG(double, speed, 1, "replay: 1 as recorded, 2 twice as fast, 0 as fast as possible");
ABSL_FLAG(std::string, topic_prefix, "", "replay: only the recording's topics with this prefix");
ABSL_FLAG(std::string, output, "",
          "table (the listing commands' default), wide (more columns: the parameter schemas, "
          "addresses, messages), json (every other command's default) or yaml");
ABSL_FLAG(std::string, o, "", "short for --output");

int main(int argc, char** argv) {
  behaviorlib::behaviorctl::CtlOptions options;
  std::vector<std::string> args = behaviorlib::server_kit::parseCommandLine(
      argc, argv,
      "a client of behavior systems and of the coordinator\n\n"
      "usage: behaviorctl --target HOST:PORT COMMAND ...        (one behavior system)\n"
      "       behaviorctl --coordinator HOST:PORT COMMAND ...   (the fleet, by robot)\n"
      "commands:\n"
      "  list                                 behaviors (-o wide: their parameter schemas)\n"
      "  activate BEHAVIOR [JSON] [--request-id ID]\n"
      "  deactivate BEHAVIOR [ACTIVATION_ID]\n"
      "  pause BEHAVIOR [ACTIVATION_ID] | resume BEHAVIOR [ACTIVATION_ID]\n"
      "  modify BEHAVIOR JSON                 changes the given parameters\n"
      "  status BEHAVIOR                      CheckActivation (--target); the behavior's\n"
      "                                       description and state (--coordinator)\n"
      "  activation BEHAVIOR                  (--coordinator only) CheckActivation\n"
      "  situation BEHAVIOR                   CheckSituation\n"
      "  watch [--since-seq N] [--incarnation ID] [--until-finished BEHAVIOR] [--timeout-s S]\n"
      "  systems                              (--coordinator only) registered systems\n"
      "  belief list [PREFIX] | get KEY | set KEY JSON | delete KEY   (--coordinator only)\n"
      "  mission run FILE [--mission-id ID] [--detach]   start (the file is sent as text) and\n"
      "                                       follow it; exit 0 when it SUCCEEDED\n"
      "  mission check FILE [--robot ID]      every problem with file:line, and each step's\n"
      "                                       plan; exit 1 when it has problems\n"
      "  mission status ID | list | watch ID | pause ID | resume ID | abort ID [REASON]\n"
      "  emergency-land [REASON] | kill --confirm [REASON]   (--coordinator, --robot)\n"
      "  health                               gRPC health check; exit 0 when SERVING\n"
      "  record FILE [--topics a,b] [--duration-s S]   (--coordinator, --channel) the flight\n"
      "                                       recorder: events, missions, beliefs and vehicle\n"
      "                                       topics into an MCAP file, until interrupted\n"
      "  replay FILE [--speed X] [--topic-prefix P]   (--channel) publishes a recording into a\n"
      "                                       broker\n"
      "activate through the coordinator: --dry-run shows the catalog's plan only,\n"
      "  --skip-plan activates the behavior alone\n"
      "output: list, systems, status, mission list and belief list print a table; -o wide\n"
      "  adds columns, -o json and -o yaml print the reply (every other command prints JSON)\n"
      "with --coordinator: --robot ID names the robot (required by activate, deactivate,\n"
      "  pause, resume, modify, status, activation, situation; a filter for list, systems,\n"
      "  watch); --behavior NAME filters watch\n");
  options.target = absl::GetFlag(FLAGS_target);
  options.coordinator = absl::GetFlag(FLAGS_coordinator);
  options.robot = absl::GetFlag(FLAGS_robot);
  options.behavior_filter = absl::GetFlag(FLAGS_behavior);
  options.request_id = absl::GetFlag(FLAGS_request_id);
  options.since_seq = absl::GetFlag(FLAGS_since_seq);
  options.incarnation = absl::GetFlag(FLAGS_incarnation);
  options.until_finished = absl::GetFlag(FLAGS_until_finished);
  options.timeout_s = absl::GetFlag(FLAGS_timeout_s);
  options.dry_run = absl::GetFlag(FLAGS_dry_run);
  options.skip_plan = absl::GetFlag(FLAGS_skip_plan);
  options.detach = absl::GetFlag(FLAGS_detach);
  options.confirm = absl::GetFlag(FLAGS_confirm);
  options.mission_id = absl::GetFlag(FLAGS_mission_id);
  options.channel = absl::GetFlag(FLAGS_channel);
  options.topics = absl::GetFlag(FLAGS_topics);
  options.duration_s = absl::GetFlag(FLAGS_duration_s);
  options.speed = absl::GetFlag(FLAGS_speed);
  options.output =
      absl::GetFlag(FLAGS_o).empty() ? absl::GetFlag(FLAGS_output) : absl::GetFlag(FLAGS_o);
  options.topic_prefix = absl::GetFlag(FLAGS_topic_prefix);
  options.args = std::move(args);
  return behaviorlib::behaviorctl::runCtl(options);
}
