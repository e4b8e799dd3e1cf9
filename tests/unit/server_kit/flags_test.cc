// Our programs' flags: absl flags, written with hyphens or underscores.

#include "behaviorlib/server_kit/flags.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <string>
#include <vector>

#include "absl/flags/flag.h"

ABSL_FLAG(std::string, robot_id, "drone1", "robot");
ABSL_FLAG(int, workers, 4, "threads");
ABSL_FLAG(bool, shared_memory, true, "rings");

namespace behaviorlib::server_kit {
namespace {

using ::testing::ElementsAre;

// Parses `args` (after the program name) as a program's command line.
void parse(std::vector<std::string> args) {
  args.insert(args.begin(), "program");
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  parseFlags(static_cast<int>(args.size()), argv.data(), "a test program");
}

std::vector<std::string> names(std::vector<std::string> args) {
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  return abslFlagNames(static_cast<int>(argv.size()), argv.data());
}

TEST(FlagNamesTest, HyphensInNamesBecomeUnderscoresAndValuesStay) {
  EXPECT_THAT(
      names({"p", "--robot-id=drone-2", "--metrics-listen", "a-b:1", "-x", "--", "--a-b"}),
      ElementsAre("p", "--robot_id=drone-2", "--metrics_listen", "a-b:1", "-x", "--", "--a-b"));
}

TEST(ParseFlagsTest, HyphenatedAndUnderscoredNamesSetTypedValues) {
  parse({"--robot-id", "drone7", "--workers=8", "--noshared_memory"});
  EXPECT_EQ(absl::GetFlag(FLAGS_robot_id), "drone7");
  EXPECT_EQ(absl::GetFlag(FLAGS_workers), 8);
  EXPECT_FALSE(absl::GetFlag(FLAGS_shared_memory));
  parse({"--robot_id=drone8", "--shared-memory=true"});
  EXPECT_EQ(absl::GetFlag(FLAGS_robot_id), "drone8");
  EXPECT_TRUE(absl::GetFlag(FLAGS_shared_memory));
}

TEST(ParseCommandLineTest, ArgumentsAmongTheFlagsComeBackInOrder) {
  std::vector<std::string> args = {"program", "activate", "--workers=3", "WAIT",
                                   "{\"duration_s\": 2}"};
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  EXPECT_THAT(parseCommandLine(static_cast<int>(args.size()), argv.data(), "a test program"),
              ElementsAre("activate", "WAIT", "{\"duration_s\": 2}"));
  EXPECT_EQ(absl::GetFlag(FLAGS_workers), 3);
}

TEST(ParseFlagsDeathTest, AnIntegerFlagRefusesAFraction) {
  EXPECT_EXIT(parse({"--workers", "4.5"}), ::testing::ExitedWithCode(1),
              "Illegal value '4.5' specified for flag 'workers'");
}

TEST(ParseFlagsDeathTest, AnUnknownFlagIsRefused) {
  EXPECT_EXIT(parse({"--robot-idd", "x"}), ::testing::ExitedWithCode(1),
              "Unknown command line flag 'robot_idd'");
}

// What was asked for is printed (to stdout, sent to stderr here for the
// death test to read), and that is a success: absl itself ends with 1 after
// --help, which reads as a failure to a script.
TEST(ParseFlagsDeathTest, HelpListsTheProgramsFlagsAndExitsWithZero) {
  EXPECT_EXIT(
      {
        (void)::dup2(STDERR_FILENO, STDOUT_FILENO);
        parse({"--help"});
      },
      ::testing::ExitedWithCode(0), "--robot_id \\(robot\\); default: \"drone1\"");
}

TEST(ParseFlagsDeathTest, HelpfullAndVersionExitWithZero) {
  EXPECT_EXIT(parse({"--helpfull"}), ::testing::ExitedWithCode(0), "");
  EXPECT_EXIT(parse({"--version"}), ::testing::ExitedWithCode(0), "");
}

TEST(ParseFlagsDeathTest, APositionalArgumentIsRefusedWithTwo) {
  EXPECT_EXIT(parse({"--workers", "2", "extra"}), ::testing::ExitedWithCode(2),
              "unexpected argument 'extra'");
}

}  // namespace
}  // namespace behaviorlib::server_kit
