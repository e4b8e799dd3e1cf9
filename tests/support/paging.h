#pragma once

// Pages through a List RPC (AIP-158: page_size, page_token,
// next_page_token) as a client does, and gives the keys of the items page by
// page, so that a test sees each page's size and every item once.
//
//   v1::ListBeliefsRequest request;
//   request.set_page_size(2);
//   std::vector<std::vector<std::string>> pages;
//   grpc::Status s = support::pageKeys(
//       *stub, &v1::Coordinator::Stub::ListBeliefs, request,
//       [](const v1::ListBeliefsResponse& r) -> const auto& { return r.beliefs(); },
//       [](const v1::Belief& b) { return b.key(); }, &pages);

#include <grpcpp/client_context.h>
#include <grpcpp/support/status.h>

#include <chrono>
#include <cstddef>
#include <string>
#include <vector>

namespace support {

/// Sends `request` (empty page_token: from the first page), then again with
/// each next_page_token until one comes back empty, and puts in `pages` the
/// `key` of every item of `items(page)`, one vector a page. Stops at the
/// first error (returned) or after `max_pages` pages (the last of which then
/// had a next_page_token). Each call has a deadline of 10 s.
template <typename Stub, typename Request, typename Response, typename Items, typename Key>
grpc::Status pageKeys(Stub& stub,
                      grpc::Status (Stub::*list)(grpc::ClientContext*, const Request&, Response*),
                      Request request, const Items& items, const Key& key,
                      std::vector<std::vector<std::string>>* pages, size_t max_pages = 100) {
  pages->clear();
  while (pages->size() < max_pages) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    Response page;
    const grpc::Status status = (stub.*list)(&context, request, &page);
    if (!status.ok()) return status;
    std::vector<std::string>& keys = pages->emplace_back();
    for (const auto& item : items(page)) keys.push_back(key(item));
    if (page.next_page_token().empty()) break;
    request.set_page_token(page.next_page_token());
  }
  return grpc::Status::OK;
}

}  // namespace support
