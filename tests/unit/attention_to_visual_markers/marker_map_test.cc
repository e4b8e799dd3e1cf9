#include "behaviorlib/attention_to_visual_markers/marker_map.h"

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

namespace behaviorlib::markers {
namespace {

using std::chrono::milliseconds;

TimePoint at(int ms) { return TimePoint(milliseconds(ms)); }

BodyPose pose(double x, double yaw) {
  BodyPose p;
  p.position_m = {x, 0, 1};
  p.world_from_body = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ());
  return p;
}

TEST(PoseHistoryTest, InterpolatesAtAStampBetweenSamples) {
  PoseHistory history(std::chrono::seconds(1));
  history.add(at(1000), pose(0.0, 0.0));
  history.add(at(1010), pose(1.0, 0.2));
  const auto p = history.at(at(1005), milliseconds(50));
  ASSERT_TRUE(p);
  EXPECT_NEAR(p->position_m.x(), 0.5, 1e-9);
  EXPECT_NEAR(Eigen::AngleAxisd(p->world_from_body).angle(), 0.1, 1e-9);
}

TEST(PoseHistoryTest, RefusesStampsOutsideTheHistory) {
  PoseHistory history(milliseconds(100));
  for (int t = 0; t <= 300; t += 10) history.add(at(t), pose(t / 100.0, 0));
  EXPECT_FALSE(history.at(at(100), milliseconds(50))) << "forgotten: older than the span";
  EXPECT_TRUE(history.at(at(330), milliseconds(50))) << "newest within the tolerance";
  EXPECT_FALSE(history.at(at(400), milliseconds(50)));
  history.add(at(250), pose(9, 0));  // out of order: ignored
  EXPECT_NEAR(history.at(at(300), milliseconds(0))->position_m.x(), 3.0, 1e-9);
}

TEST(MarkerMapTest, PublishesOnceAfterMinSightingsAndAveragesByRange) {
  MarkerMap map;
  EXPECT_FALSE(map.add("A", {1, 0, 0}, 1.0, at(0), 3));
  EXPECT_FALSE(map.add("A", {1, 0, 0}, 1.0, at(10), 3));
  auto third = map.add("A", {4, 0, 0}, 2.0, at(20), 3);
  ASSERT_TRUE(third);
  EXPECT_TRUE(third->first_time);
  // Weights 1, 1, 1/4: (1 + 1 + 1) / 2.25.
  EXPECT_NEAR(third->estimate.position_m.x(), 3.0 / 2.25, 1e-9);
  EXPECT_EQ(third->estimate.sightings, 3u);
  auto fourth = map.add("A", {1, 0, 0}, 1.0, at(30), 3);
  ASSERT_TRUE(fourth);
  EXPECT_FALSE(fourth->first_time);
  EXPECT_EQ(map.published(), std::vector<std::string>{"A"});
  EXPECT_EQ(fourth->estimate.first_seen, at(0));
  EXPECT_EQ(fourth->estimate.last_seen, at(30));
}

TEST(DecodeImageTest, MalformedImagesAreErrorsNotCrashes) {
  v1::Image image;
  EXPECT_FALSE(decodeImage(image).ok());
  image.set_encoding("jpeg");
  image.set_data("not a jpeg at all");
  EXPECT_EQ(decodeImage(image).status().code(), absl::StatusCode::kInvalidArgument);
  image.set_encoding("mono8");
  image.set_width_px(640);
  image.set_height_px(480);
  EXPECT_FALSE(decodeImage(image).ok()) << "too few bytes";
  image.set_encoding("yuv422");
  EXPECT_NE(decodeImage(image).status().message().find("yuv422"), std::string::npos);
}

TEST(DecodeImageTest, DecodesRawAndCompressed) {
  cv::Mat grey(4, 6, CV_8UC1, cv::Scalar(77));
  v1::Image raw;
  raw.set_encoding("mono8");
  raw.set_width_px(6);
  raw.set_height_px(4);
  raw.set_data(std::string(reinterpret_cast<const char*>(grey.data), 24));
  auto decoded = decodeImage(raw);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(decoded->at<uint8_t>(3, 5), 77);
  std::vector<uint8_t> png;
  ASSERT_TRUE(cv::imencode(".png", grey, png));
  v1::Image compressed;
  compressed.set_encoding("png");
  compressed.set_data(std::string(png.begin(), png.end()));
  decoded = decodeImage(compressed);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(decoded->cols, 6);
}

TEST(CameraModelTest, RejectsAnUnusableCameraInfo) {
  v1::CameraInfo info;
  EXPECT_FALSE(cameraModel(info).ok());
  info.set_width_px(640);
  info.set_height_px(480);
  info.set_fx_px(500);
  info.set_fy_px(500);
  info.mutable_pose_in_body()->mutable_orientation()->set_w(1);
  EXPECT_TRUE(cameraModel(info).ok());
  info.set_fx_px(-1);
  EXPECT_FALSE(cameraModel(info).ok());
}

TEST(BeliefKeySegmentTest, KeepsSlashesAndReplacesOtherCharacters) {
  EXPECT_EQ(beliefKeySegment("AC-001/NOSE"), "AC-001/NOSE");
  EXPECT_EQ(beliefKeySegment("a b:c"), "a_b_c");
  EXPECT_EQ(beliefKeySegment("/x//y/"), "_/x/_/y/_");
  EXPECT_EQ(beliefKeySegment(""), "_");
}

}  // namespace
}  // namespace behaviorlib::markers
