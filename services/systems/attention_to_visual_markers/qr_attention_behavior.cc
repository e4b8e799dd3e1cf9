#include "behaviorlib/attention_to_visual_markers/qr_attention_behavior.h"

#include <google/protobuf/util/time_util.h>

#include <cmath>
#include <cstdio>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::markers {
namespace {

// The locator works with this size; estimates are rescaled to each code's.
constexpr double kNominalSizeM = 1.0;

std::string topic(const std::string& robot, const char* name) {
  return "robots/" + robot + "/" + name;
}

v1::Vector3 toVector(const Eigen::Vector3d& v) {
  v1::Vector3 out;
  out.set_x(v.x());
  out.set_y(v.y());
  out.set_z(v.z());
  return out;
}

google::protobuf::Timestamp toStamp(TimePoint t) {
  return google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
      std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count());
}

BehaviorOptions attentionOptions() {
  BehaviorOptions o;
  o.frequency_hz = 10.0;
  // checkSituation reads the channel (two bounded reads).
  o.watchdog_timeout = std::chrono::seconds(2);
  return o;
}

std::string number(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%g", v);
  return text;
}

}  // namespace

QrAttentionBehavior::QrAttentionBehavior(channel::ChannelClient* channel,
                                         const server::BeliefClient* beliefs)
    : Behavior(attentionOptions()), channel_(channel), beliefs_(beliefs) {}

QrAttentionBehavior::~QrAttentionBehavior() { stop(); }

absl::Status QrAttentionBehavior::onConfigure(
    const config::v1::PayAttentionToQrCodesConfig& config) {
  pose_timeout_ = seconds(config.pose_timeout_s());
  pose_history_ = seconds(config.pose_history_s());
  pose_tolerance_ = seconds(config.pose_tolerance_s());
  belief_refresh_m_ = config.belief_refresh_m();
  return absl::OkStatus();
}

absl::StatusOr<QrAttentionBehavior::Settings> QrAttentionBehavior::settingsFrom(
    const v1::PayAttentionToQrCodesParameters& p) {
  Settings s;
  s.marker_size_m = p.marker_size_m();
  for (const auto& [text, size] : p.marker_sizes_m()) {
    if (!std::isfinite(size) || size < 0.01 || size > 10) {
      return absl::InvalidArgumentError("marker_sizes_m[\"" + text + "\"] is " + number(size) +
                                        ": a marker's side must be in [0.01, 10] m");
    }
    if (text.empty()) {
      return absl::InvalidArgumentError("marker_sizes_m has an empty text: name the code");
    }
    s.marker_sizes_m[text] = size;
  }
  s.min_sightings = static_cast<unsigned>(p.min_sightings());
  s.max_range_m = p.max_range_m();
  s.max_reprojection_error_px = p.max_reprojection_error_px();
  s.image_timeout = seconds(p.image_timeout_s());
  return s;
}

absl::Status QrAttentionBehavior::onActivate() {
  if (!channel_) return absl::FailedPreconditionError("no data channel");
  absl::StatusOr<Settings> settings = settingsFrom(parameters());
  if (!settings.ok()) return settings.status();
  stop();
  settings_ = std::move(*settings);
  pending_.reset();
  busy_ = false;
  last_image_.reset();
  last_pose_stamp_.reset();
  camera_.reset();
  poses_ = PoseHistory(pose_history_);
  counters_ = {};
  codes_ = 0;
  publish_error_ = absl::OkStatus();
  running_ = decoding_ = true;
  // A new map; a job of an earlier activation keeps its own.
  locating_ = std::make_shared<Locating>();
  activated_at_ = now();
  active_ = true;
  const std::string robot = robotId();
  info_sub_ = channel_->subscribeTyped<v1::CameraInfo>(
      topic(robot, "camera/info"), {.send_latest_first = true},
      onWorker<v1::CameraInfo>([this](const v1::CameraInfo& m) { onCameraInfo(m); },
                               Delivery::kLatest));
  // Every pose sample goes into the history: a queue.
  pose_sub_ = channel_->subscribeTyped<v1::PoseStamped>(
      flight::poseEstimateTopic(robot),
      {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 1000, .send_latest_first = true},
      onWorker<v1::PoseStamped>([this](const v1::PoseStamped& m) { onPose(m); }));
  image_sub_ = channel_->subscribeTyped<v1::Image>(
      topic(robot, "camera/image"), {.mode = v1::DELIVERY_MODE_LATEST},
      onWorker<v1::Image>([this](const v1::Image& m) { onImage(m); }, Delivery::kLatest));
  return absl::OkStatus();
}

