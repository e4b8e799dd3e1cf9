#pragma once

// Command-line flags of our programs are absl flags (ABSL_FLAG), read with
// absl::GetFlag into the program's options struct:
//
//   ABSL_FLAG(std::string, robot_id, "drone1", "robot this process serves");
//   ABSL_FLAG(int, workers, 4, "threads for blocking calls");
//
//   int main(int argc, char** argv) {
//     behaviorlib::server_kit::parseFlags(argc, argv, "the coordinator: ...");
//     options.workers = absl::GetFlag(FLAGS_workers);
//
// On the command line a flag's name is written with hyphens (--robot-id, the
// names the launcher, the compose files and the docs use) or, as absl
// spells it, with underscores (--robot_id). Accepts `--name value`,
// `--name=value`, `--flag`/`--noflag` for booleans; an integer flag refuses
// "4.5". --help lists the flags.

#include <string>
#include <vector>

namespace behaviorlib::server_kit {

/// Parses argv into the program's ABSL_FLAGs. Exits like absl does, 1 after
/// printing an unknown flag or a bad value, and 0 after printing what
/// --help, --helpfull or --version asked for. A positional argument is
/// refused with exit code 2 (our programs take none).
void parseFlags(int argc, char** argv, const std::string& usage);

/// As parseFlags, for a program that takes arguments besides its flags (a
/// command and its operands, anywhere among the flags): returns them in
/// order, without the program's name.
std::vector<std::string> parseCommandLine(int argc, char** argv, const std::string& usage);

/// argv with the name (up to '=') of each argument that starts with "--"
/// written with underscores instead of hyphens. A separate value that
/// starts with "--" would be rewritten too; none of our flags takes one.
std::vector<std::string> abslFlagNames(int argc, char** argv);

}  // namespace behaviorlib::server_kit
