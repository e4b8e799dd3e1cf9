#include "simulator/world/camera.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <opencv2/objdetect.hpp>
#include <opencv2/wechat_qrcode.hpp>

#include "behaviorlib/image_codec/image_codec.h"
#include "formats/world/str_cat.h"

namespace behaviorlib::sim {
namespace {

using world::internal::strCat;

/// Quiet zone around a QR code, in modules (the QR standard asks for 4).
constexpr int kQuietZoneModules = 4;
/// Markers are drawn this far in front of their surface.
constexpr double kMarkerLift_m = 0.005;
/// Projected polygons are clipped to the image plus this margin.
constexpr double kClipMargin_px = 2.0;
/// Sub-pixel bits for cv::fillConvexPoly.
constexpr int kShift = 4;

/// A plane `a . p + b >= 0` in camera coordinates.
struct ClipPlane {
  Eigen::Vector3d a;
  double b;
};

std::vector<Eigen::Vector3d> clip(std::vector<Eigen::Vector3d> polygon,
                                  const std::vector<ClipPlane>& planes) {
  std::vector<Eigen::Vector3d> out;
  for (const ClipPlane& plane : planes) {
    if (polygon.empty()) break;
    out.clear();
    for (std::size_t i = 0; i < polygon.size(); ++i) {
      const Eigen::Vector3d& p = polygon[i];
      const Eigen::Vector3d& q = polygon[(i + 1) % polygon.size()];
      const double fp = plane.a.dot(p) + plane.b;
      const double fq = plane.a.dot(q) + plane.b;
      if (fp >= 0.0) out.push_back(p);
      if ((fp >= 0.0) != (fq >= 0.0)) out.push_back(p + (q - p) * (fp / (fp - fq)));
    }
    polygon.swap(out);
  }
  return polygon;
}

cv::Scalar toBgr(world::Rgb color, double shade = 1.0) {
  return cv::Scalar(std::clamp(color.b * shade, 0.0, 255.0),
                    std::clamp(color.g * shade, 0.0, 255.0),
                    std::clamp(color.r * shade, 0.0, 255.0));
}

/// Flat shading from a fixed light high in the north-east.
double shadeFor(const Eigen::Vector3d& normal_world) {
  static const Eigen::Vector3d kLight = Eigen::Vector3d(0.32, 0.45, 0.83).normalized();
  return 0.55 + 0.45 * (0.5 + 0.5 * normal_world.dot(kLight));
}

/// The QR texture of `text` at `module_px` pixels per module and its
/// successive halvings down to about one pixel per module.
std::vector<cv::Mat> markerMips(const std::string& text, int module_px) {
  cv::Mat code;
  try {
    cv::Ptr<cv::QRCodeEncoder> encoder = cv::QRCodeEncoder::create();
    encoder->encode(text, code);
  } catch (const cv::Exception&) {
    return {};
  }
  if (code.empty()) return {};
  // The encoder leaves a 2-module border; widen it to the standard 4.
  cv::Mat bordered;
  cv::copyMakeBorder(code, bordered, kQuietZoneModules - 2, kQuietZoneModules - 2,
                     kQuietZoneModules - 2, kQuietZoneModules - 2, cv::BORDER_CONSTANT,
                     cv::Scalar(255));
  std::vector<cv::Mat> mips;
  cv::Mat level;
  cv::resize(bordered, level, cv::Size(), module_px, module_px, cv::INTER_NEAREST);
  mips.push_back(level);
  while (mips.back().cols / 2 >= bordered.cols) {
    cv::Mat half;
    cv::resize(mips.back(), half, cv::Size(mips.back().cols / 2, mips.back().rows / 2), 0, 0,
               cv::INTER_AREA);
    mips.push_back(half);
  }
  return mips;
}

/// Inverse depth 1/z over the image for the plane n . x = d (camera frame):
/// 1/z = A u + B v + C.
struct InverseDepth {
  double a, b, c;
};

InverseDepth inverseDepthOf(const Eigen::Vector3d& n, double d, double f, double cx, double cy) {
  return {n.x() / (f * d), n.y() / (f * d), (n.z() - n.x() * cx / f - n.y() * cy / f) / d};
}

/// The rendering state of one frame.
struct Frame {
  cv::Mat image;  ///< CV_8UC3
  cv::Mat depth;  ///< CV_32F inverse depth; 0 where only sky
  const cv::Mat* u_grid;
  const cv::Mat* v_grid;