void QrAttentionBehavior::stop() {
  running_ = false;
  image_sub_.reset();
  pose_sub_.reset();
  info_sub_.reset();
}

void QrAttentionBehavior::onDeactivate() {
  active_ = false;
  stop();
  std::fprintf(stderr,
               "PAY_ATTENTION_TO_QR_CODES: %llu images (%llu decoded, %llu malformed, %llu "
               "dropped, %llu without a pose), %llu sightings (%llu rejected), %zu codes\n",
               static_cast<unsigned long long>(counters_.images),
               static_cast<unsigned long long>(counters_.decoded),
               static_cast<unsigned long long>(counters_.malformed),
               static_cast<unsigned long long>(counters_.dropped),
               static_cast<unsigned long long>(counters_.without_pose),
               static_cast<unsigned long long>(counters_.sightings),
               static_cast<unsigned long long>(counters_.rejected), codes_);
}

void QrAttentionBehavior::onPause() { decoding_ = false; }

void QrAttentionBehavior::onResume() { decoding_ = true; }

absl::Status QrAttentionBehavior::onModify(
    const v1::PayAttentionToQrCodesParameters& new_parameters) {
  absl::StatusOr<Settings> settings = settingsFrom(new_parameters);
  if (!settings.ok()) return settings.status();
  settings_ = std::move(*settings);
  return absl::OkStatus();
}

void QrAttentionBehavior::onImage(const v1::Image& image) {
  if (!running_) return;
  last_image_ = now();
  ++counters_.images;
  if (!decoding_) return;
  if (busy_) {
    if (pending_) ++counters_.dropped;
    pending_ = image;
    return;
  }
  decode(image);
}

void QrAttentionBehavior::onPose(const v1::PoseStamped& pose) {
  const auto& p = pose.pose().position_m();
  const auto& q = pose.pose().orientation();
  BodyPose body;
  body.position_m = {p.x(), p.y(), p.z()};
  body.world_from_body = Eigen::Quaterniond(q.w(), q.x(), q.y(), q.z());
  if (!body.position_m.allFinite() || !body.world_from_body.coeffs().allFinite() ||
      body.world_from_body.norm() < 1e-6) {
    return;
  }
  body.world_from_body.normalize();
  const TimePoint stamp = flight::stampTime(pose.header());
  if (!running_) return;
  poses_.add(stamp, body);
  last_pose_stamp_ = stamp;
}

void QrAttentionBehavior::onCameraInfo(const v1::CameraInfo& info) {
  absl::StatusOr<CameraModel> model = cameraModel(info);
  if (!model.ok()) return;  // checkProcesses reports a camera without a model
  camera_ = *model;
}

void QrAttentionBehavior::decode(const v1::Image& image) {
  busy_ = true;
  // Decoded in the background; the pose is looked up once the pixels are
  // back, so that the estimate for the image's stamp has had time to come.
  inBackground<Decoded>(
      [image] {
        return Decoded{image.header(), decodeImage(image)};
      },
      [this](const Decoded& decoded) { onDecoded(decoded); });
}

void QrAttentionBehavior::onDecoded(const Decoded& decoded) {
  if (!decoded.pixels.ok()) {
    if (counters_.malformed++ == 0) {
      std::fprintf(stderr, "PAY_ATTENTION_TO_QR_CODES: skipping a malformed image: %s\n",
                   std::string(decoded.pixels.status().message()).c_str());
    }
    return nextImage();
  }
  ++counters_.decoded;
  const TimePoint stamp = flight::stampTime(decoded.header);
  const std::optional<BodyPose> pose = poses_.at(stamp, pose_tolerance_);
  if (!pose) ++counters_.without_pose;
  if (!camera_ || !pose) return nextImage();
  if (decoded.pixels->cols != camera_->width_px || decoded.pixels->rows != camera_->height_px) {
    ++counters_.malformed;
    return nextImage();
  }
  inBackground<Located>(
      [this, state = locating_, decoded, camera = *camera_, pose = *pose, settings = settings_] {
        return locate(*state, *decoded.pixels, decoded.header, camera, pose, settings);
      },
      [this](const Located& located) {
        counters_.sightings += located.sightings;
        counters_.rejected += located.rejected;
        if (located.belief_errors > 0 && counters_.belief_errors == 0) {
          std::fprintf(stderr, "PAY_ATTENTION_TO_QR_CODES: cannot write belief memory: %s\n",
                       located.belief_error.c_str());
        }
        counters_.belief_errors += located.belief_errors;
        codes_ = located.codes;
        if (!located.publish_error.ok() && publish_error_.ok()) {
          publish_error_ = located.publish_error;
        }
        nextImage();
      });
}

