#include "behaviorlib/server_kit/flags.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <mutex>

#include "absl/flags/internal/parse.h"
#include "absl/flags/internal/usage.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/flags/usage_config.h"
#include "absl/strings/match.h"

namespace behaviorlib::server_kit {

std::vector<std::string> abslFlagNames(int argc, char** argv) {
  std::vector<std::string> out(argv, argv + argc);
  for (size_t i = 1; i < out.size(); ++i) {
    std::string& arg = out[i];
    if (arg == "--") break;  // the end of the flags
    if (arg.size() <= 2 || arg.rfind("--", 0) != 0) continue;
    const size_t end = std::min(arg.find('='), arg.size());
    std::replace(arg.begin() + 2, arg.begin() + static_cast<std::ptrdiff_t>(end), '-', '_');
  }
  return out;
}

std::vector<std::string> parseCommandLine(int argc, char** argv, const std::string& usage) {
  // absl takes the usage once per process (a test may parse twice).
  static std::once_flag once;
  std::call_once(once, [&] {
    absl::SetProgramUsageMessage(usage +
                                 "\n\nFlag names are written with hyphens or underscores alike "
                                 "(--robot-id or --robot_id).");
    // --help lists the program's flags (absl's own, such as --flagfile, are
    // left to --helpfull), wherever they are defined.
    absl::FlagsUsageConfig config;
    config.contains_help_flags = [](absl::string_view file) {
      return !absl::StrContains(file, "absl/");
    };
    config.contains_helpshort_flags = config.contains_help_flags;
    config.normalize_filename = [](absl::string_view file) {
      const size_t slash = file.rfind('/');
      return std::string(slash == absl::string_view::npos ? file : file.substr(slash + 1));
    };
    absl::SetFlagsUsageConfig(config);
  });
  std::vector<std::string> names = abslFlagNames(argc, argv);
  std::vector<char*> args;
  args.reserve(names.size() + 1);
  for (std::string& a : names) args.push_back(a.data());
  args.push_back(nullptr);
  // absl::ParseCommandLine, except that the usage flags are handled here:
  // absl (as packaged) ends with status 1 after printing --help, which reads
  // as a failure to a script. What was asked for and printed is a success.
  namespace internal = absl::flags_internal;
  const std::vector<char*> rest = internal::ParseCommandLineImpl(
      static_cast<int>(names.size()), args.data(), internal::ArgvListAction::kRemoveParsedArgs,
      internal::UsageFlagsAction::kIgnoreUsage, internal::OnUndefinedFlag::kAbortIfUndefined);
  if (internal::HandleUsageFlags(std::cout, absl::ProgramUsageMessage()) != -1) {
    std::cout.flush();
    std::exit(0);
  }
  return std::vector<std::string>(rest.begin() + 1, rest.end());
}

void parseFlags(int argc, char** argv, const std::string& usage) {
  const std::vector<std::string> rest = parseCommandLine(argc, argv, usage);
  if (!rest.empty()) {
    std::fprintf(stderr, "%s: unexpected argument '%s'\nRun with --help for the list of flags.\n",
                 argc > 0 ? argv[0] : "program", rest[0].c_str());
    std::exit(2);
  }
}

}  // namespace behaviorlib::server_kit
