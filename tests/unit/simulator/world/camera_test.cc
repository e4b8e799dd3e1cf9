#include "simulator/world/camera.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <numbers>
#include <opencv2/imgcodecs.hpp>

#include "formats/world/world.h"

namespace behaviorlib::sim {
namespace {

using ::testing::ElementsAre;
using ::testing::IsEmpty;
using ::testing::UnorderedElementsAre;

Eigen::Quaterniond yaw(double yaw_rad) {
  return Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
}

/// A 4 m wide panel whose near face is x = 3, with a 0.8 m marker on it.
world::World markerWorld(const std::string& text) {
  world::World world("marker");
  world.addBox(world::Box{
      "panel", {3.1, 0.0, 1.5}, {0.2, 4.0, 3.0}, 0.0, {90, 110, 160}, world::Box::Kind::kBox});
  world::Marker marker;
  marker.name = "m";
  marker.text = text;
  marker.center_m = {3.0, 0.0, 1.0};
  marker.normal = {-1, 0, 0};
  marker.up = {0, 0, 1};
  marker.size_m = 0.8;
  marker.attached_to = "panel";
  world.addMarker(marker);
  return world;
}

cv::Vec3b bgrOf(world::Rgb color) { return cv::Vec3b(color.b, color.g, color.r); }

TEST(Camera, MarkerThreeMetresAheadDecodes) {
  const world::World world = markerWorld("behaviorlib marker 1");
  absl::StatusOr<Camera> camera = Camera::create(world, CameraConfig{});
  ASSERT_TRUE(camera.ok()) << camera.status();
  const cv::Mat image = camera->render({0, 0, 1}, Eigen::Quaterniond::Identity());
  ASSERT_EQ(image.type(), CV_8UC3);
  ASSERT_EQ(image.cols, 640);
  ASSERT_EQ(image.rows, 480);
  EXPECT_THAT(decodeQr(image), ElementsAre("behaviorlib marker 1"));
  // The marker is centred: the principal point sees it.
  const std::optional<Eigen::Vector2d> centre =
      camera->project({2.995, 0, 1}, {0, 0, 1}, Eigen::Quaterniond::Identity());
  ASSERT_TRUE(centre.has_value());
  EXPECT_NEAR(centre->x(), 319.5, 1e-9);
  EXPECT_NEAR(centre->y(), 239.5, 1e-9);
}

TEST(Camera, SkyGroundAndFramesAreWhereExpected) {
  const world::World world = markerWorld("x");
  absl::StatusOr<Camera> camera = Camera::create(world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  // Facing west (away from the panel): sky above the horizon, ground below.
  const cv::Mat image = camera->render({0, 0, 1}, yaw(std::numbers::pi));
  EXPECT_EQ(image.at<cv::Vec3b>(10, 320), bgrOf(world.skyColor()));
  EXPECT_EQ(image.at<cv::Vec3b>(470, 320), bgrOf(world.groundColor()));
  // A point left of the body (+y in FLU) appears on the left of the image.
  const std::optional<Eigen::Vector2d> left =
      camera->project({3, 1, 1}, {0, 0, 1}, Eigen::Quaterniond::Identity());
  ASSERT_TRUE(left.has_value());
  EXPECT_LT(left->x(), 319.5);
  // A camera exactly at ground level still sees the ground below the horizon.
  const cv::Mat low = camera->render({0, 0, 0}, yaw(std::numbers::pi));
  EXPECT_EQ(low.at<cv::Vec3b>(250, 320), bgrOf(world.groundColor()));
  EXPECT_EQ(low.at<cv::Vec3b>(230, 320), bgrOf(world.skyColor()));
  // Pitched down 90 degrees the camera sees only the ground.
  CameraConfig down;
  down.mount_pitch_rad = std::numbers::pi / 2;
  absl::StatusOr<Camera> down_camera = Camera::create(world, down);
  ASSERT_TRUE(down_camera.ok());
  const cv::Mat ground = down_camera->render({-5, 0, 2}, Eigen::Quaterniond::Identity());
  EXPECT_EQ(ground.at<cv::Vec3b>(0, 0), bgrOf(world.groundColor()));
  EXPECT_EQ(ground.at<cv::Vec3b>(479, 639), bgrOf(world.groundColor()));
}

TEST(Camera, AircraftMarkersDecode) {
  absl::StatusOr<world::World> world =
      world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/aircraft.yaml");
  ASSERT_TRUE(world.ok()) << world.status();
  absl::StatusOr<Camera> camera = Camera::create(*world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  // 3 m in front of each marker (except the one on the wing, seen from
  // above), looking at it.
  for (const world::Marker& marker : world->markers()) {
    Eigen::Vector3d position = marker.center_m + marker.normal * 3.0;
    Eigen::Quaterniond orientation = yaw(std::atan2(-marker.normal.y(), -marker.normal.x()));
    if (std::abs(marker.normal.z()) > 0.5) {
      // Above the wing, looking straight down with the body's x along the
      // marker's up so the code is upright in the image.
      orientation =
          Eigen::Quaterniond(Eigen::AngleAxisd(std::atan2(marker.up.y(), marker.up.x()),
                                               Eigen::Vector3d::UnitZ())) *
          Eigen::Quaterniond(Eigen::AngleAxisd(std::numbers::pi / 2, Eigen::Vector3d::UnitY()));
    }
    const cv::Mat image = camera->render(position, orientation);
    EXPECT_THAT(decodeQr(image), ElementsAre(marker.text)) << marker.name;
  }
}

TEST(Camera, SceneWithoutMarkerDecodesNothing) {
  absl::StatusOr<world::World> world =
      world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  ASSERT_TRUE(world.ok()) << world.status();
  absl::StatusOr<Camera> camera = Camera::create(*world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  const cv::Mat image = camera->render({2, 2, 1}, Eigen::Quaterniond::Identity());
  EXPECT_THAT(decodeQr(image), IsEmpty());
  const world::World empty("empty");
  absl::StatusOr<Camera> empty_camera = Camera::create(empty, CameraConfig{});
  ASSERT_TRUE(empty_camera.ok());
  EXPECT_THAT(decodeQr(empty_camera->render({0, 0, 1}, Eigen::Quaterniond::Identity())), IsEmpty());
}

TEST(Camera, OccludedMarkerDecodesNothing) {
  world::World world = markerWorld("hidden");
  // A crate between the camera and the marker.
  world.addBox(world::Box{
      "crate", {1.5, 0.0, 1.0}, {0.4, 1.5, 1.5}, 0.0, {180, 140, 80}, world::Box::Kind::kBox});
  absl::StatusOr<Camera> camera = Camera::create(world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  const cv::Mat image = camera->render({0, 0, 1}, Eigen::Quaterniond::Identity());
  EXPECT_THAT(decodeQr(image), IsEmpty());
  const cv::Vec3b centre = image.at<cv::Vec3b>(240, 320);
  EXPECT_NE(centre, cv::Vec3b(255, 255, 255));
  EXPECT_NE(centre, cv::Vec3b(0, 0, 0));
}

TEST(Camera, SeveralMarkersInOneImage) {
  world::World world("two");
  const world::World single = markerWorld("unused");
  world.addBox(single.boxes().front());
  world::Marker left = single.markers().front();
  left.text = "left one";
  left.center_m.y() = 1.2;
  world::Marker right = left;
  right.name = "m2";
  right.text = "right one";
  right.center_m.y() = -1.2;
  world.addMarker(left);
  world.addMarker(right);
  absl::StatusOr<Camera> camera = Camera::create(world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  const cv::Mat image = camera->render({0, 0, 1}, Eigen::Quaterniond::Identity());
  EXPECT_THAT(decodeQr(image), UnorderedElementsAre("left one", "right one"));
}

TEST(Camera, EncodedImagesStillDecode) {
  const world::World world = markerWorld("encoded");
  absl::StatusOr<Camera> camera = Camera::create(world, CameraConfig{});
  ASSERT_TRUE(camera.ok());
  const cv::Mat image = camera->render({0, 0, 1}, Eigen::Quaterniond::Identity());
  for (const char* format : {"jpeg", "png"}) {
    absl::StatusOr<std::string> bytes = encodeImage(image, format);
    ASSERT_TRUE(bytes.ok()) << bytes.status();
    ASSERT_FALSE(bytes->empty());
    const std::vector<unsigned char> buffer(bytes->begin(), bytes->end());
    const cv::Mat decoded = cv::imdecode(buffer, cv::IMREAD_COLOR);
    ASSERT_EQ(decoded.size(), image.size()) << format;
    EXPECT_THAT(decodeQr(decoded), ElementsAre("encoded")) << format;
    if (std::string(format) == "png") {
      EXPECT_EQ(cv::norm(decoded, image, cv::NORM_INF), 0.0);  // lossless
    }
  }
  EXPECT_FALSE(encodeImage(image, "gif").ok());
  EXPECT_FALSE(encodeImage(cv::Mat(), "png").ok());
}

TEST(Camera, InvalidConfigIsRejected) {
  const world::World world("empty");
  CameraConfig config;
  config.width_px = 0;
  EXPECT_FALSE(Camera::create(world, config).ok());
  config = CameraConfig();
  config.horizontal_fov_rad = 0.0;
  EXPECT_FALSE(Camera::create(world, config).ok());
}

TEST(Camera, TimePerFrame) {
  for (const char* file : {"rooms.yaml", "aircraft.yaml"}) {
    absl::StatusOr<world::World> world =
        world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/" + file);
    ASSERT_TRUE(world.ok()) << world.status();
    absl::StatusOr<Camera> camera = Camera::create(*world, CameraConfig{});
    ASSERT_TRUE(camera.ok());
    const world::StartPose* start = world->findStartPose("drone1");
    ASSERT_NE(start, nullptr);
    const Eigen::Vector3d position = start->position_m + Eigen::Vector3d(0, 0, 1.5);
    constexpr int kFrames = 30;
    cv::Mat image;
    auto start_time = std::chrono::steady_clock::now();
    for (int i = 0; i < kFrames; ++i) {
      image = camera->render(position, yaw(start->yaw_rad + 0.02 * i));
    }
    const double render_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_time)
            .count() /
        kFrames;
    start_time = std::chrono::steady_clock::now();
    for (int i = 0; i < kFrames; ++i) ASSERT_TRUE(encodeImage(image, "jpeg").ok());
    const double jpeg_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_time)
            .count() /
        kFrames;
    start_time = std::chrono::steady_clock::now();
    for (int i = 0; i < kFrames; ++i) decodeQr(image);
    const double decode_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_time)
            .count() /
        kFrames;
    std::printf(
        "[ timing ] camera 640x480 in %s: render %.2f ms, jpeg %.2f ms, decodeQr %.2f ms per "
        "frame\n",
        file, render_ms, jpeg_ms, decode_ms);
  }
}

}  // namespace
}  // namespace behaviorlib::sim
