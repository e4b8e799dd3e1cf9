// perception_bench: the costs behind the perception and navigation behavior
// systems, measured on the shipped worlds with the simulator's own lidar and
// camera (in-process):
//   - OctoMap insertion per 3-D lidar scan (16 x 360 beams) in the building;
//   - planning time of room-to-room queries in the mapped building (OMPL
//     RRT-Connect + shortening), p50 / p95;
//   - QR decoding + localisation per 640x480 frame of the aircraft, and the
//     search in frames without a code;
//   - EKF prediction (one IMU sample) and GPS update.
//
//   perception_bench            # markdown tables
//   perception_bench --smoke    # few samples; fails only on errors

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "behaviorlib/navigation/occupancy_map.h"
#include "behaviorlib/navigation/path_planner.h"
#include "behaviorlib/sensor_fusion/ekf.h"
#include "behaviorlib/visual_markers/marker_locator.h"
#include "formats/world/world.h"
#include "simulator/world/camera.h"
#include "simulator/world/lidar.h"
#include "unit/navigation/mapping.h"

namespace {

using Clock = std::chrono::steady_clock;
using namespace behaviorlib;

double ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

struct Stats {
  double p50 = 0, p95 = 0, p99 = 0, max = 0;
};

Stats stats(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  auto at = [&](double p) {
    return v[std::min(v.size() - 1, static_cast<size_t>(p * static_cast<double>(v.size())))];
  };
  return {at(0.5), at(0.95), at(0.99), v.back()};
}

}  // namespace

