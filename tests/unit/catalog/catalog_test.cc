#include "coordinator/catalog/catalog.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <set>
#include <string>
#include <string_view>

#include "behaviorlib/embedded_descriptors.h"
#include "behaviorlib/v1/options.pb.h"
#include "google/protobuf/descriptor.pb.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::HasSubstr;

constexpr const char* kCatalog = R"(capabilities:
  self_localization:
    default: LOCALIZE
resources:
  platform: the lease
behaviors:
  LOCALIZE:
    provides: [self_localization]
  MOVE:
    requires: self_localization
    holds: [platform]
    defaults: {speed_m_s: 1.5, mode: "fast", enabled: true, path: [1, 2]}
)";

TEST(Catalog, ParsesCapabilitiesResourcesAndDefaults) {
  auto catalog = Catalog::parse(kCatalog, "c.yaml");
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  const CatalogBehavior* move = catalog->find("MOVE");
  ASSERT_NE(move, nullptr);
  EXPECT_EQ(move->line, 9);
  EXPECT_EQ(move->requires_, std::vector<std::string>{"self_localization"});
  EXPECT_EQ(move->holds, std::vector<std::string>{"platform"});
  const auto& d = move->defaults.fields();
  EXPECT_DOUBLE_EQ(d.at("speed_m_s").number_value(), 1.5);
  EXPECT_EQ(d.at("mode").string_value(), "fast");
  EXPECT_TRUE(d.at("enabled").bool_value());
  EXPECT_EQ(d.at("path").list_value().values_size(), 2);
  EXPECT_EQ(catalog->capability("self_localization")->default_provider, "LOCALIZE");
  EXPECT_EQ(catalog->find("UNLISTED"), nullptr);
}

struct BadCatalog {
  std::string text;
  int line;
  std::string problem;
};

class CatalogErrors : public ::testing::TestWithParam<BadCatalog> {};

TEST_P(CatalogErrors, NameFileLineAndProblem) {
  auto catalog = Catalog::parse(GetParam().text, "bad.yaml");
  ASSERT_FALSE(catalog.ok());
  EXPECT_EQ(catalog.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(catalog.status().message()),
              HasSubstr("bad.yaml:" + std::to_string(GetParam().line) + ": "));
  EXPECT_THAT(std::string(catalog.status().message()), HasSubstr(GetParam().problem));
}

INSTANTIATE_TEST_SUITE_P(
    Problems, CatalogErrors,
    ::testing::Values(
        BadCatalog{"behaviors:\n  A:\n    provide: [x]\n", 3, "unknown key 'provide'"},
        BadCatalog{"behaviors:\n  A:\n    requires: [nav]\n", 3, "not a declared capability"},
        BadCatalog{"resources: {r: x}\nbehaviors:\n  A:\n    holds: [q]\n", 4,
                   "not a declared resource"},
        BadCatalog{"capabilities:\n  c:\n    default: B\nbehaviors:\n  A: {}\n", 2,
                   "'B' is not a listed behavior"},
        BadCatalog{"capabilities:\n  c:\n    default: A\nbehaviors:\n  A: {}\n", 2,
                   "does not provide it"},
        BadCatalog{"capabilities:\n  a: {default: A}\n  b: {default: B}\nbehaviors:\n"
                   "  A: {provides: [a], requires: [b]}\n  B: {provides: [b], requires: [a]}\n",
                   5, "requirements loop: A -> B -> A"},
        BadCatalog{"behaviors:\n  A: {}\n  A: {}\n", 3, "duplicate key 'A'"},
        BadCatalog{"behaviors: [A, B\n", 2, "not valid YAML"},
        BadCatalog{"capabilities: {}\n", 1, "missing 'behaviors'"}));

v1::BehaviorDescription registered(const std::string& name) {
  v1::BehaviorDescription d;
  d.set_name(name);
  auto* speed = d.add_parameters();
  speed->set_name("speed_m_s");
  speed->set_type("number");
  auto* mode = d.add_parameters();
  mode->set_name("mode");
  mode->set_type("enum");
  auto* enabled = d.add_parameters();
  enabled->set_name("enabled");
  enabled->set_type("boolean");
  auto* path = d.add_parameters();
  path->set_name("path");
  path->set_type("number");
  path->set_repeated(true);
  return d;
}

TEST(Catalog, DefaultsAgreeingWithTheRegistrationAreAccepted) {
  auto catalog = Catalog::parse(kCatalog, "c.yaml");
  ASSERT_TRUE(catalog.ok());
  EXPECT_TRUE(catalog->checkRegistration(registered("MOVE"), "motion_system").ok());
  EXPECT_TRUE(catalog->checkRegistration(registered("NOT_IN_CATALOG"), "motion_system").ok());
}

