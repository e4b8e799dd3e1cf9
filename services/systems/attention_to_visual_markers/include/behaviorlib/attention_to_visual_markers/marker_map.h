#pragma once

// What PAY_ATTENTION_TO_QR_CODES builds on, without transport: the pose
// estimate's recent history (to place an image at its own stamp), the
// decoding of an Image message, and the map of codes found (sightings
// averaged, each code published once when it has enough of them).
//
//   PoseHistory poses(std::chrono::seconds(3));
//   poses.add(stamp, position, attitude);
//   if (auto pose = poses.at(image_stamp, std::chrono::milliseconds(100))) ...
//
//   MarkerMap map;
//   if (auto update = map.add(text, world_position, range, stamp, min_sightings)) {
//     if (update->first_time) publish(*update);
//   }

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <deque>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/v1/types.pb.h"
#include "behaviorlib/visual_markers/marker_locator.h"

namespace behaviorlib::markers {

/// A pose of the body in the world.
struct BodyPose {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  Eigen::Quaterniond world_from_body = Eigen::Quaterniond::Identity();
};

/// The last `span` of pose estimates, in stamp order. Not thread-safe.
class PoseHistory {
 public:
  explicit PoseHistory(Duration span) : span_(span) {}

  /// Adds a sample; one older than the newest is ignored (out of order).
  void add(TimePoint stamp, const BodyPose& pose);
  /// The pose at `stamp`: interpolated between the samples around it
  /// (linear position, slerp attitude), or the newest when `stamp` is at
  /// most `tolerance` after it. nullopt when `stamp` is outside the history.
  std::optional<BodyPose> at(TimePoint stamp, Duration tolerance) const;
  std::optional<TimePoint> newest() const;
  void clear() { samples_.clear(); }

 private:
  Duration span_;
  std::deque<std::pair<TimePoint, BodyPose>> samples_;
};

/// The camera model from a CameraInfo; INVALID_ARGUMENT for one that cannot
/// be used (sizes or focal lengths not positive, non-finite values).
absl::StatusOr<CameraModel> cameraModel(const v1::CameraInfo& info);

/// The pixels of an Image ("jpeg", "png", "bgr8", "mono8"; JPEG and PNG
/// decoded to grey by behaviorlib::image_codec, within its DecodeLimits);
/// INVALID_ARGUMENT saying what is wrong with a malformed one.
absl::StatusOr<cv::Mat> decodeImage(const v1::Image& image);

/// `marker` located with the locator's nominal size, for a marker of side
/// `marker_size_m` instead: its position along the camera ray scales with
/// the size; the world position follows from `camera` and `pose`.
LocatedMarker rescaled(const LocatedMarker& marker, double nominal_size_m, double marker_size_m,
                       const CameraModel& camera, const BodyPose& pose);

/// A code's estimate.
struct MarkerEstimate {
  std::string text;
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  unsigned sightings = 0;
  TimePoint first_seen{};
  TimePoint last_seen{};
  /// True once the code has been published (it had min_sightings).
  bool published = false;
};

/// The codes seen, their sightings averaged with weights 1 / range^2.
class MarkerMap {
 public:
  struct Update {
    MarkerEstimate estimate;
    /// This sighting made the code reach min_sightings: publish it.
    bool first_time = false;
  };
  /// Adds a sighting. Returns the code's estimate once it has
  /// `min_sightings` (nullopt before).
  std::optional<Update> add(const std::string& text, const Eigen::Vector3d& position_m,
                            double range_m, TimePoint stamp, unsigned min_sightings);
  const std::map<std::string, MarkerEstimate>& estimates() const { return estimates_; }
  /// Texts of the published codes, in publication order.
  const std::vector<std::string>& published() const { return published_; }
  void clear();

 private:
  struct Sums {
    Eigen::Vector3d weighted = Eigen::Vector3d::Zero();
    double weight = 0.0;
  };
  std::map<std::string, MarkerEstimate> estimates_;
  std::map<std::string, Sums> sums_;
  std::vector<std::string> published_;
};

/// `text` as a belief key segment: characters other than letters, digits,
/// '_', '-', '.' and '/' become '_', empty segments are filled with '_'.
std::string beliefKeySegment(const std::string& text);

}  // namespace behaviorlib::markers