int main(int argc, char** argv) {
  const bool smoke = argc > 1 && std::strcmp(argv[1], "--smoke") == 0;
  int failures = 0;

  // --- the building: map from scans, then room-to-room plans ---------------
  auto rooms = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  if (!rooms.ok()) return 1;
  auto lidar = sim::Lidar::create(*rooms, nav::testing::mappingLidar());
  if (!lidar.ok()) return 1;
  nav::OccupancyMap map;
  std::vector<double> insert_ms;
  std::vector<Eigen::Vector3d> scan_points;
  for (double x = 1.5; x < 17.0; x += smoke ? 5.0 : 1.5) {
    for (double y = 1.5; y < 9.0; y += smoke ? 4.0 : 1.5) scan_points.emplace_back(x, y, 1.5);
  }
  for (const auto& p : scan_points) {
    if (!rooms->collidingSurface(p, 0.3).empty()) continue;
    const auto t0 = Clock::now();
    nav::testing::scanInto(map, *lidar, p);
    insert_ms.push_back(ms(Clock::now() - t0));
  }
  // The simulator's default lidar: 2-D, 360 beams, 30 m.
  sim::LidarConfig planar_config;
  planar_config.range_max_m = 30.0;
  auto planar = sim::Lidar::create(*rooms, planar_config);
  if (!planar.ok()) return 1;
  nav::OccupancyMap planar_map;
  std::vector<double> planar_ms;
  for (const auto& p : scan_points) {
    if (!rooms->collidingSurface(p, 0.3).empty()) continue;
    const auto t0 = Clock::now();
    nav::testing::scanInto(planar_map, *planar, p);
    planar_ms.push_back(ms(Clock::now() - t0));
  }
  nav::seedPlanner(7);
  nav::PlanOptions options;
  options.bounds_min_m = {0.2, 0.2, 0.8};
  options.bounds_max_m = {17.8, 9.8, 2.0};
  const std::vector<Eigen::Vector3d> rooms_centres = {
      {3, 3, 1.5}, {9, 5, 1.5}, {15, 2.5, 1.5}, {16.5, 8.5, 1.5}};
  std::vector<double> plan_ms, inflation_ms;
  const int repeats = smoke ? 1 : 10;
  for (int r = 0; r < repeats; ++r) {
    for (size_t i = 0; i < rooms_centres.size(); ++i) {
      for (size_t j = 0; j < rooms_centres.size(); ++j) {
        if (i == j) continue;
        auto path = nav::planPath(map, rooms_centres[i], rooms_centres[j], options);
        if (!path.ok()) {
          std::fprintf(stderr, "plan failed: %s\n", std::string(path.status().message()).c_str());
          ++failures;
          continue;
        }
        plan_ms.push_back(path->planning_time_s * 1000.0);
        inflation_ms.push_back(path->inflation_time_s * 1000.0);
      }
    }
  }

  // --- the aircraft: QR decoding and localisation per frame ----------------
  auto aircraft = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/aircraft.yaml");
  if (!aircraft.ok()) return 1;
  sim::CameraConfig config;
  auto camera = sim::Camera::create(*aircraft, config);
  if (!camera.ok()) return 1;
  markers::CameraModel model;
  model.fx_px = model.fy_px = camera->focalLengthPx();
  // Each marker from 3, 5 and 7 m, straight on and from the side (a fresh
  // locator per marker, warmed up by one frame: WeChatQRCode's first call
  // initialises it); then the same views turned 50 degrees away from the
  // marker (the aircraft's skin without a code: most frames of a mission).
  std::vector<double> qr_ms, qr_empty_ms;
  size_t located = 0, frames = 0;
  for (const auto& marker : aircraft->markers()) {
    markers::MarkerLocator locator(model, marker.size_m);
    for (const double distance : {3.0, 5.0, 7.0}) {
      for (const double sideways : {0.0, 0.4 * distance}) {
        const Eigen::Vector3d position =
            marker.center_m + marker.normal * distance + marker.right() * sideways;
        const Eigen::Quaterniond attitude = Eigen::Quaterniond::FromTwoVectors(
            Eigen::Vector3d::UnitX(), (marker.center_m - position).normalized());
        const cv::Mat frame = camera->render(position, attitude);
        located += locator.locate(frame, attitude, position).size();
        ++frames;
        for (int k = 0; k < (smoke ? 1 : 10); ++k) {
          const auto t0 = Clock::now();
          locator.locate(frame, attitude, position);
          qr_ms.push_back(ms(Clock::now() - t0));
        }
        const Eigen::Quaterniond away =
            attitude * Eigen::Quaterniond(Eigen::AngleAxisd(0.87, Eigen::Vector3d::UnitZ()));
        const cv::Mat skin = camera->render(position, away);
        for (int k = 0; k < (smoke ? 1 : 10); ++k) {
          const auto t0 = Clock::now();
          located += 100 * locator.locate(skin, away, position).size();  // none expected
          qr_empty_ms.push_back(ms(Clock::now() - t0));
        }
      }
    }
  }
  std::fprintf(stderr, "QR: %zu of %zu frames with a marker located\n", located, frames);
  if (located != frames) ++failures;

  // --- EKF -------------------------------------------------------------------
  fusion::InsEkf ekf;
  ekf.initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  std::mt19937_64 rng(1);
  std::normal_distribution<double> n(0, 0.05);
  std::vector<double> predict_us, update_us;
  for (int i = 0; i < (smoke ? 100 : 20000); ++i) {
    const Eigen::Vector3d gyro(n(rng), n(rng), n(rng));
    const Eigen::Vector3d accel(n(rng), n(rng), 9.81 + n(rng));
    auto t0 = Clock::now();
    ekf.predict(gyro, accel, 0.005);
    predict_us.push_back(ms(Clock::now() - t0) * 1000.0);
    if (i % 20 == 0) {
      t0 = Clock::now();
      ekf.updatePosition(Eigen::Vector3d(n(rng), n(rng), 1.0 + n(rng)), 0.3, 0.5);
      update_us.push_back(ms(Clock::now() - t0) * 1000.0);
    }
  }
  if (!ekf.finite()) ++failures;

  const Stats ins = stats(insert_ms), plan = stats(plan_ms), qr = stats(qr_ms),
              pred = stats(predict_us), upd = stats(update_us);
  std::printf(
      "| figure | samples | p50 | p95 | p99 | max | target "
      "|\n|---|---:|---:|---:|---:|---:|---|\n");
  const Stats planar_stats = stats(planar_ms);
  std::printf(
      "| OctoMap insertion per 2-D scan (360 beams, 30 m: the simulator's default lidar) | %zu | "
      "%.2f ms | %.2f ms | %.2f ms | %.2f ms | <= 20 ms |\n",
      planar_ms.size(), planar_stats.p50, planar_stats.p95, planar_stats.p99, planar_stats.max);
  std::printf(
      "| OctoMap insertion per 3-D scan (16x360 beams, 12 m) | %zu | %.2f ms | %.2f ms | %.2f ms | "
      "%.2f ms | <= 20 ms |\n",
      insert_ms.size(), ins.p50, ins.p95, ins.p99, ins.max);
  std::printf(
      "| planning, room to room (RRT-Connect + shortening) | %zu | %.2f ms | %.2f ms | %.2f ms | "
      "%.2f ms | p50 <= 20 ms, p95 <= 100 ms |\n",
      plan_ms.size(), plan.p50, plan.p95, plan.p99, plan.max);
  const Stats infl = stats(inflation_ms);
  std::printf(
      "| of which the inflated grid (EDT over the planning box) | %zu | %.2f ms | %.2f ms | %.2f "
      "ms | %.2f ms | — |\n",
      inflation_ms.size(), infl.p50, infl.p95, infl.p99, infl.max);
  std::printf(
      "| QR decode + locate per 640x480 frame with a code | %zu | %.2f ms | %.2f ms | %.2f ms | "
      "%.2f ms | <= 10 ms |\n",
      qr_ms.size(), qr.p50, qr.p95, qr.p99, qr.max);
  const Stats qr_empty = stats(qr_empty_ms);
  std::printf(
      "| QR search per 640x480 frame without a code | %zu | %.2f ms | %.2f ms | %.2f ms | %.2f "
      "ms | — |\n",
      qr_empty_ms.size(), qr_empty.p50, qr_empty.p95, qr_empty.p99, qr_empty.max);
  std::printf(
      "| EKF prediction (one IMU sample) | %zu | %.2f us | %.2f us | %.2f us | %.2f us | — |\n",
      predict_us.size(), pred.p50, pred.p95, pred.p99, pred.max);
  std::printf("| EKF GPS update | %zu | %.2f us | %.2f us | %.2f us | %.2f us | — |\n",
              update_us.size(), upd.p50, upd.p95, upd.p99, upd.max);
  std::printf("\nmap: %zu occupied leaves, %.0f m^3 known free\n", map.occupiedLeafCount(),
              map.freeVolumeM3());
  return failures == 0 ? 0 : 1;
}
