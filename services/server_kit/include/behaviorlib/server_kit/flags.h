#pragma once

// A small command-line flag parser for our server binaries:
//
//   FlagSet flags("behavior system");
//   std::string robot_id = "drone1";
//   flags.add("robot-id", &robot_id, "robot this process serves");
//   if (!flags.parse(argc, argv)) return 2;   // prints the error and usage
//
// Accepts `--name value` and `--name=value`; `--help` prints the usage.

#include <functional>
#include <string>
#include <vector>

namespace behaviorlib::server {

class FlagSet {
 public:
  explicit FlagSet(std::string program_description);
  void add(std::string name, std::string* value, std::string help);
  void add(std::string name, double* value, std::string help);
  /// An integer flag: "4" is accepted, "4.5" and "four" are refused.
  void add(std::string name, int* value, std::string help);
  void add(std::string name, bool* value, std::string help);

  /// False after printing an actionable message (unknown flag, missing or
  /// malformed value) or the usage for --help; `exit_code` tells main what
  /// to return (0 for --help, 2 otherwise).
  bool parse(int argc, char** argv, int* exit_code = nullptr);
  std::string usage(const std::string& program) const;

 private:
  struct Flag {
    std::string name;
    std::string help;
    std::string default_text;
    std::function<bool(const std::string&)> set;
    bool is_bool = false;
  };
  std::string description_;
  std::vector<Flag> flags_;
};

}  // namespace behaviorlib::server