TEST(Catalog, ADefaultTheRegistrationDoesNotKnowNamesLineAndParameter) {
  auto catalog = Catalog::parse(kCatalog, "c.yaml");
  ASSERT_TRUE(catalog.ok());
  v1::BehaviorDescription d = registered("MOVE");
  d.mutable_parameters()->RemoveLast();  // no "path" any more
  absl::Status s = catalog->checkRegistration(d, "motion_system");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(s.message()),
              HasSubstr("c.yaml:9: behavior 'MOVE': default parameter 'path'"));
  EXPECT_THAT(std::string(s.message()), HasSubstr("registered by motion_system"));
}

TEST(Catalog, ADefaultOfTheWrongTypeIsAnError) {
  auto catalog = Catalog::parse(kCatalog, "c.yaml");
  ASSERT_TRUE(catalog.ok());
  v1::BehaviorDescription d = registered("MOVE");
  d.mutable_parameters(0)->set_type("string");  // speed_m_s default is a number
  absl::Status s = catalog->checkRegistration(d, "motion_system");
  EXPECT_THAT(std::string(s.message()), HasSubstr("'speed_m_s' must be of type string"));
}

// The behaviors the API declares: every typed service carrying the
// (behaviorlib.v1.behavior) option in the embedded descriptor set.
std::set<std::string> declaredBehaviors() {
  google::protobuf::FileDescriptorSet files;
  const std::string_view bytes = embedded::descriptorSet();
  EXPECT_TRUE(files.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())));
  std::set<std::string> names;
  for (const auto& file : files.file()) {
    for (const auto& service : file.service()) {
      if (service.options().HasExtension(v1::behavior)) {
        names.insert(service.options().GetExtension(v1::behavior).name());
      }
    }
  }
  return names;
}

TEST(Catalog, TheShippedCatalogListsExactlyTheDeclaredBehaviors) {
  auto catalog = Catalog::load(BEHAVIORLIB_SHIPPED_CATALOG);
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  std::set<std::string> listed;
  for (const auto& [name, behavior] : catalog->behaviors()) listed.insert(name);
  std::set<std::string> declared = declaredBehaviors();
  // The paper's table has 30; the set itself comes from the protos.
  EXPECT_GE(declared.size(), 30u);
  // And the behaviors written in Python, whose parameters are declared in
  // Python (examples/python_behavior; its test checks this entry).
  declared.insert("CIRCLE_AROUND");
  EXPECT_EQ(listed, declared);
}

TEST(Catalog, AMissingFileIsNamed) {
  auto catalog = Catalog::load("/nonexistent/catalog.yaml");
  EXPECT_EQ(catalog.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(catalog.status().message()), HasSubstr("/nonexistent/catalog.yaml"));
}

// `writes`: the belief keys a behavior may write, as patterns of the step's
// robot and literal string parameters, with a trailing '*'.
TEST(Catalog, WritesArePatternsOfTheRobotAndTheStepsParameters) {
  auto catalog = Catalog::parse(
      "behaviors:\n"
      "  PLAN:\n"
      "    writes: [\"{parameter:belief_key}\", \"{robot}/path\", \"{robot}/plans/*\"]\n",
      "c.yaml");
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  const auto& writes = catalog->find("PLAN")->writes;
  ASSERT_EQ(writes.size(), 3u);
  google::protobuf::Struct given;
  (*given.mutable_fields())["belief_key"].set_string_value("drone2/route");
  EXPECT_EQ(instantiateBeliefPattern(writes[0], "drone2", given), "drone2/route");
  EXPECT_EQ(instantiateBeliefPattern(writes[1], "drone2", given), "drone2/path");
  EXPECT_EQ(instantiateBeliefPattern(writes[2], "drone2", given), "drone2/plans/*");
  EXPECT_EQ(instantiateBeliefPattern(writes[0], "drone2", {}), std::nullopt) << "not given";
  (*given.mutable_fields())["belief_key"].set_string_value("${belief.where}");
  EXPECT_EQ(instantiateBeliefPattern(writes[0], "drone2", given), std::nullopt)
      << "known only when the step starts";
  for (const auto& [pattern, problem] :
       std::vector<std::pair<std::string, std::string>>{{"{robot/path", "without its '}'"},
                                                        {"{name}/x", "neither {robot}"},
                                                        {"{parameter:}", "neither {robot}"},
                                                        {"a*/b", "'*' only at the end"}}) {
    auto bad = Catalog::parse("behaviors:\n  PLAN: {writes: [\"" + pattern + "\"]}\n", "c.yaml");
    ASSERT_FALSE(bad.ok()) << pattern;
    EXPECT_THAT(std::string(bad.status().message()), HasSubstr("c.yaml:2: "));
    EXPECT_THAT(std::string(bad.status().message()), HasSubstr(problem));
  }
}

}  // namespace
}  // namespace behaviorlib::coordinator
