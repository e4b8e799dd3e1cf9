#include "behaviorlib/visual_markers/marker_locator.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/objdetect.hpp>

#include "behaviorlib/visual_markers/qr_finder.h"
#include "formats/world/world.h"
#include "simulator/world/camera.h"

namespace behaviorlib::markers {
namespace {

class Aircraft : public ::testing::Test {
 protected:
  void SetUp() override {
    auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/aircraft.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<world::World>(std::move(*world));
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
  std::pair<Eigen::Vector3d, Eigen::Quaterniond> facing(const world::Marker& marker,
                                                        double distance) const {
    const Eigen::Vector3d position = marker.center_m + marker.normal * distance;
    return {position, Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitX(), -marker.normal)};
  }

  std::unique_ptr<world::World> world_;
  std::unique_ptr<sim::Camera> camera_;
  CameraModel model_;
};

TEST_F(Aircraft, EveryMarkerIsDecodedAndLocatedWithinTenCentimetres) {
  ASSERT_FALSE(world_->markers().empty());
  for (const world::Marker& marker : world_->markers()) {
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

TEST_F(Aircraft, SymbolCornersAreFoundWithinAPixel) {
  // The symbol's corners (its quiet zone left out) projected with the camera
  // model against the finder's, from 2 to 7 m (the whole marker in view),
  // straight on and from the side. (The renderer lifts markers 5 mm off
  // their surface.)
  std::vector<double> worsts;
  for (const world::Marker& marker : world_->markers()) {
    MarkerLocator locator(model_, marker.size_m);
    const double h = 0.5 * locator.symbolSideM(marker.text);
    const Eigen::Vector3d lifted = marker.center_m + marker.normal * 0.005;
    const Eigen::Vector3d right = marker.right();
    const std::array<Eigen::Vector3d, 4> truth = {
        lifted - right * h + marker.up * h, lifted + right * h + marker.up * h,
        lifted + right * h - marker.up * h, lifted - right * h - marker.up * h};
    for (const double distance : {2.0, 3.0, 5.0, 7.0}) {
      for (const double sideways : {0.0, 0.4 * distance}) {
        Eigen::Vector3d position = marker.center_m + marker.normal * distance + right * sideways;
        const Eigen::Quaterniond attitude = Eigen::Quaterniond::FromTwoVectors(
            Eigen::Vector3d::UnitX(), (marker.center_m - position).normalized());
        cv::Mat gray;
        cv::cvtColor(camera_->render(position, attitude), gray, cv::COLOR_BGR2GRAY);
        const auto quads = findQrSymbols(gray);
        ASSERT_EQ(quads.size(), 1u) << marker.name << " at " << distance << " m";
        const Eigen::Quaterniond optical_from_world =
            (attitude * model_.body_from_optical).conjugate();
        const Eigen::Vector3d camera = position + attitude * model_.position_in_body_m;
        double worst = 0;
        for (size_t k = 0; k < 4; ++k) {
          const Eigen::Vector3d p = optical_from_world * (truth[k] - camera);
          const cv::Point2f expected(
              static_cast<float>(model_.cx_px + model_.fx_px * p.x() / p.z()),
              static_cast<float>(model_.cy_px + model_.fy_px * p.y() / p.z()));
          worst = std::max(worst, static_cast<double>(cv::norm(quads[0].corners[k] - expected)));
        }
        worsts.push_back(worst);
        EXPECT_LT(worst, 1.5) << marker.name << " at " << distance << " m, " << sideways
                              << " m sideways";
      }
    }
  }
  // Typically a fifth of a pixel.
  ASSERT_EQ(worsts.size(), world_->markers().size() * 8);
  std::nth_element(worsts.begin(), worsts.begin() + worsts.size() / 2, worsts.end());
  EXPECT_LT(worsts[worsts.size() / 2], 0.4);
}

TEST_F(Aircraft, ViewsUpTo55DegreesOffTheNormalStillLocate) {
  // Flying past a marker: seen 45 and 55 degrees off its normal, to either
  // side (foreshortened to 0.7 and 0.57 of its width).
  for (const world::Marker& marker : world_->markers()) {
    MarkerLocator locator(model_, marker.size_m);
    for (const double degrees : {-55.0, -45.0, 45.0, 55.0}) {
      const double angle = degrees * std::numbers::pi / 180.0;
      const Eigen::Vector3d position = marker.center_m + marker.normal * 3.0 * std::cos(angle) +
                                       marker.right() * 3.0 * std::sin(angle);
      const Eigen::Quaterniond attitude = Eigen::Quaterniond::FromTwoVectors(
          Eigen::Vector3d::UnitX(), (marker.center_m - position).normalized());
      const auto found = locator.locate(camera_->render(position, attitude), attitude, position);
      ASSERT_EQ(found.size(), 1u) << marker.name << " at " << degrees << " degrees";
      EXPECT_EQ(found[0].text, marker.text);
      EXPECT_LT((found[0].position_world_m - marker.center_m).norm(), 0.15)
          << marker.name << " at " << degrees << " degrees";
    }
  }
}

TEST_F(Aircraft, NoisyBlurredAndCompressedFramesStillLocate) {
  // A real camera's frame: sensor noise (sigma 6 grey levels), a little
  // defocus, and JPEG at quality 75.
  cv::RNG rng(7);
  for (const world::Marker& marker : world_->markers()) {
    MarkerLocator locator(model_, marker.size_m);
    for (const double distance : {3.0, 5.0}) {
      const auto [position, attitude] = facing(marker, distance);
      cv::Mat image = camera_->render(position, attitude), noise(image.size(), CV_16SC3);
      rng.fill(noise, cv::RNG::NORMAL, 0, 6);
      cv::Mat noisy;
      image.convertTo(noisy, CV_16SC3);
      noisy += noise;
      noisy.convertTo(image, CV_8UC3);
      cv::GaussianBlur(image, image, cv::Size(3, 3), 0.8);
      std::vector<uchar> jpeg;
      cv::imencode(".jpg", image, jpeg, {cv::IMWRITE_JPEG_QUALITY, 75});
      image = cv::imdecode(jpeg, cv::IMREAD_COLOR);
      const auto found = locator.locate(image, attitude, position);
      ASSERT_EQ(found.size(), 1u) << marker.name << " at " << distance << " m";
      EXPECT_EQ(found[0].text, marker.text);
      EXPECT_LT((found[0].position_world_m - marker.center_m).norm(), 0.1)
          << marker.name << " at " << distance << " m";
    }
  }
}

TEST_F(Aircraft, AnObliqueViewStillLocatesTheMarker) {
  const world::Marker& marker = world_->markers().front();
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

TEST(QrFinder, CornersFollowTheSymbolWhateverItsRotation) {
  // A 21-module code at 6 px per module (4-module quiet zone), rotated about
  // the canvas centre: corner 0 stays the symbol's own top-left.
  cv::Mat code;
  cv::QRCodeEncoder::create()->encode("ROTATION", code);
  cv::Mat symbol = code(cv::Rect(2, 2, code.cols - 4, code.rows - 4)), big;
  ASSERT_EQ(symbol.cols, 21);
  cv::resize(symbol, big, cv::Size(), 6, 6, cv::INTER_NEAREST);
  cv::Mat canvas(480, 640, CV_8UC1, cv::Scalar(255));
  const cv::Point2f origin(320 - 63, 240 - 63);  // the symbol's outer top-left edge
  big.copyTo(canvas(cv::Rect(static_cast<int>(origin.x), static_cast<int>(origin.y), 126, 126)));
  // Edges in pixel-centre coordinates: half a pixel before the first pixel.
  const std::array<cv::Point2f, 4> corners = {
      origin - cv::Point2f(0.5f, 0.5f), origin + cv::Point2f(125.5f, -0.5f),
      origin + cv::Point2f(125.5f, 125.5f), origin + cv::Point2f(-0.5f, 125.5f)};
  for (const double degrees : {0.0, 30.0, 90.0, 165.0, 180.0, 270.0, 315.0}) {
    const cv::Mat rotation = cv::getRotationMatrix2D({319.5f, 239.5f}, degrees, 1.0);
    cv::Mat rotated;
    cv::warpAffine(canvas, rotated, rotation, canvas.size(), cv::INTER_LINEAR, cv::BORDER_CONSTANT,
                   cv::Scalar(255));
    std::vector<cv::Point2f> expected;
    cv::transform(std::vector<cv::Point2f>(corners.begin(), corners.end()), expected, rotation);
    const auto quads = findQrSymbols(rotated);
    ASSERT_EQ(quads.size(), 1u) << degrees << " degrees";
    EXPECT_EQ(quads[0].modules, 21);
    for (size_t k = 0; k < 4; ++k) {
      EXPECT_LT(cv::norm(quads[0].corners[k] - expected[k]), 1.0)
          << "corner " << k << " at " << degrees << " degrees: " << quads[0].corners[k] << " vs "
          << expected[k];
    }
    MarkerLocator locator(CameraModel{}, 1.0);
    const auto decoded = locator.decode(rotated);
    ASSERT_EQ(decoded.size(), 1u) << degrees << " degrees";
    EXPECT_EQ(decoded[0].first, "ROTATION");
  }
}

TEST(QrFinder, NothingInAnEmptyOrWrongTypeImage) {
  EXPECT_TRUE(findQrSymbols(cv::Mat()).empty());
  EXPECT_TRUE(findQrSymbols(cv::Mat(480, 640, CV_8UC1, cv::Scalar(128))).empty());
  EXPECT_TRUE(findQrSymbols(cv::Mat(480, 640, CV_32FC1, cv::Scalar(0))).empty());
}

TEST(MarkerLocator, TheSymbolSideExcludesTheQuietZone) {
  MarkerLocator locator(CameraModel{}, 1.0);
  const double side = locator.symbolSideM("AC-001/FUSELAGE-LEFT");
  EXPECT_GT(side, 0.7);  // 21 modules + 8 of quiet zone -> 0.72 m
  EXPECT_LT(side, 1.0);
}

}  // namespace
}  // namespace behaviorlib::markers
