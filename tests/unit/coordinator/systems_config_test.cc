// The --systems file: entries, and errors naming the file and the line.

#include "coordinator/registry/systems_config.h"

#include <gtest/gtest.h>

#include <string>

namespace behaviorlib::coordinator {
namespace {

TEST(SystemsConfigTest, ReadsEntriesWithTheirLines) {
  auto systems = parseSystemsConfig(
      "# fleet\n"
      "systems:\n"
      "  - robot_id: drone1\n"
      "    address: 127.0.0.1:50061\n"
      "  - {robot_id: drone2, address: 'host-b:50062'}\n",
      "fleet.yaml");
  ASSERT_TRUE(systems.ok()) << systems.status();
  ASSERT_EQ(systems->size(), 2u);
  EXPECT_EQ((*systems)[0].robot_id, "drone1");
  EXPECT_EQ((*systems)[0].address, "127.0.0.1:50061");
  EXPECT_EQ((*systems)[0].line, 3);
  EXPECT_EQ((*systems)[1].robot_id, "drone2");
  EXPECT_EQ((*systems)[1].address, "host-b:50062");
  EXPECT_EQ((*systems)[1].line, 5);
}

TEST(SystemsConfigTest, EmptyFileOrListIsNoSystems) {
  auto empty = parseSystemsConfig("", "f.yaml");
  ASSERT_TRUE(empty.ok());
  EXPECT_TRUE(empty->empty());
  auto none = parseSystemsConfig("systems: []\n", "f.yaml");
  ASSERT_TRUE(none.ok());
  EXPECT_TRUE(none->empty());
}

void expectError(const std::string& text, const std::string& where, const std::string& what) {
  auto result = parseSystemsConfig(text, "fleet.yaml");
  ASSERT_FALSE(result.ok()) << text;
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  const std::string message(result.status().message());
  EXPECT_EQ(message.rfind(where, 0), 0u) << message;
  EXPECT_NE(message.find(what), std::string::npos) << message;
}

TEST(SystemsConfigTest, ErrorsNameTheFileTheLineAndTheProblem) {
  expectError("systems:\n  - robot_id: drone1\n    address: 127.0.0.1\n",
              "fleet.yaml:3:", "expected host:port");
  expectError("systems:\n  - robot_id: drone1\n    address: h:99999\n",
              "fleet.yaml:3:", "expected host:port");
  expectError("systems:\n  - address: h:1\n", "fleet.yaml:2:", "robot_id is missing");
  expectError("systems:\n  - robot_id: d\n", "fleet.yaml:2:", "address is missing");
  expectError("systems:\n  - robot_id: d\n    adress: h:1\n",
              "fleet.yaml:3:", "unknown key 'adress'");
  expectError("sytems: []\n", "fleet.yaml:1:", "unknown key 'sytems'");
  expectError("systems: {robot_id: d}\n", "fleet.yaml:1:", "must be a list");
  expectError("systems:\n  - robot_id: a\n    address: h:1\n  - robot_id: b\n    address: h:1\n",
              "fleet.yaml:4:", "listed twice");
  expectError("systems: [\n", "fleet.yaml:", "");
}

TEST(SystemsConfigTest, MissingFileIsReported) {
  auto result = loadSystemsConfig("/nonexistent/fleet.yaml");
  ASSERT_FALSE(result.ok());
  EXPECT_NE(std::string(result.status().message()).find("/nonexistent/fleet.yaml"),
            std::string::npos);
}

TEST(SystemsConfigTest, HostPort) {
  EXPECT_TRUE(isHostPort("127.0.0.1:50061"));
  EXPECT_TRUE(isHostPort("[::1]:80"));
  EXPECT_TRUE(isHostPort("drone-1.local:1"));
  EXPECT_FALSE(isHostPort("127.0.0.1"));
  EXPECT_FALSE(isHostPort(":50061"));
  EXPECT_FALSE(isHostPort("h:0"));
  EXPECT_FALSE(isHostPort("h:65536"));
  EXPECT_FALSE(isHostPort("h:12a"));
}

}  // namespace
}  // namespace behaviorlib::coordinator
