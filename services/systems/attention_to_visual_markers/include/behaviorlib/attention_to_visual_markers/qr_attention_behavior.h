#pragma once

// PAY_ATTENTION_TO_QR_CODES (recurrent): QR codes found in the camera
// images, located in the world, published once and remembered.
//
//   robots/{id}/camera/image            Image, latest only: decoded on a worker
//                                       thread; a frame arriving while one is
//                                       decoded replaces the waiting one (counted)
//   robots/{id}/camera/info             CameraInfo, the camera model
//   robots/{id}/self_localization/pose  PoseStamped, queued: the pose at each
//                                       image's stamp is interpolated
//   -> robots/{id}/markers/detections   MarkerDetections (frame "world"), each
//                                       code once, when it has min_sightings
//   -> belief memory (with --coordinator): "<id>/markers/<text>" QrCodeBelief,
//      rewritten as sightings refine it; "<id>/markers" QrCodeList
//
//   checkSituation  before: a data channel, camera info on it, and a fresh
//                   pose estimate
//   checkGoal       none (recurrent)
//   checkProcesses  no image for image_timeout_s, the pose estimate older
//                   than pose_timeout_s (behavior clock), or detections that
//                   cannot be published -> PROCESS_FAILURE
//
// Malformed images (undecodable, wrong sizes) are counted and skipped, as
// are frames without a pose estimate at their stamp. Belief-memory errors
// are logged and retried with the next sighting, never fatal (the data
// channel has the detections).
//
// Config (defaults): pose_timeout_s [0.5], pose_history_s [3],
// pose_tolerance_s [0.1] (how far an image may be newer than the newest
// pose), belief_refresh_m [0.02] (a remembered position is rewritten when
// the estimate moves this far).

#include <condition_variable>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "behaviorlib/attention_to_visual_markers/marker_map.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/attention_to_visual_markers.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::markers {

class QrAttentionBehavior final : public Behavior<v1::PayAttentionToQrCodesParameters> {
 public:
  /// `channel` may be null (the behavior is then infeasible); `beliefs` may
  /// be null (nothing is remembered).
  QrAttentionBehavior(channel::ChannelClient* channel, const server::BeliefClient* beliefs);
  ~QrAttentionBehavior() override;

  /// Counters of the current (or last) activation.
  struct Counters {
    uint64_t images = 0;
    uint64_t decoded = 0;
    uint64_t malformed = 0;
    uint64_t dropped = 0;  ///< replaced while waiting for the worker
    uint64_t without_pose = 0;
    uint64_t sightings = 0;
    uint64_t rejected = 0;  ///< too far, or a bad fit
    uint64_t belief_errors = 0;
  };

 protected:
  absl::Status onConfigure(const YAML::Node& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const google::protobuf::Message& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProcesses() override;

 private:
  struct Settings {
    double marker_size_m = 1.0;
    std::map<std::string, double> marker_sizes_m;
    unsigned min_sightings = 3;
    double max_range_m = 8.0;
    double max_reprojection_error_px = 3.0;
    Duration image_timeout = std::chrono::seconds(5);
  };
  static absl::StatusOr<Settings> settingsFrom(const v1::PayAttentionToQrCodesParameters& p);

  void onImage(const v1::Image& image);
  void onPose(const v1::PoseStamped& pose);
  void onCameraInfo(const v1::CameraInfo& info);
  void workerLoop();
  void process(const v1::Image& image);
  void remember(const MarkerEstimate& estimate, double size_m, bool list_changed);
  void stop();

  channel::ChannelClient* channel_;
  const server::BeliefClient* beliefs_;
  // Config.
  Duration pose_timeout_ = std::chrono::milliseconds(500);
  Duration pose_history_ = std::chrono::seconds(3);
  Duration pose_tolerance_ = std::chrono::milliseconds(100);
  double belief_refresh_m_ = 0.02;

  // Shared with the subscriptions' threads and the worker.
  std::mutex mutex_;
  std::condition_variable cv_;
  bool running_ = false, decoding_ = false;
  Settings settings_;
  std::optional<v1::Image> pending_;
  std::optional<TimePoint> last_image_;  // behavior clock, at arrival
  std::optional<TimePoint> last_pose_stamp_;
  std::optional<CameraModel> camera_;
  PoseHistory poses_{std::chrono::seconds(3)};
  Counters counters_;
  absl::Status publish_error_;

  // Worker only.
  std::unique_ptr<MarkerLocator> locator_;
  MarkerMap map_;
  std::map<std::string, Eigen::Vector3d> remembered_;  // text -> position written
  uint64_t seq_ = 0;

  TimePoint activated_at_{};
  bool active_ = false;
  std::thread worker_;
  std::unique_ptr<channel::Subscription> image_sub_, pose_sub_, info_sub_;
};

}  // namespace behaviorlib::markers
