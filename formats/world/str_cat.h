#pragma once

// strCat(): message formatting for this directory. (Debian's Abseil is built
// with its own absl::string_view, so absl::StrCat does not take
// std::string_view.) Internal; not part of the API.

#include <sstream>
#include <string>

namespace behaviorlib::world::internal {

/// Streams every argument into one string; doubles print with up to 6
/// significant digits ("0.5", "4.3").
template <typename... Args>
std::string strCat(const Args&... args) {
  std::ostringstream out;
  (out << ... << args);
  return out.str();
}

}  // namespace behaviorlib::world::internal
