// AccessPolicy: which role each method needs, the policy file, and how a
// caller is identified (by bearer token, else by its certificate's names).

#include "behaviorlib/server_kit/access_policy.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>

namespace behaviorlib::server_kit {
namespace {

using ::testing::HasSubstr;

TEST(RequiredRoleTest, EveryKindOfMethodNeedsItsRole) {
  EXPECT_EQ(requiredRole("/grpc.health.v1.Health/Check"), Role::kViewer);
  EXPECT_EQ(requiredRole("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"),
            Role::kViewer);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/ListMissions"), Role::kViewer);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/WatchEvents"), Role::kViewer);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Channel/Subscribe"), Role::kViewer);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/StartMission"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/WriteBelief"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.BehaviorSystem/ActivateBehavior"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/PauseFleetBehavior"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/ModifyFleetBehavior"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/CheckFleetBehaviorActivation"),
            Role::kViewer);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.behaviors.TakeOff/Activate"), Role::kOperator);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/Kill"), Role::kSafety);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/EmergencyLand"), Role::kSafety);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Coordinator/RegisterSystem"), Role::kSystem);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Simulator/FollowTime"), Role::kSystem);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Simulator/Reset"), Role::kAdmin);
  EXPECT_EQ(requiredRole("/behaviorlib.v1.Simulator/InjectFailure"), Role::kAdmin);
  // Unknown methods need more than viewing.
  EXPECT_EQ(requiredRole("/evil.Service/DoIt"), Role::kOperator);
  EXPECT_EQ(requiredRole(""), Role::kOperator);
}

constexpr char kPolicy[] = R"(identities:
  - certificate: behaviorlib:operator
    roles: [viewer, operator]
  - certificate: behaviorlib:drone1-nav
    roles: [viewer, system]
    system: {robot: drone1, name: navigation_with_lidar}
  - token_sha256: 9F86D081884C7D659A2FEAA0C55AD015A3BF4F1B2B0B822CD15D6C15B0F00A08
    name: dashboard
    roles: [viewer]
)";

TEST(AccessPolicyTest, IdentifiesByTokenElseByCertificateName) {
  auto policy = AccessPolicy::parse(kPolicy, "policy.yaml");
  ASSERT_TRUE(policy.ok()) << policy.status();
  EXPECT_EQ(policy->size(), 3u);
  const Identity* op = policy->identify({"behaviorlib:operator", "localhost"}, "");
  ASSERT_NE(op, nullptr);
  EXPECT_EQ(op->roles, (std::set<Role>{Role::kViewer, Role::kOperator}));
  const Identity* nav = policy->identify({"x", "behaviorlib:drone1-nav"}, "");
  ASSERT_NE(nav, nullptr);
  EXPECT_EQ(nav->robot_id, "drone1");
  EXPECT_EQ(nav->system, "navigation_with_lidar");
  // sha256("test"), written in upper case in the file.
  const Identity* token = policy->identify({"behaviorlib:operator"}, "test");
  ASSERT_NE(token, nullptr);
  EXPECT_EQ(token->name, "dashboard");
  EXPECT_EQ(policy->identify({"behaviorlib:operator"}, "wrong"), nullptr)
      << "a wrong token is not made good by the certificate";
  EXPECT_EQ(policy->identify({"behaviorlib:stranger"}, ""), nullptr);
}

TEST(AccessPolicyTest, BindsAnIdentityToOneRobot) {
  auto policy = AccessPolicy::parse(R"(identities:
  - certificate: tablet
    roles: [viewer, operator]
    robot: drone2
)",
                                    "policy.yaml");
  ASSERT_TRUE(policy.ok()) << policy.status();
  const Identity* tablet = policy->identify({"tablet"}, "");
  ASSERT_NE(tablet, nullptr);
  EXPECT_EQ(tablet->robot_id, "drone2");
}

TEST(RobotScopeTest, ABoundCallerCommandsAndPublishesOnlyItsRobot) {
  const RobotScope unbound;
  EXPECT_TRUE(unbound.permits("drone2", "activate behaviors").ok());
  EXPECT_TRUE(unbound.permitsTopic("robots/drone2/pose").ok());

  const RobotScope drone1("behaviorlib:drone1-nav", "drone1");
  EXPECT_TRUE(drone1.permits("drone1", "activate behaviors").ok());
  const absl::Status other = drone1.permits("drone2", "activate behaviors");
  EXPECT_EQ(other.code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(other.message(),
              HasSubstr("'behaviorlib:drone1-nav' may activate behaviors only for robot drone1, "
                        "not for robot 'drone2'"));
  EXPECT_EQ(drone1.permits("", "start missions").code(), absl::StatusCode::kPermissionDenied);

  EXPECT_TRUE(drone1.permitsTopic("robots/drone1/pose").ok());
  EXPECT_EQ(drone1.permitsTopic("robots/drone2/pose").code(), absl::StatusCode::kPermissionDenied);
  // A prefix of another robot's name is not its own.
  EXPECT_EQ(drone1.permitsTopic("robots/drone10/pose").code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(drone1.permitsTopic("robots/drone1").code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(drone1.permitsTopic("world/obstacles").code(), absl::StatusCode::kPermissionDenied);
  // Topics every robot publishes, when the caller names their prefix.
  EXPECT_TRUE(drone1.permitsTopic("robots/swarm/positions", "robots/swarm/").ok());
  const absl::Status shared = drone1.permitsTopic("robots/drone2/pose", "robots/swarm/");
  EXPECT_THAT(shared.message(),
              HasSubstr("may publish only under robots/drone1/ or robots/swarm/, not on "
                        "'robots/drone2/pose'"));
}

struct BadPolicy {
  std::string text;
  std::string message;
};

class BadPolicyTest : public ::testing::TestWithParam<BadPolicy> {};

TEST_P(BadPolicyTest, IsRefusedNamingFileAndLine) {
  auto policy = AccessPolicy::parse(GetParam().text, "p.yaml");
  ASSERT_FALSE(policy.ok());
  EXPECT_EQ(policy.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(policy.status().message(), HasSubstr("p.yaml:"));
  EXPECT_THAT(policy.status().message(), HasSubstr(GetParam().message));
}

INSTANTIATE_TEST_SUITE_P(
    Files, BadPolicyTest,
    ::testing::Values(
        BadPolicy{"identities: {}\n", "a list 'identities'"},
        BadPolicy{"identities: []\nextra: 1\n", "unknown key 'extra'"},
        BadPolicy{"identities:\n  - roles: [viewer]\n", "either a certificate or a token_sha256"},
        BadPolicy{"identities:\n  - certificate: a\n", "needs a list of roles"},
        BadPolicy{"identities:\n  - certificate: a\n    roles: [root]\n", "unknown role 'root'"},
        BadPolicy{"identities:\n  - certificate: a\n    roles: [system]\n",
                  "the system role needs system"},
        BadPolicy{"identities:\n  - token_sha256: abc\n    roles: [viewer]\n", "64 hex digits"},
        BadPolicy{"identities:\n  - certificate: a\n    roles: [viewer]\n    robot: [x]\n",
                  "robot: ROBOT_ID"},
        BadPolicy{"identities:\n  - certificate: a\n    roles: [system]\n"
                  "    system: {robot: drone1, name: s}\n    robot: drone2\n",
                  "is not the system's robot 'drone1'"},
        BadPolicy{"identities:\n  - ? [a]\n    : 1\n", "p.yaml:"}));

}  // namespace
}  // namespace behaviorlib::server_kit
