#include "visual_markers/marker_locator.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numbers>
#include <opencv2/imgproc.hpp>
#include <opencv2/objdetect.hpp>

#include "simulator/world/camera.h"
#include "simulator/world/world.h"

namespace behaviorlib::markers {
namespace {

class Aircraft : public ::testing::Test {
 protected:
  void SetUp() override {
    auto world = sim::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/aircraft.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<sim::World>(std::move(*world));
    sim::CameraConfig config;
    config.mount_position_m = {0.1, 0.0, -0.05};
    config.mount_pitch_rad = 0.1;
    auto camera = sim::Camera::create(*world_, config);
    ASSERT_TRUE(camera.ok());
    camera_ = std::make_unique<sim::Camera>(std::move(*camera));
    model_.width_px = config.width_px;
    model_.height_px = config.height_px;
    model_.fx_px = model_.fy_px = camera_->focalLengthPx();
    model_.cx_px = (config.width_px - 1) / 2.0;
    model_.cy_px = (config.height_px - 1) / 2.0;
    model_.position_in_body_m = config.mount_position_m;
    // Optical axes: z = mount +x (pitched down), x = mount -y, y = mount -z.
    const Eigen::Quaterniond mount(
        Eigen::AngleAxisd(config.mount_pitch_rad, Eigen::Vector3d::UnitY()));
    model_.body_from_optical = mount * model_.body_from_optical;
  }

  // A viewpoint `distance` m in front of a marker with the body's x axis
  // towards it (for a marker facing up, the body looks down: the locator's
  // geometry does not care how a vehicle would get there).
  std::pair<Eigen::Vector3d, Eigen::Quaterniond> facing(const sim::Marker& marker,
                                                        double distance) const {
    const Eigen::Vector3d position = marker.center_m + marker.normal * distance;
    return {position, Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitX(), -marker.normal)};
  }

  std::unique_ptr<sim::World> world_;
  std::unique_ptr<sim::Camera> camera_;
  CameraModel model_;
};

TEST_F(Aircraft, EveryMarkerIsDecodedAndLocatedWithinTenCentimetres) {
  ASSERT_FALSE(world_->markers().empty());
  for (const sim::Marker& marker : world_->markers()) {
    MarkerLocator locator(model_, marker.size_m);
    const auto [position, attitude] = facing(marker, 3.0);
    const cv::Mat image = camera_->render(position, attitude);
    const auto found = locator.locate(image, attitude, position);
    ASSERT_EQ(found.size(), 1u) << marker.name;
    EXPECT_EQ(found[0].text, marker.text);
    EXPECT_LT((found[0].position_world_m - marker.center_m).norm(), 0.1)
        << marker.name << ": " << found[0].position_world_m.transpose();
    EXPECT_NEAR(found[0].range_m,
                (position + attitude * model_.position_in_body_m - marker.center_m).norm(), 0.1);
    EXPECT_LT(found[0].reprojection_error_px, 2.0);
  }
}

TEST_F(Aircraft, AnObliqueViewStillLocatesTheMarker) {
  const sim::Marker& marker = world_->markers().front();
  MarkerLocator locator(model_, marker.size_m);
  auto [position, attitude] = facing(marker, 4.0);
  // Step sideways by 1.5 m and turn back towards the marker.
  const Eigen::Vector3d side = marker.up.cross(marker.normal).normalized();
  position += side * 1.5;
  const Eigen::Vector3d look = marker.center_m - position;
  attitude = Eigen::AngleAxisd(std::atan2(look.y(), look.x()), Eigen::Vector3d::UnitZ());
  const auto found = locator.locate(camera_->render(position, attitude), attitude, position);
  ASSERT_EQ(found.size(), 1u);
  EXPECT_LT((found[0].position_world_m - marker.center_m).norm(), 0.2);
}

TEST_F(Aircraft, AnImageWithoutMarkersGivesNothing) {
  MarkerLocator locator(model_, 1.0);
  const Eigen::Quaterniond up_to_sky(Eigen::AngleAxisd(-1.2, Eigen::Vector3d::UnitY()));
  EXPECT_TRUE(
      locator.locate(camera_->render({30, 30, 2}, up_to_sky), up_to_sky, {30, 30, 2}).empty());
  EXPECT_TRUE(locator.locate(cv::Mat(), up_to_sky, {0, 0, 0}).empty());
}

TEST(MarkerLocator, DecodesSeveralCodesInOneImage) {
  cv::Mat canvas(480, 640, CV_8UC1, cv::Scalar(255));
  int x = 40;
  for (const std::string text : {"FIRST-CODE", "SECOND-CODE"}) {
    cv::Mat code, big;
    cv::QRCodeEncoder::create()->encode(text, code);
    cv::resize(code, big, cv::Size(), 8, 8, cv::INTER_NEAREST);
    big.copyTo(canvas(cv::Rect(x, 140, big.cols, big.rows)));
    x += big.cols + 80;
  }
  MarkerLocator locator(CameraModel{}, 1.0);
  const auto found = locator.decode(canvas);
  std::vector<std::string> texts;
  for (const auto& [text, quad] : found) {
    texts.push_back(text);
    EXPECT_EQ(quad.size(), 4u);
  }
  std::sort(texts.begin(), texts.end());
  EXPECT_EQ(texts, (std::vector<std::string>{"FIRST-CODE", "SECOND-CODE"}));
}

TEST(MarkerLocator, TheSymbolSideExcludesTheQuietZone) {
  MarkerLocator locator(CameraModel{}, 1.0);
  const double side = locator.symbolSideM("AC-001/FUSELAGE-LEFT");
  EXPECT_GT(side, 0.7);  // 25 modules + 8 of quiet zone -> 0.76 m
  EXPECT_LT(side, 1.0);
}

}  // namespace
}  // namespace behaviorlib::markers
