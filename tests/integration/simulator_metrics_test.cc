// The simulator's /metrics, scraped from the running binary (with the
// channel broker, free-running at 5x): every series exists, and they move
// as the vehicle takes off, the sensors publish, the camera renders for a
// subscriber and a fault is injected.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <thread>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/prometheus_text.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

using Labels = std::map<std::string, std::string>;

std::unique_ptr<grpc::ClientContext> deadline(seconds s = seconds(10)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + s);
  return context;
}

/// The value of the series `name` with (at least) `labels` in a Prometheus
/// text exposition; nullopt when absent.
std::optional<double> value(const std::string& text, const std::string& name,
                            const Labels& labels = {}) {
  return support::metricValue(text, name, labels);
}

class SimulatorMetricsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        std::vector<std::string>{"--channel", broker_.address(), "--vehicles", "drone1",
                                 "--time-scale", "5", "--enable-fault-injection"});
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    ASSERT_GT(simulator_->metricsPort(), 0);
    auto channel = grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials());
    sim_ = v1::Simulator::NewStub(channel);
    flight_ = v1::FlightController::NewStub(channel);
  }

  std::string scrape() { return support::httpGet(simulator_->metricsPort(), "/metrics"); }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
};

TEST_F(SimulatorMetricsTest, EverySeriesExistsAndMovesWithTheSimulation) {
  std::this_thread::sleep_for(milliseconds(800));
  const std::string first = scrape();
  ASSERT_FALSE(first.empty()) << "GET /metrics failed";
  const Labels z = {{"robot", "drone1"}, {"axis", "z"}};
  const Labels drone1 = {{"robot", "drone1"}};
  for (const char* name :
       {"behaviorlib_simulator_real_time_factor", "behaviorlib_simulator_time_scale",
        "behaviorlib_simulator_lock_step", "behaviorlib_simulator_time_seconds",
        "behaviorlib_simulator_step_seconds_count", "behaviorlib_simulator_step_seconds_sum",
        "behaviorlib_simulator_publish_dropped_total"}) {
    EXPECT_TRUE(value(first, name)) << name << " missing";
  }
  EXPECT_EQ(value(first, "behaviorlib_simulator_time_scale"), 5.0);
  EXPECT_EQ(value(first, "behaviorlib_simulator_lock_step"), 0.0);
  EXPECT_EQ(value(first, "behaviorlib_simulator_vehicle_position_meters", z), 0.0) << "landed";
  // One series per state, 1 for the vehicle's.
  EXPECT_EQ(value(first, "behaviorlib_simulator_vehicle_flight_state",
                  {{"robot", "drone1"}, {"state", "LANDED"}}),
            1.0);
  for (const char* state : {"TAKING_OFF", "FLYING", "HOVERING", "LANDING", "EMERGENCY"}) {
    EXPECT_EQ(value(first, "behaviorlib_simulator_vehicle_flight_state",
                    {{"robot", "drone1"}, {"state", state}}),
              0.0)
        << state;
  }
  EXPECT_EQ(value(first, "behaviorlib_simulator_vehicle_crashed", drone1), 0.0);
  EXPECT_TRUE(value(first, "behaviorlib_simulator_vehicle_battery_ratio", drone1));
  EXPECT_TRUE(value(first, "behaviorlib_simulator_sensor_samples_total",
                    {{"robot", "drone1"}, {"sensor", "imu"}}));

  // Take off, look through the camera, fail the GPS.
  v1::AcquireLeaseRequest lease_request;
  lease_request.set_robot_id("drone1");
  lease_request.set_holder("test");
  *lease_request.mutable_ttl() = TimeUtil::SecondsToDuration(10);
  v1::AcquireLeaseResponse lease;
  ASSERT_TRUE(flight_->AcquireLease(deadline().get(), lease_request, &lease).ok());
  v1::ExecuteFlightActionRequest takeoff;
  takeoff.set_robot_id("drone1");
  takeoff.set_lease_id(lease.lease_id());
  takeoff.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
  takeoff.set_takeoff_altitude_m(3.0);
  v1::ExecuteFlightActionResponse reply;
  ASSERT_TRUE(flight_->ExecuteFlightAction(deadline().get(), takeoff, &reply).ok());
  behaviorlib::channel::ChannelClient client(broker_.address());
  auto camera = client.subscribe("robots/drone1/camera/image", {.mode = v1::DELIVERY_MODE_LATEST},
                                 [](const v1::SubscribeResponse&) {});
  ASSERT_TRUE(camera->waitConnected(seconds(10)));
  v1::InjectFailureRequest gps_off;
  gps_off.set_robot_id("drone1");
  gps_off.set_component(v1::FAILURE_COMPONENT_GPS);
  gps_off.set_type(v1::FAILURE_TYPE_OFF);
  v1::InjectFailureResponse injected;
  ASSERT_TRUE(sim_->InjectFailure(deadline().get(), gps_off, &injected).ok());
  std::this_thread::sleep_for(milliseconds(1500));  // 7.5 s simulated, camera polled
  const std::string second = scrape();

  auto moved = [&](const std::string& name, const Labels& labels = {}) {
    const auto a = value(first, name, labels);
    const auto b = value(second, name, labels);
    EXPECT_TRUE(a && b) << name;
    return a && b ? *b - *a : 0.0;
  };
  EXPECT_GT(moved("behaviorlib_simulator_time_seconds"), 3.0);
  EXPECT_GT(moved("behaviorlib_simulator_step_seconds_count"), 3000.0) << "one count per step";
  EXPECT_GT(moved("behaviorlib_simulator_step_seconds_sum"), 0.0);
  EXPECT_GT(value(second, "behaviorlib_simulator_real_time_factor").value_or(0), 1.0);
  EXPECT_GT(moved("behaviorlib_simulator_vehicle_position_meters", z), 1.0) << "took off";
  EXPECT_LT(moved("behaviorlib_simulator_vehicle_battery_ratio", drone1), 0.0) << "drains";
  EXPECT_EQ(value(second, "behaviorlib_simulator_vehicle_flight_state",
                  {{"robot", "drone1"}, {"state", "LANDED"}}),
            0.0);
  // Every server's own metrics: its gRPC calls, the process, the build.
  EXPECT_EQ(value(second, "grpc_server_handled_total",
                  {{"grpc_type", "unary"},
                   {"grpc_service", "behaviorlib.v1.FlightController"},
                   {"grpc_method", "ExecuteFlightAction"},
                   {"grpc_code", "OK"}}),
            1.0);
  EXPECT_EQ(value(second, "grpc_server_handling_seconds_count",
                  {{"grpc_service", "behaviorlib.v1.Simulator"}, {"grpc_method", "InjectFailure"}}),
            1.0);
  EXPECT_GT(value(second, "process_resident_memory_bytes").value_or(0), 1 << 20);
  EXPECT_GT(value(second, "process_cpu_seconds_total").value_or(0), 0.0);
  EXPECT_EQ(value(second, "behaviorlib_build_info"), 1.0);
  EXPECT_GT(
      moved("behaviorlib_simulator_sensor_samples_total", {{"robot", "drone1"}, {"sensor", "imu"}}),
      3.0 * 200);
  EXPECT_GT(value(second, "behaviorlib_simulator_sensor_frame_seconds_count", {{"sensor", "lidar"}})
                .value_or(0),
            value(first, "behaviorlib_simulator_sensor_frame_seconds_count", {{"sensor", "lidar"}})
                .value_or(0));
  EXPECT_GT(
      value(second, "behaviorlib_simulator_sensor_frame_seconds_count", {{"sensor", "camera"}})
          .value_or(0),
      0.0)
      << "frames rendered for the subscriber";
  EXPECT_EQ(value(second, "behaviorlib_simulator_active_faults",
                  {{"robot", "drone1"}, {"component", "gps"}}),
            1.0);
  EXPECT_GT(value(second, "behaviorlib_simulator_sensor_samples_dropped_total",
                  {{"robot", "drone1"}, {"sensor", "gps"}, {"reason", "fault"}})
                .value_or(0),
            10.0);
  EXPECT_TRUE(value(second, "behaviorlib_simulator_sensor_samples_dropped_total",
                    {{"robot", "drone1"}, {"sensor", "camera"}, {"reason", "worker_busy"}}));
  EXPECT_EQ(simulator_->terminate(), 0);
}

}  // namespace
