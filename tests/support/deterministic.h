#pragma once

// The deterministic mode's arguments for tests that fly (decision 18): the
// simulator steps itself in quanta granted to the behavior systems, so a
// loaded machine slows a test's simulated time instead of starving its
// controllers. Time starts once `followers` systems joined; a system started
// later joins when it comes up (idle until activated, so not waited for).
//
//   support::ServerProcess simulator(kSimulatorPath,
//       support::deterministicSimulatorArgs({"--channel", broker.address()}, 1));
//   support::ServerProcess system(kBasicPath,
//       support::followTimeArgs({"--channel", broker.address(), "--clock", "sim"},
//                               simulator.address()));

#include <string>
#include <vector>

namespace support {

/// `args` plus --time-scale max and --min-followers `followers`.
inline std::vector<std::string> deterministicSimulatorArgs(std::vector<std::string> args,
                                                           int followers) {
  args.insert(args.end(), {"--time-scale", "max", "--min-followers", std::to_string(followers)});
  return args;
}

/// `args` (which must choose --clock sim) plus --follow-time `simulator`.
inline std::vector<std::string> followTimeArgs(std::vector<std::string> args,
                                               const std::string& simulator) {
  args.insert(args.end(), {"--follow-time", simulator});
  return args;
}

}  // namespace support
