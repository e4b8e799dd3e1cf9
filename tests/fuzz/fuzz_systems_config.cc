// Fuzzes the coordinator's --systems file (coordinator/registry/
// systems_config.h): parseSystemsConfig on the raw bytes, and isHostPort on
// them as an address.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <set>
#include <string>

#include "coordinator/registry/systems_config.h"
#include "fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  (void)behaviorlib::coordinator::isHostPort(text);
  const auto systems =
      behaviorlib::coordinator::parseSystemsConfig(text, behaviorlib::fuzz::kFileName);
  if (!systems.ok()) {
    behaviorlib::fuzz::checkParseError(systems.status(), "parseSystemsConfig");
    return 0;
  }
  // What it promises of an accepted file.
  std::set<std::string> addresses;
  for (const auto& system : *systems) {
    if (system.robot_id.empty() || !behaviorlib::coordinator::isHostPort(system.address) ||
        !addresses.insert(system.address).second || system.line < 1) {
      std::fprintf(stderr, "parseSystemsConfig accepted a bad entry at line %d\n", system.line);
      std::abort();
    }
  }
  return 0;
}