  /// Inverse depth of a plane over `roi`, and the mask where it wins the
  /// depth test (inside `polygon_mask` if given).
  cv::Mat nearer(const InverseDepth& plane, const cv::Rect& roi, const cv::Mat& polygon_mask,
                 cv::Mat* inverse_depth) const {
    cv::addWeighted((*u_grid)(roi), plane.a, (*v_grid)(roi), plane.b, plane.c, *inverse_depth);
    cv::Mat mask;
    cv::compare(*inverse_depth, depth(roi), mask, cv::CMP_GT);
    if (!polygon_mask.empty()) cv::bitwise_and(mask, polygon_mask, mask);
    return mask;
  }

  void paint(const InverseDepth& plane, const cv::Rect& roi, const cv::Mat& polygon_mask,
             const cv::Scalar& color) {
    cv::Mat inverse_depth;
    const cv::Mat mask = nearer(plane, roi, polygon_mask, &inverse_depth);
    image(roi).setTo(color, mask);
    inverse_depth.copyTo(depth(roi), mask);
  }
};

}  // namespace

absl::Status CameraConfig::validate() const {
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError(strCat("camera: ", what));
  };
  if (width_px < 8 || width_px > 8192) return bad("width_px must be within 8..8192");
  if (height_px < 8 || height_px > 8192) return bad("height_px must be within 8..8192");
  if (!(horizontal_fov_rad > 0.0 && horizontal_fov_rad < 175.0 * std::numbers::pi / 180.0)) {
    return bad("horizontal_fov_rad must be within (0, 175 degrees)");
  }
  if (!(near_m > 0.0)) return bad("near_m must be positive");
  if (marker_module_px < 1 || marker_module_px > 32) {
    return bad("marker_module_px must be within 1..32");
  }
  if (!mount_position_m.allFinite() || !std::isfinite(mount_pitch_rad)) {
    return bad("the mounting must be finite");
  }
  return absl::OkStatus();
}

absl::StatusOr<Camera> Camera::create(const world::World& world, CameraConfig config) {
  if (absl::Status status = config.validate(); !status.ok()) return status;
  return Camera(world, std::move(config));
}

Camera::Camera(const world::World& world, CameraConfig config)
    : world_(&world), config_(std::move(config)) {
  focal_px_ = (config_.width_px / 2.0) / std::tan(config_.horizontal_fov_rad / 2.0);
  cx_ = (config_.width_px - 1) / 2.0;
  cy_ = (config_.height_px - 1) / 2.0;
  u_grid_.create(config_.height_px, config_.width_px, CV_32F);
  v_grid_.create(config_.height_px, config_.width_px, CV_32F);
  for (int v = 0; v < config_.height_px; ++v) {
    float* u_row = u_grid_.ptr<float>(v);
    float* v_row = v_grid_.ptr<float>(v);
    for (int u = 0; u < config_.width_px; ++u) {
      u_row[u] = static_cast<float>(u);
      v_row[u] = static_cast<float>(v);
    }
  }
  for (const world::Marker& marker : world_->markers()) {
    marker_mips_.push_back(markerMips(marker.text, config_.marker_module_px));
  }
}

Eigen::Isometry3d Camera::worldFromOptical(const Eigen::Vector3d& position_m,
                                           const Eigen::Quaterniond& world_from_body) const {
  Eigen::Matrix3d mount_from_optical;
  mount_from_optical << 0, 0, 1,  //
      -1, 0, 0,                   //
      0, -1, 0;
  const Eigen::Matrix3d body_from_mount =
      Eigen::AngleAxisd(config_.mount_pitch_rad, Eigen::Vector3d::UnitY()).toRotationMatrix();
  const Eigen::Matrix3d world_from_body_r = world_from_body.normalized().toRotationMatrix();
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() = world_from_body_r * body_from_mount * mount_from_optical;
  pose.translation() = position_m + world_from_body_r * config_.mount_position_m;
  return pose;
}