void QrAttentionBehavior::nextImage() {
  busy_ = false;
  if (!pending_ || !decoding_) return;
  const v1::Image image = std::move(*pending_);
  pending_.reset();
  decode(image);
}

QrAttentionBehavior::Located QrAttentionBehavior::locate(Locating& state, const cv::Mat& pixels,
                                                         const v1::Header& header,
                                                         const CameraModel& camera,
                                                         const BodyPose& pose,
                                                         const Settings& settings) const {
  Located result;
  const TimePoint stamp = flight::stampTime(header);
  if (!state.locator || state.locator->camera().fx_px != camera.fx_px ||
      state.locator->camera().fy_px != camera.fy_px ||
      state.locator->camera().cx_px != camera.cx_px ||
      state.locator->camera().cy_px != camera.cy_px ||
      !state.locator->camera().position_in_body_m.isApprox(camera.position_in_body_m) ||
      !state.locator->camera().body_from_optical.isApprox(camera.body_from_optical)) {
    state.locator = std::make_unique<MarkerLocator>(camera, kNominalSizeM);
  }
  v1::MarkerDetections detections;
  for (const LocatedMarker& nominal :
       state.locator->locate(pixels, pose.world_from_body, pose.position_m)) {
    auto it = settings.marker_sizes_m.find(nominal.text);
    const double size = it != settings.marker_sizes_m.end() ? it->second : settings.marker_size_m;
    const LocatedMarker m = rescaled(nominal, kNominalSizeM, size, camera, pose);
    const bool accepted = m.position_world_m.allFinite() && m.range_m <= settings.max_range_m &&
                          m.reprojection_error_px <= settings.max_reprojection_error_px;
    ++(accepted ? result.sightings : result.rejected);
    if (!accepted) continue;
    const auto update =
        state.map.add(m.text, m.position_world_m, m.range_m, stamp, settings.min_sightings);
    if (!update) continue;
    if (update->first_time) {
      v1::MarkerDetection* d = detections.add_detections();
      d->set_text(m.text);
      d->set_center_x_px(m.center_px.x());
      d->set_center_y_px(m.center_px.y());
      *d->mutable_pose()->mutable_position_m() = toVector(update->estimate.position_m);
      d->mutable_pose()->mutable_orientation()->set_w(1.0);
    }
    if (absl::Status s = remember(state, update->estimate, size, update->first_time); !s.ok()) {
      if (result.belief_errors++ == 0) result.belief_error = std::string(s.message());
    }
  }
  result.codes = state.map.published().size();
  if (detections.detections_size() == 0) return result;
  *detections.mutable_header() = header;
  detections.mutable_header()->set_frame_id("world");
  detections.mutable_header()->set_robot_id(robotId());
  detections.mutable_header()->set_seq(++state.seq);
  result.publish_error = channel_->publish(topic(robotId(), "markers/detections"), detections);
  return result;
}

absl::Status QrAttentionBehavior::remember(Locating& state, const MarkerEstimate& estimate,
                                           double size_m, bool list_changed) const {
  if (!beliefs_) return absl::OkStatus();
  auto known = state.remembered.find(estimate.text);
  if (!list_changed && known != state.remembered.end() &&
      (known->second - estimate.position_m).norm() < belief_refresh_m_) {
    return absl::OkStatus();
  }
  const std::string prefix = beliefKeySegment(robotId()) + "/markers";
  const std::string writer = robotId() + "/PAY_ATTENTION_TO_QR_CODES";
  v1::QrCodeBelief belief;
  belief.set_text(estimate.text);
  *belief.mutable_position_m() = toVector(estimate.position_m);
  belief.set_sightings(estimate.sightings);
  belief.set_marker_size_m(size_m);
  *belief.mutable_first_seen_time() = toStamp(estimate.first_seen);
  *belief.mutable_last_seen_time() = toStamp(estimate.last_seen);
  absl::Status status =
      beliefs_->writeMessage(prefix + "/" + beliefKeySegment(estimate.text), belief, writer)
          .status();
  if (status.ok() && (list_changed || known == state.remembered.end())) {
    v1::QrCodeList list;
    for (const std::string& text : state.map.published()) list.add_texts(text);
    list.set_count(static_cast<uint32_t>(list.texts_size()));
    status = beliefs_->writeMessage(prefix, list, writer).status();
  }
  if (!status.ok()) return status;  // retried with the next sighting
  state.remembered[estimate.text] = estimate.position_m;
  return absl::OkStatus();
}

