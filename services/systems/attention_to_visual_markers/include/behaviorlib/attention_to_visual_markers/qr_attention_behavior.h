#pragma once

// PAY_ATTENTION_TO_QR_CODES (recurrent): QR codes found in the camera
// images, located in the world, published once and remembered.
//
//   robots/{id}/camera/image            Image, latest only: decoded and located
//                                       by background jobs (inBackground); a
//                                       frame arriving while one is processed
//                                       replaces the waiting one (counted)
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

#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/attention_to_visual_markers/marker_map.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/attention_to_visual_markers.pb.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/attention_to_visual_markers.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::markers {

class QrAttentionBehavior final : public Behavior<v1::PayAttentionToQrCodesParameters,
                                                  config::v1::PayAttentionToQrCodesConfig> {
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
  absl::Status onConfigure(const config::v1::PayAttentionToQrCodesConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::PayAttentionToQrCodesParameters& new_parameters) override;

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

  // What the locating jobs own: the locator, the map of codes and what was
  // written to belief memory. One job runs at a time (the background
  // thread); the worker only hands the pointer on.
  struct Locating {
    std::unique_ptr<MarkerLocator> locator;
    MarkerMap map;
    std::map<std::string, Eigen::Vector3d> remembered;  // text -> position written
    uint64_t seq = 0;
  };
  struct Decoded {
    v1::Header header;
    absl::StatusOr<cv::Mat> pixels;
  };
  struct Located {
    uint64_t sightings = 0, rejected = 0, belief_errors = 0;
    std::string belief_error;  // the first
    size_t codes = 0;
    absl::Status publish_error;
  };

  void onImage(const v1::Image& image);
  void onPose(const v1::PoseStamped& pose);
  void onCameraInfo(const v1::CameraInfo& info);
  // Worker: starts the background decoding of `image`.
  void decode(const v1::Image& image);
  void onDecoded(const Decoded& decoded);
  // Worker: the image is done with; the waiting one (if any) is next.
  void nextImage();
  // Background jobs: read only `state`, their arguments and the
  // configuration.
  Located locate(Locating& state, const cv::Mat& pixels, const v1::Header& header,
                 const CameraModel& camera, const BodyPose& pose, const Settings& settings) const;
  absl::Status remember(Locating& state, const MarkerEstimate& estimate, double size_m,
                        bool list_changed) const;
  void stop();

  channel::ChannelClient* channel_;
  const server::BeliefClient* beliefs_;
  // Config (defaults: PayAttentionToQrCodesConfig).
  Duration pose_timeout_ = std::chrono::milliseconds(500);
  Duration pose_history_ = std::chrono::seconds(3);
  Duration pose_tolerance_ = std::chrono::milliseconds(100);
  double belief_refresh_m_ = 0.02;

  // Worker only: samples and job results arrive there (onWorker,
  // inBackground).
  bool running_ = false, decoding_ = false;
  bool busy_ = false;  // an image is in the background jobs
  Settings settings_;
  std::optional<v1::Image> pending_;
  std::optional<TimePoint> last_image_;  // behavior clock, at arrival
  std::optional<TimePoint> last_pose_stamp_;
  std::optional<CameraModel> camera_;
  PoseHistory poses_{std::chrono::seconds(3)};
  Counters counters_;
  size_t codes_ = 0;
  absl::Status publish_error_;
  std::shared_ptr<Locating> locating_;

  TimePoint activated_at_{};
  bool active_ = false;
  std::unique_ptr<channel::Subscription> image_sub_, pose_sub_, info_sub_;
};

}  // namespace behaviorlib::markers
