// paginate(): AIP-158 pages over a response's repeated field, with keyset
// tokens that do not shift when items before the page go away.

#include "behaviorlib/server_kit/pagination.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::server_kit {
namespace {

v1::ListBeliefsResponse beliefs(const std::vector<std::string>& keys) {
  v1::ListBeliefsResponse response;
  for (const auto& k : keys) response.add_beliefs()->set_key(k);
  return response;
}

std::vector<std::string> keysOf(const v1::ListBeliefsResponse& r) {
  std::vector<std::string> out;
  for (const auto& b : r.beliefs()) out.push_back(b.key());
  return out;
}

grpc::Status page(v1::ListBeliefsResponse* response, int size, const std::string& token) {
  v1::ListBeliefsRequest request;
  request.set_page_size(size);
  request.set_page_token(token);
  return paginate<v1::Belief>(
      response->mutable_beliefs(), [](const v1::Belief& b) { return b.key(); }, request,
      response->mutable_next_page_token(), {.default_size = 3, .max_size = 4});
}

TEST(PaginationTest, PagesInKeyOrderUntilAnEmptyToken) {
  const std::vector<std::string> all = {"e", "a", "d", "b", "c"};
  auto first = beliefs(all);
  ASSERT_TRUE(page(&first, 2, "").ok());
  EXPECT_EQ(keysOf(first), (std::vector<std::string>{"a", "b"}));
  ASSERT_FALSE(first.next_page_token().empty());
  auto second = beliefs(all);
  ASSERT_TRUE(page(&second, 2, first.next_page_token()).ok());
  EXPECT_EQ(keysOf(second), (std::vector<std::string>{"c", "d"}));
  auto last = beliefs(all);
  ASSERT_TRUE(page(&last, 2, second.next_page_token()).ok());
  EXPECT_EQ(keysOf(last), (std::vector<std::string>{"e"}));
  EXPECT_TRUE(last.next_page_token().empty());
}

TEST(PaginationTest, ItemsRemovedBeforeThePageDoNotShiftIt) {
  auto first = beliefs({"a", "b", "c", "d"});
  ASSERT_TRUE(page(&first, 2, "").ok());
  auto after_removal = beliefs({"b", "c", "d"});  // "a" went
  ASSERT_TRUE(page(&after_removal, 2, first.next_page_token()).ok());
  EXPECT_EQ(keysOf(after_removal), (std::vector<std::string>{"c", "d"}));
}

TEST(PaginationTest, DefaultAndMaximumSizesAndBadRequests) {
  auto by_default = beliefs({"a", "b", "c", "d", "e", "f"});
  ASSERT_TRUE(page(&by_default, 0, "").ok());
  EXPECT_EQ(by_default.beliefs_size(), 3);
  auto capped = beliefs({"a", "b", "c", "d", "e", "f"});
  ASSERT_TRUE(page(&capped, 100, "").ok());
  EXPECT_EQ(capped.beliefs_size(), 4);
  auto bad = beliefs({"a"});
  EXPECT_EQ(page(&bad, -1, "").error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(page(&bad, 1, "not-ours").error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(page(&bad, 1, "k1.!!!").error_code(), grpc::StatusCode::INVALID_ARGUMENT);
}

}  // namespace
}  // namespace behaviorlib::server_kit
