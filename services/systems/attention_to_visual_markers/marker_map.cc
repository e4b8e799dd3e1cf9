#include "behaviorlib/attention_to_visual_markers/marker_map.h"

#include <cmath>

#include "behaviorlib/image_codec/image_codec.h"

namespace behaviorlib::markers {

void PoseHistory::add(TimePoint stamp, const BodyPose& pose) {
  if (!samples_.empty() && stamp <= samples_.back().first) return;
  samples_.emplace_back(stamp, pose);
  while (!samples_.empty() && samples_.back().first - samples_.front().first > span_) {
    samples_.pop_front();
  }
}

std::optional<TimePoint> PoseHistory::newest() const {
  if (samples_.empty()) return std::nullopt;
  return samples_.back().first;
}

std::optional<BodyPose> PoseHistory::at(TimePoint stamp, Duration tolerance) const {
  if (samples_.empty() || stamp < samples_.front().first) return std::nullopt;
  if (stamp >= samples_.back().first) {
    if (stamp - samples_.back().first > tolerance) return std::nullopt;
    return samples_.back().second;
  }
  for (size_t i = 1; i < samples_.size(); ++i) {
    const auto& [t1, p1] = samples_[i];
    if (t1 < stamp) continue;
    const auto& [t0, p0] = samples_[i - 1];
    const double span = std::chrono::duration<double>(t1 - t0).count();
    const double f = span > 0 ? std::chrono::duration<double>(stamp - t0).count() / span : 1.0;
    BodyPose out;
    out.position_m = p0.position_m + f * (p1.position_m - p0.position_m);
    out.world_from_body = p0.world_from_body.slerp(f, p1.world_from_body).normalized();
    return out;
  }
  return samples_.back().second;
}

absl::StatusOr<CameraModel> cameraModel(const v1::CameraInfo& info) {
  if (info.width_px() == 0 || info.height_px() == 0) {
    return absl::InvalidArgumentError("camera info without an image size");
  }
  for (double v : {info.fx_px(), info.fy_px()}) {
    if (!std::isfinite(v) || v <= 0) {
      return absl::InvalidArgumentError("camera info with a focal length that is not positive");
    }
  }
  const auto& p = info.pose_in_body().position_m();
  const auto& q = info.pose_in_body().orientation();
  const Eigen::Quaterniond rotation(q.w(), q.x(), q.y(), q.z());
  const Eigen::Vector3d position(p.x(), p.y(), p.z());
  if (!std::isfinite(info.cx_px()) || !std::isfinite(info.cy_px()) || !position.allFinite() ||
      !rotation.coeffs().allFinite() || rotation.norm() < 1e-6) {
    return absl::InvalidArgumentError(
        "camera info with a non-finite principal point or mounting pose");
  }
  CameraModel model;
  model.width_px = static_cast<int>(info.width_px());
  model.height_px = static_cast<int>(info.height_px());
  model.fx_px = info.fx_px();
  model.fy_px = info.fy_px();
  model.cx_px = info.cx_px();
  model.cy_px = info.cy_px();
  model.position_in_body_m = position;
  model.body_from_optical = rotation.normalized();
  return model;
}

absl::StatusOr<cv::Mat> decodeImage(const v1::Image& image) {
  const std::string& data = image.data();
  if (data.empty()) return absl::InvalidArgumentError("image without data");
  const std::string& encoding = image.encoding();
  if (encoding == "jpeg" || encoding == "png") {
    // The data's signature decides between JPEG and PNG; the codec refuses
    // garbage, truncated data and oversized headers with kInvalidArgument
    // and a message that names the format.
    return image_codec::decodeToGray(data);
  }
  if (encoding == "mono8" || encoding == "bgr8") {
    const int channels = encoding == "mono8" ? 1 : 3;
    const uint64_t width = image.width_px(), height = image.height_px();
    const uint64_t step = image.step_bytes() ? image.step_bytes() : width * channels;
    if (width == 0 || height == 0 || width > 16384 || height > 16384 || step < width * channels ||
        step * height > data.size()) {
      return absl::InvalidArgumentError(
          std::string("raw ") + encoding + " image of " + std::to_string(width) + "x" +
          std::to_string(height) + " with step " + std::to_string(step) + " does not fit its " +
          std::to_string(data.size()) + " bytes");
    }
    const cv::Mat view(static_cast<int>(height), static_cast<int>(width),
                       channels == 1 ? CV_8UC1 : CV_8UC3, const_cast<char*>(data.data()), step);
    return view.clone();
  }
  return absl::InvalidArgumentError("unknown image encoding '" + encoding +
                                    "' (expected jpeg, png, bgr8 or mono8)");
}

LocatedMarker rescaled(const LocatedMarker& marker, double nominal_size_m, double marker_size_m,
                       const CameraModel& camera, const BodyPose& pose) {
  LocatedMarker out = marker;
  const double scale = marker_size_m / nominal_size_m;
  out.position_optical_m = marker.position_optical_m * scale;
  out.range_m = marker.range_m * scale;
  const Eigen::Vector3d in_body =
      camera.position_in_body_m + camera.body_from_optical * out.position_optical_m;
  out.position_world_m = pose.position_m + pose.world_from_body * in_body;
  return out;
}

std::optional<MarkerMap::Update> MarkerMap::add(const std::string& text,
                                                const Eigen::Vector3d& position_m, double range_m,
                                                TimePoint stamp, unsigned min_sightings) {
  MarkerEstimate& e = estimates_[text];
  Sums& sums = sums_[text];
  if (e.sightings == 0) {
    e.text = text;
    e.first_seen = stamp;
  }
  const double weight = 1.0 / std::max(range_m * range_m, 1e-3);
  sums.weighted += weight * position_m;
  sums.weight += weight;
  e.position_m = sums.weighted / sums.weight;
  ++e.sightings;
  e.last_seen = stamp;
  if (e.sightings < std::max(min_sightings, 1u)) return std::nullopt;
  Update update{e, false};
  if (!e.published) {
    e.published = true;
    update.estimate.published = true;
    update.first_time = true;
    published_.push_back(text);
  }
  return update;
}

void MarkerMap::clear() {
  estimates_.clear();
  sums_.clear();
  published_.clear();
}

std::string beliefKeySegment(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '-' || c == '.' || c == '/';
    out.push_back(ok ? c : '_');
  }
  // No empty segment: "a//b", a leading or trailing '/'.
  std::string fixed;
  for (size_t i = 0; i < out.size(); ++i) {
    if (out[i] == '/' && (fixed.empty() || fixed.back() == '/')) fixed.push_back('_');
    fixed.push_back(out[i]);
  }
  if (fixed.empty() || fixed.back() == '/') fixed.push_back('_');
  return fixed;
}

}  // namespace behaviorlib::markers
