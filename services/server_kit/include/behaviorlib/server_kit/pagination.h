#pragma once

// Pagination of List* RPCs, as Google's AIP-158 describes: a request's
// page_size (0: the server's default; more than the maximum: the maximum;
// negative: INVALID_ARGUMENT) and page_token (empty: the first page), and a
// response's next_page_token (empty: the last page).
//
// Tokens are keyset tokens: the key of the last item sent, so a page does
// not shift when items before it come or go. The items of a response are
// put in key order.
//
//   grpc::Status s = paginate(response->mutable_beliefs(),
//                             [](const v1::Belief& b) { return b.key(); }, *request,
//                             response->mutable_next_page_token());

#include <google/protobuf/repeated_ptr_field.h>
#include <grpcpp/support/status.h>

#include <algorithm>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::server_kit {

struct PageLimits {
  int32_t default_size = 500;
  int32_t max_size = 1000;
};

/// The key a page_token carries; nullopt for a token this server did not make.
std::optional<std::string> decodePageToken(const std::string& token);
std::string encodePageToken(const std::string& last_key);

template <typename T, typename Request>
grpc::Status paginate(google::protobuf::RepeatedPtrField<T>* items,
                      const std::function<std::string(const T&)>& key, const Request& request,
                      std::string* next_page_token, PageLimits limits = {}) {
  if (request.page_size() < 0) {
    const std::string message = "page_size must not be negative";
    return errors::toGrpc(errors::withFieldViolation(
        errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST), "page_size",
        message));
  }
  std::optional<std::string> after;
  if (!request.page_token().empty()) {
    after = decodePageToken(request.page_token());
    if (!after) {
      return errors::grpcError(grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_PAGE_TOKEN,
                               "page_token is not a token this server gave (next_page_token)");
    }
  }
  const size_t size = static_cast<size_t>(request.page_size() == 0
                                              ? limits.default_size
                                              : std::min(request.page_size(), limits.max_size));
  std::vector<std::pair<std::string, T>> keyed;
  keyed.reserve(static_cast<size_t>(items->size()));
  for (T& item : *items) {
    std::string k = key(item);
    if (after && k <= *after) continue;
    keyed.emplace_back(std::move(k), std::move(item));
  }
  std::stable_sort(keyed.begin(), keyed.end(),
                   [](const auto& a, const auto& b) { return a.first < b.first; });
  items->Clear();
  next_page_token->clear();
  for (size_t i = 0; i < keyed.size() && i < size; ++i) *items->Add() = std::move(keyed[i].second);
  if (keyed.size() > size) *next_page_token = encodePageToken(keyed[size - 1].first);
  return grpc::Status::OK;
}

}  // namespace behaviorlib::server_kit
