// Typed configuration (decision 45): a YAML section decoded into messages,
// with file:line:column on every error.

#include "behaviorlib/configuration.h"

#include <google/protobuf/empty.pb.h>
#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <string>

#include "behaviorlib/config/v1/execution.pb.h"
#include "test_parameters.pb.h"

namespace behaviorlib {
namespace {

using config::Source;
using test::SectionConfig;

const Source kSource{"sys.yaml", "behaviors.X"};

absl::Status decodeText(const std::string& text, SectionConfig* out,
                        config::v1::ExecutionConfig* execution) {
  return config::decode(YAML::Load(text), kSource, {execution, out});
}

TEST(ConfigurationTest, DecodesOwnFlattenedAndLibraryKeysWithDefaults) {
  SectionConfig c;
  config::v1::ExecutionConfig e;
  ASSERT_TRUE(decodeText("frequency_hz: 25\n"
                         "timeout_s: 2\n"
                         "preempt: true\n"
                         "mount_m: [0.1, 0, -0.2]\n"
                         "window: 20\n"
                         "name: \"7\"\n"
                         "home: {x_m: 3}\n",
                         &c, &e)
                  .ok());
  EXPECT_DOUBLE_EQ(e.frequency_hz(), 25);
  EXPECT_FALSE(e.has_watchdog_timeout_s());  // the behavior's own default stays
  EXPECT_DOUBLE_EQ(c.shared().timeout_s(), 2);
  EXPECT_TRUE(c.shared().preempt());
  EXPECT_DOUBLE_EQ(c.tolerance_m(), 0.1);  // default_json
  ASSERT_EQ(c.mount_m_size(), 3);
  EXPECT_DOUBLE_EQ(c.mount_m(2), -0.2);
  EXPECT_EQ(c.window(), 20);
  EXPECT_EQ(c.name(), "7");  // quoted: text, not a number
  EXPECT_DOUBLE_EQ(c.home().x_m(), 3);
}

TEST(ConfigurationTest, AnEmptyOrMissingSectionGivesTheDefaults) {
  for (const char* text : {"", "~"}) {
    SectionConfig c;
    config::v1::ExecutionConfig e;
    ASSERT_TRUE(decodeText(text, &c, &e).ok()) << text;
    EXPECT_DOUBLE_EQ(c.shared().timeout_s(), 0.5);
    EXPECT_FALSE(c.shared().preempt());
  }
  SectionConfig c;
  ASSERT_TRUE(config::decode(YAML::Node(), kSource, {&c}).ok());
  EXPECT_DOUBLE_EQ(c.tolerance_m(), 0.1);
}

TEST(ConfigurationTest, AnUnknownKeyNamesItsLineAndTheKnownKeys) {
  SectionConfig c;
  config::v1::ExecutionConfig e;
  const absl::Status s = decodeText("timeout_s: 1\ntolerence_m: 0.2\n", &c, &e);
  ASSERT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  const std::string m(s.message());
  EXPECT_EQ(m.rfind("sys.yaml:2:1: behaviors.X: unknown key 'tolerence_m'", 0), 0u) << m;
  // The known keys: the library's, the flattened ones and the section's.
  EXPECT_NE(m.find("frequency_hz"), std::string::npos) << m;
  EXPECT_NE(m.find("timeout_s"), std::string::npos) << m;
  EXPECT_NE(m.find("tolerance_m"), std::string::npos) << m;
  // The flattened field's own name is not a key.
  EXPECT_EQ(m.find("shared"), std::string::npos) << m;
  EXPECT_FALSE(decodeText("shared: {timeout_s: 1}\n", &c, &e).ok());
}

TEST(ConfigurationTest, OutOfRangeAndWrongTypesNameTheValuesLine) {
  SectionConfig c;
  config::v1::ExecutionConfig e;
  absl::Status s = decodeText("name: a\ntimeout_s: 120\n", &c, &e);
  EXPECT_EQ(std::string(s.message()),
            "sys.yaml:2:12: behaviors.X: key 'shared.timeout_s' = 120 is out of range "
            "[0.001, 60]");
  s = decodeText("tolerance_m: far\n", &c, &e);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:1:14: behaviors.X: key 'tolerance_m'", 0), 0u)
      << s.message();
  s = decodeText("mount_m: [0, 0.5,\n  3]\n", &c, &e);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:2:3: ", 0), 0u) << s.message();
  s = decodeText("window: 2.5\n", &c, &e);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:1:9: ", 0), 0u) << s.message();
  s = decodeText("frequency_hz: 0\n", &c, &e);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:1:15: behaviors.X: key 'frequency_hz'", 0), 0u)
      << s.message();
  s = decodeText("home: {x_m: 300}\n", &c, &e);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:1:13: behaviors.X: key 'home.x_m'", 0), 0u)
      << s.message();
  s = decodeText("preempt: maybe\n", &c, &e);
  EXPECT_EQ(std::string(s.message()).rfind("sys.yaml:1:10: ", 0), 0u) << s.message();
  s = decodeText("tolerance_m:\n", &c, &e);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << "a key without a value";
}

TEST(ConfigurationTest, ASectionThatIsNotAMapIsRefused) {
  SectionConfig c;
  const absl::Status s = config::decode(YAML::Load("[1, 2]"), kSource, {&c});
  EXPECT_EQ(std::string(s.message()), "sys.yaml:1:1: behaviors.X: must be a map of keys");
}

TEST(ConfigurationTest, SkippedKeysArePassedOver) {
  google::protobuf::Empty none;
  const Source top{.file = "sys.yaml", .section = "", .skip = {"behaviors"}};
  EXPECT_TRUE(config::decode(YAML::Load("behaviors: {X: {a: 1}}\n"), top, {&none}).ok());
  const absl::Status s = config::decode(YAML::Load("behaviors: {}\nmaping: {}\n"), top, {&none});
  EXPECT_EQ(std::string(s.message()), "sys.yaml:2:1: unknown key 'maping'; known keys: (none)");
}

TEST(ConfigurationTest, DeepValuesAreBounded) {
  std::string deep = "home: ";
  for (int i = 0; i < 40; ++i) deep += "[";
  for (int i = 0; i < 40; ++i) deep += "]";
  SectionConfig c;
  const absl::Status s = config::decode(YAML::Load(deep), kSource, {&c});
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(s.message()).find("nested deeper than"), std::string::npos) << s.message();
}

TEST(ConfigurationTest, DocumentListsEveryKeyWithItsRule) {
  const std::string doc = config::document(
      {config::v1::ExecutionConfig::descriptor(), SectionConfig::descriptor()}, "  ");
  EXPECT_NE(doc.find("  frequency_hz (number, Hz) in [0.001, 10000]"), std::string::npos) << doc;
  EXPECT_NE(doc.find("  timeout_s (number, s) in [0.001, 60], default 0.5"), std::string::npos)
      << doc;
  EXPECT_NE(doc.find("  tolerance_m (number, m) in [0, 10], default 0.1"), std::string::npos)
      << doc;
  EXPECT_EQ(doc.find("shared"), std::string::npos) << doc;
}

}  // namespace
}  // namespace behaviorlib
