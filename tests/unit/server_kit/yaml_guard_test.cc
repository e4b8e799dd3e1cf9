// loadYaml: YAML from outside within limits on bytes, nodes (aliases
// expanded), aliases and depth; guardYamlParse: no exception escapes.

#include "behaviorlib/server_kit/yaml_guard.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>

namespace behaviorlib::server_kit {
namespace {

using ::testing::HasSubstr;

// `levels` levels of ten aliases to the level below: 10^levels leaves, in
// about 50 bytes a level.
std::string aliasBomb(int levels) {
  std::string text = "l0: &l0 [x, x, x, x, x, x, x, x, x, x]\n";
  for (int i = 1; i <= levels; ++i) {
    const std::string below = "*l" + std::to_string(i - 1);
    text += "l" + std::to_string(i) + ": &l" + std::to_string(i) + " [";
    for (int k = 0; k < 10; ++k) text += (k ? ", " : "") + below;
    text += "]\n";
  }
  return text;
}

TEST(YamlGuardTest, LoadsOrdinaryYamlWithAliases) {
  YAML::Node root;
  const std::string text = "base: &b {x: 1, y: 2}\nuse: [*b, *b]\nname: test\n";
  ASSERT_TRUE(loadYaml(text, "t.yaml", &root).ok());
  EXPECT_EQ(root["name"].as<std::string>(), "test");
  EXPECT_EQ(root["use"][1]["y"].as<int>(), 2);
}

TEST(YamlGuardTest, RefusesAnAliasBombBeforeExpandingIt) {
  const std::string bomb = aliasBomb(9);  // 10^9 leaves
  ASSERT_LT(bomb.size(), 1000u);
  YAML::Node root;
  const absl::Status s = loadYaml(bomb, "bomb.yaml", &root);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("bomb.yaml:"));
  EXPECT_THAT(s.message(), HasSubstr("nodes once its aliases are expanded"));
  EXPECT_TRUE(root.IsNull());
}

TEST(YamlGuardTest, CountsExpandedNodesExactly) {
  // The root mapping, three keys, and the sequences expanded: l0 has 1 + 10
  // nodes, l1 1 + 10 * 11, l2 1 + 10 * 111.
  const std::string text = aliasBomb(2);
  YamlLimits limits;
  limits.max_nodes = 1 + 3 + 11 + 111 + 1111;
  YAML::Node root;
  EXPECT_TRUE(loadYaml(text, "t.yaml", &root, limits).ok());
  limits.max_nodes -= 1;
  EXPECT_FALSE(loadYaml(text, "t.yaml", &root, limits).ok());
}

TEST(YamlGuardTest, RefusesAnAliasInsideTheNodeItRefersTo) {
  // A cycle: walking the tree would never end.
  for (const std::string text :
       {"defaults: &d {x: *d}\n", "a: &a [1, [2, *a]]\n", "&r {k: *r}\n"}) {
    YAML::Node root;
    const absl::Status s = loadYaml(text, "cycle.yaml", &root);
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << text;
    EXPECT_THAT(s.message(), HasSubstr("cycle.yaml:1: refused"));
    EXPECT_THAT(s.message(), HasSubstr("a cycle"));
  }
  // The same anchor used after its node ended is fine.
  YAML::Node root;
  EXPECT_TRUE(loadYaml("a: &a {x: 1}\nb: {y: *a}\n", "t.yaml", &root).ok());
}

TEST(YamlGuardTest, RefusesTooManyAliases) {
  std::string text = "a: &a 1\nb: [";
  for (int i = 0; i < 20; ++i) text += (i ? ", " : "") + std::string("*a");
  text += "]\n";
  YamlLimits limits;
  limits.max_aliases = 19;
  YAML::Node root;
  const absl::Status s = loadYaml(text, "t.yaml", &root, limits);
  EXPECT_THAT(s.message(), HasSubstr("more than 19 aliases"));
  limits.max_aliases = 20;
  EXPECT_TRUE(loadYaml(text, "t.yaml", &root, limits).ok());
}

TEST(YamlGuardTest, RefusesDeepNestingAlsoThroughAliases) {
  YAML::Node root;
  const std::string deep = std::string(200, '[') + std::string(200, ']');
  const absl::Status s = loadYaml(deep, "deep.yaml", &root);
  EXPECT_THAT(s.message(), HasSubstr("nested deeper than 64 levels"));

  // 40 levels anchored, then used 40 levels down: 80 once expanded.
  const std::string forty_open(40, '['), forty_close(40, ']');
  const std::string text =
      "a: &a " + forty_open + "1" + forty_close + "\nb: " + forty_open + "*a" + forty_close + "\n";
  EXPECT_THAT(loadYaml(text, "t.yaml", &root).message(), HasSubstr("nested deeper"));
}

TEST(YamlGuardTest, RefusesLongTextAndNamesTheLineOfSyntaxErrors) {
  YamlLimits limits;
  limits.max_bytes = 10;
  YAML::Node root;
  EXPECT_THAT(loadYaml("a: 12345678901", "t.yaml", &root, limits).message(),
              HasSubstr("more than the 10 allowed"));
  const absl::Status s = loadYaml("a: 1\nb: [1, 2\n", "bad.yaml", &root);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("bad.yaml:"));
  EXPECT_THAT(s.message(), HasSubstr("not valid YAML"));
}

TEST(YamlGuardTest, GuardTurnsExceptionsIntoInvalidArgumentWithTheLine) {
  YAML::Node root;
  // A mapping as a key: as<std::string>() throws.
  ASSERT_TRUE(loadYaml("ok: 1\n? {a: 1}\n: 2\n", "keys.yaml", &root).ok());
  const absl::Status s = guardYamlParse("keys.yaml", [&]() {
    for (const auto& entry : root) (void)entry.first.as<std::string>();
    return absl::OkStatus();
  });
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("keys.yaml:2:"));
  const absl::Status other =
      guardYamlParse("x.yaml", []() -> absl::Status { throw std::runtime_error("boom"); });
  EXPECT_EQ(other.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(other.message(), HasSubstr("x.yaml: boom"));
}

}  // namespace
}  // namespace behaviorlib::server_kit