Situation QrAttentionBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  const std::string info_topic = topic(robotId(), "camera/info");
  auto info = channel_->getLatest(info_topic, flight::kChannelReadTimeout);
  if (!info.ok()) {
    return Situation::infeasible(
        info.status().code() == absl::StatusCode::kNotFound
            ? v1::SITUATION_REASON_INPUT_MISSING
            : v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
        info.status().code() == absl::StatusCode::kNotFound
            ? "no camera info on " + info_topic + ": has the robot a camera (is it publishing)?"
            : "cannot read " + info_topic + " from the channel at " + channel_->address() + ": " +
                  std::string(info.status().message()));
  }
  v1::CameraInfo camera_info;
  if (!info->sample().UnpackTo(&camera_info)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_INVALID,
                                 info_topic + " does not carry a CameraInfo");
  }
  if (auto model = cameraModel(camera_info); !model.ok()) {
    return Situation::infeasible(
        v1::SITUATION_REASON_INPUT_INVALID,
        "unusable " + info_topic + ": " + std::string(model.status().message()));
  }
  const std::string pose_topic = flight::poseEstimateTopic(robotId());
  auto pose = channel_->getLatest(pose_topic, flight::kChannelReadTimeout);
  if (!pose.ok()) {
    return Situation::infeasible(
        pose.status().code() == absl::StatusCode::kNotFound
            ? v1::SITUATION_REASON_INPUT_MISSING
            : v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
        pose.status().code() == absl::StatusCode::kNotFound
            ? "no pose estimate on " + pose_topic +
                  ": activate a self-localization behavior (SELF_LOCALIZE_WITH_GROUND_TRUTH, ...)"
            : "cannot read " + pose_topic + " from the channel at " + channel_->address() + ": " +
                  std::string(pose.status().message()));
  }
  v1::PoseStamped estimate;
  if (!pose->sample().UnpackTo(&estimate)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_INVALID,
                                 pose_topic + " does not carry a PoseStamped");
  }
  // Before activation the channel read itself takes time: twice the limit.
  if (auto stale = flight::staleness([&] { return "the pose estimate on " + pose_topic; },
                                     estimate.header(), now(), 2 * pose_timeout_)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_STALE,
                                 *stale + ": is a self-localization behavior active?");
  }
  return Situation::ok();
}

Verdict QrAttentionBehavior::checkProcesses() {
  const TimePoint t = now();
  if (!publish_error_.ok()) {
    return Verdict::finish("cannot publish detections: " + std::string(publish_error_.message()));
  }
  const std::string robot = robotId();
  const TimePoint since_image = last_image_.value_or(activated_at_);
  if (t - since_image > settings_.image_timeout) {
    return Verdict::finish(std::string("no camera image on ") + topic(robot, "camera/image") +
                           " for " + flight::secondsText(t - since_image) +
                           " (limit image_timeout_s " +
                           flight::secondsText(settings_.image_timeout) + ")" +
                           (last_image_ ? ": the camera stopped" : ": is the camera on?"));
  }
  const TimePoint since_pose = last_pose_stamp_.value_or(activated_at_);
  if (t - since_pose > pose_timeout_) {
    return Verdict::finish("the pose estimate on " + flight::poseEstimateTopic(robot) +
                           (last_pose_stamp_
                                ? " is " + flight::secondsText(t - since_pose) + " old (limit " +
                                      flight::secondsText(pose_timeout_) + ")"
                                : std::string(" never arrived")) +
                           ": codes cannot be located without it");
  }
  if (last_image_ && !camera_ && t - activated_at_ > std::chrono::seconds(3)) {
    return Verdict::finish("images arrive but no usable camera info on " +
                           topic(robot, "camera/info") + ": codes cannot be located");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::markers