std::optional<Eigen::Vector2d> Camera::project(const Eigen::Vector3d& point_m,
                                               const Eigen::Vector3d& position_m,
                                               const Eigen::Quaterniond& world_from_body) const {
  const Eigen::Vector3d p = worldFromOptical(position_m, world_from_body).inverse() * point_m;
  if (p.z() < config_.near_m) return std::nullopt;
  return Eigen::Vector2d(cx_ + focal_px_ * p.x() / p.z(), cy_ + focal_px_ * p.y() / p.z());
}

cv::Mat Camera::render(const Eigen::Vector3d& position_m,
                       const Eigen::Quaterniond& world_from_body) const {
  const int width = config_.width_px;
  const int height = config_.height_px;
  const double f = focal_px_;
  const Eigen::Isometry3d world_from_optical = worldFromOptical(position_m, world_from_body);
  const Eigen::Matrix3d optical_from_world = world_from_optical.linear().transpose();
  const Eigen::Vector3d eye = world_from_optical.translation();
  auto to_camera = [&](const Eigen::Vector3d& p) -> Eigen::Vector3d {
    return optical_from_world * (p - eye);
  };

  Frame frame;
  frame.image = cv::Mat(height, width, CV_8UC3, toBgr(world_->skyColor()));
  frame.depth = cv::Mat(height, width, CV_32F, cv::Scalar(0.0));
  frame.u_grid = &u_grid_;
  frame.v_grid = &v_grid_;
  const cv::Rect full(0, 0, width, height);

  // Infinite planes cover the part of the image where their inverse depth
  // is positive (in front of the camera).
  auto paint_plane = [&](const Eigen::Vector3d& normal_world, const Eigen::Vector3d& point_world,
                         const cv::Scalar& color) {
    double d = normal_world.dot(point_world - eye);
    // A camera on the plane (a landed vehicle's camera at z = 0) sees it as
    // if from just in front: the plane fills the image below its horizon.
    if (std::abs(d) < 1e-6) d = -1e-6;
    frame.paint(inverseDepthOf(optical_from_world * normal_world, d, f, cx_, cy_), full, cv::Mat(),
                color);
  };
  paint_plane(Eigen::Vector3d::UnitZ(), Eigen::Vector3d::Zero(), toBgr(world_->groundColor()));
  for (const world::Plane& plane : world_->planes()) {
    paint_plane(plane.normal, plane.point_m, toBgr(plane.color, shadeFor(plane.normal)));
  }

  // Clipping: near plane and the image borders (plus a margin).
  const double m = kClipMargin_px;
  const std::vector<ClipPlane> clip_planes = {
      {{0, 0, 1}, -config_.near_m},         {{f, 0, cx_ + m}, 0.0},
      {{-f, 0, width - 1 + m - cx_}, 0.0},  {{0, f, cy_ + m}, 0.0},
      {{0, -f, height - 1 + m - cy_}, 0.0},
  };

  /// Clips a convex polygon (camera frame) and returns its pixel bounding
  /// box and fixed-point vertices relative to it; false if nothing remains.
  auto rasterize = [&](const std::vector<Eigen::Vector3d>& polygon, cv::Rect* roi,
                       cv::Mat* mask) -> bool {
    const std::vector<Eigen::Vector3d> clipped = clip(polygon, clip_planes);
    if (clipped.size() < 3) return false;
    std::vector<Eigen::Vector2d> pixels;
    double u0 = 1e30, v0 = 1e30, u1 = -1e30, v1 = -1e30;
    for (const Eigen::Vector3d& p : clipped) {
      const Eigen::Vector2d px(cx_ + f * p.x() / p.z(), cy_ + f * p.y() / p.z());
      pixels.push_back(px);
      u0 = std::min(u0, px.x());
      u1 = std::max(u1, px.x());
      v0 = std::min(v0, px.y());
      v1 = std::max(v1, px.y());
    }
    const cv::Rect box(
        cv::Point(static_cast<int>(std::floor(u0)), static_cast<int>(std::floor(v0))),
        cv::Point(static_cast<int>(std::ceil(u1)) + 1, static_cast<int>(std::ceil(v1)) + 1));
    *roi = box & full;
    if (roi->empty()) return false;
    std::vector<cv::Point> points;
    for (const Eigen::Vector2d& px : pixels) {
      points.emplace_back(static_cast<int>(std::lround((px.x() - roi->x) * (1 << kShift))),
                          static_cast<int>(std::lround((px.y() - roi->y) * (1 << kShift))));
    }
    *mask = cv::Mat::zeros(roi->size(), CV_8U);
    cv::fillConvexPoly(*mask, points, cv::Scalar(255), cv::LINE_8, kShift);
    return true;
  };

  // Box faces facing the camera.
  for (const world::Box& box : world_->boxes()) {
    const Eigen::Matrix3d rotation =
        Eigen::AngleAxisd(box.yaw_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    const Eigen::Vector3d half = box.size_m / 2.0;
    for (int axis = 0; axis < 3; ++axis) {
      for (int sign = -1; sign <= 1; sign += 2) {
        const Eigen::Vector3d normal = rotation.col(axis) * sign;
        const Eigen::Vector3d face_center = box.center_m + normal * half[axis];
        const double d = normal.dot(face_center - eye);
        if (d >= -1e-9) continue;  // back face or edge-on
        const int a1 = (axis + 1) % 3;
        const int a2 = (axis + 2) % 3;
        const Eigen::Vector3d e1 = rotation.col(a1) * half[a1];
        const Eigen::Vector3d e2 = rotation.col(a2) * half[a2];
        const std::vector<Eigen::Vector3d> polygon = {
            to_camera(face_center + e1 + e2), to_camera(face_center - e1 + e2),
            to_camera(face_center - e1 - e2), to_camera(face_center + e1 - e2)};
        cv::Rect roi;
        cv::Mat mask;
        if (!rasterize(polygon, &roi, &mask)) continue;
        frame.paint(inverseDepthOf(optical_from_world * normal, d, f, cx_, cy_), roi, mask,
                    toBgr(box.color, shadeFor(normal)));
      }
    }
  }

  // Markers facing the camera.
  const std::vector<world::Marker>& markers = world_->markers();
  for (std::size_t i = 0; i < markers.size(); ++i) {
    const world::Marker& marker = markers[i];
    world::Marker lifted = marker;
    lifted.center_m += marker.normal * kMarkerLift_m;
    const double d = marker.normal.dot(lifted.center_m - eye);
    if (d >= -1e-9) continue;
    std::vector<Eigen::Vector3d> polygon;
    bool in_front = true;
    for (const Eigen::Vector3d& corner : lifted.corners()) {
      polygon.push_back(to_camera(corner));
      in_front = in_front && polygon.back().z() >= config_.near_m;
    }
    if (!in_front) continue;
    cv::Rect roi;
    cv::Mat mask;
    if (!rasterize(polygon, &roi, &mask)) continue;
    const InverseDepth plane = inverseDepthOf(optical_from_world * marker.normal, d, f, cx_, cy_);
    // (A marker added to the World after the Camera was made has no texture.)
    static const std::vector<cv::Mat> kNoTexture;
    const std::vector<cv::Mat>& mips = i < marker_mips_.size() ? marker_mips_[i] : kNoTexture;
    if (mips.empty()) {
      frame.paint(plane, roi, mask, cv::Scalar(255, 255, 255));
      continue;
    }
    // Projected corners relative to the ROI; the longest side picks the mip.
    std::vector<cv::Point2f> quad;
    double side_px = 0.0;
    for (std::size_t k = 0; k < polygon.size(); ++k) {
      const Eigen::Vector3d& p = polygon[k];
      quad.emplace_back(static_cast<float>(cx_ + f * p.x() / p.z() - roi.x),
                        static_cast<float>(cy_ + f * p.y() / p.z() - roi.y));
    }
    for (std::size_t k = 0; k < quad.size(); ++k) {
      const cv::Point2f edge = quad[(k + 1) % quad.size()] - quad[k];
      side_px = std::max(side_px, static_cast<double>(std::hypot(edge.x, edge.y)));
    }
    std::size_t level = 0;
    while (level + 1 < mips.size() && mips[level + 1].cols >= side_px) ++level;
    const cv::Mat& texture = mips[level];
    const float s = static_cast<float>(texture.cols);
    const std::vector<cv::Point2f> texture_corners = {
        {-0.5f, -0.5f}, {s - 0.5f, -0.5f}, {s - 0.5f, s - 0.5f}, {-0.5f, s - 0.5f}};
    const cv::Mat homography = cv::getPerspectiveTransform(texture_corners, quad);
    cv::Mat warped;
    cv::warpPerspective(texture, warped, homography, roi.size(), cv::INTER_LINEAR,
                        cv::BORDER_CONSTANT, cv::Scalar(255));
    cv::Mat inverse_depth;
    const cv::Mat visible = frame.nearer(plane, roi, mask, &inverse_depth);
    cv::Mat warped_bgr;
    cv::cvtColor(warped, warped_bgr, cv::COLOR_GRAY2BGR);
    warped_bgr.copyTo(frame.image(roi), visible);
    inverse_depth.copyTo(frame.depth(roi), visible);
  }
  return frame.image;
}

absl::StatusOr<std::string> encodeImage(const cv::Mat& bgr, std::string_view format,
                                        int jpeg_quality) {
  if (bgr.empty()) return absl::InvalidArgumentError("encodeImage: empty image");
  std::string lower(format);
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  absl::StatusOr<std::string> encoded;
  if (lower == "jpeg" || lower == "jpg") {
    encoded = image_codec::encodeJpeg(bgr, std::clamp(jpeg_quality, 1, 100));
  } else if (lower == "png") {
    encoded = image_codec::encodePng(bgr);  // fast; the stream is live
  } else {
    return absl::InvalidArgumentError(
        strCat("encodeImage: unknown format '", format, "' (use jpeg or png)"));
  }
  if (!encoded.ok()) {
    return absl::Status(encoded.status().code(),
                        strCat("encodeImage: ", encoded.status().message()));
  }
  return encoded;
}

std::vector<std::string> decodeQr(const cv::Mat& image) {
  if (image.empty()) return {};
  // Without model files WeChatQRCode uses its traditional (zxing) detector,
  // which treats the whole image as one candidate and so returns at most one
  // code. cv::QRCodeDetector::detectMulti finds further codes (OpenCV 4.6 on
  // Debian cannot decode them itself, lacking quirc); each region is then
  // decoded by WeChatQRCode on its own. Both are cheap to construct; new ones
  // per call keep this thread-safe.
  cv::wechat_qrcode::WeChatQRCode decoder;
  std::vector<std::string> texts = decoder.detectAndDecode(image);
  auto add = [&texts](const std::vector<std::string>& found) {
    for (const std::string& text : found) {
      if (std::find(texts.begin(), texts.end(), text) == texts.end()) texts.push_back(text);
    }
  };
  std::vector<cv::Point2f> corners;
  try {
    cv::QRCodeDetector detector;
    if (!detector.detectMulti(image, corners)) corners.clear();
  } catch (const cv::Exception&) {
    corners.clear();
  }
  const cv::Rect whole(0, 0, image.cols, image.rows);
  for (std::size_t i = 0; i + 3 < corners.size(); i += 4) {
    const std::vector<cv::Point2f> quad(corners.begin() + i, corners.begin() + i + 4);
    cv::Rect region = cv::boundingRect(quad);
    // Room for the quiet zone and some background around it.
    const int margin = std::max(region.width, region.height) / 2 + 4;
    region = cv::Rect(region.x - margin, region.y - margin, region.width + 2 * margin,
                      region.height + 2 * margin) &
             whole;
    if (region.width < 8 || region.height < 8) continue;
    add(decoder.detectAndDecode(image(region).clone()));
  }
  return texts;
}

}  // namespace behaviorlib::sim
