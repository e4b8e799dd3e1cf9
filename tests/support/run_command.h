#pragma once

// Runs a command line with a shell, for the tests that drive behaviorctl and
// the tools as a user would.
//
//   std::string output;
//   EXPECT_EQ(support::run(ctl + " belief list", &output), 0) << output;

#include <sys/wait.h>

#include <cstdio>
#include <string>

namespace support {

/// Runs `command` with a shell; its exit code (-1 when it did not exit
/// normally), its stdout and stderr appended to `output`.
inline int run(const std::string& command, std::string* output) {
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (!pipe) return -1;
  char buffer[4096];
  size_t n;
  while ((n = fread(buffer, 1, sizeof(buffer), pipe)) > 0) output->append(buffer, n);
  const int status = pclose(pipe);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

}  // namespace support
