#include "behaviorlib/server_kit/pagination.h"

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"

namespace behaviorlib::server_kit {
namespace {
constexpr char kPrefix[] = "k1.";
}  // namespace

std::string encodePageToken(const std::string& last_key) {
  return kPrefix + absl::WebSafeBase64Escape(last_key);
}

std::optional<std::string> decodePageToken(const std::string& token) {
  if (!absl::StartsWith(token, kPrefix) || token.size() > 4096) return std::nullopt;
  std::string key;
  if (!absl::WebSafeBase64Unescape(token.substr(sizeof(kPrefix) - 1), &key)) return std::nullopt;
  return key;
}

}  // namespace behaviorlib::server_kit
