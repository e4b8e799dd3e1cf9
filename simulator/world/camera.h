#pragma once

// Camera: a pinhole camera rendering a World with OpenCV — sky, ground,
// planes, shaded box faces and QR markers — plus image encoding and QR
// decoding helpers. Kept apart from world.h because OpenCV headers are slow
// to compile: only code that handles images includes this.
//
//   CameraConfig config;                        // 640 x 480, 60 degrees wide
//   absl::StatusOr<Camera> camera = Camera::create(world, config);
//   cv::Mat bgr = camera->render(position_m, world_from_body);
//   absl::StatusOr<std::string> jpeg = encodeImage(bgr, "jpeg");
//   for (const std::string& text : decodeQr(bgr)) { ... }
//
// Frames: the camera is mounted at `mount_position_m` in the body frame (FLU)
// looking along body +x, tilted down by `mount_pitch_rad` (a rotation about
// body +y). Its optical frame is OpenCV's: x right, y down, z forward (optical
// z = mount +x, optical x = mount -y, optical y = mount -z). Pixel (u, v) has
// u to the right and v down; pixel centres are at integer coordinates, the
// principal point is the image centre ((width - 1) / 2, (height - 1) / 2) and
// pixels are square (fx = fy).
//
// Rendering: a depth buffer of inverse depths (exact per pixel for planar
// faces), so overlapping boxes and markers are ordered correctly; faces are
// clipped at the near plane and flat-shaded from a fixed light. Markers are
// the QR image (4-module quiet zone) warped onto their quad with
// cv::warpPerspective from a precomputed mip chain; a marker with a corner
// behind the near plane is not drawn. render() is const and may run on
// several threads at once (while the World is not modified).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <numbers>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "formats/world/world.h"

namespace behaviorlib::sim {

struct CameraConfig {
  int width_px = 640;
  int height_px = 480;
  /// Full horizontal field of view; the vertical one follows from the aspect.
  double horizontal_fov_rad = std::numbers::pi / 3.0;
  /// Position of the camera in the body frame (FLU).
  Eigen::Vector3d mount_position_m = Eigen::Vector3d::Zero();
  /// Tilt below body +x; positive looks down.
  double mount_pitch_rad = 0.0;
  /// Nothing closer than this along the optical axis is drawn.
  double near_m = 0.05;
  /// Texture resolution of markers at the finest mip level.
  int marker_module_px = 8;

  /// OK, or kInvalidArgument naming the first bad field.
  absl::Status validate() const;
};

class Camera {
 public:
  /// `world` must outlive the Camera. Precomputes the marker textures.
  static absl::StatusOr<Camera> create(const world::World& world, CameraConfig config);

  const CameraConfig& config() const { return config_; }
  double focalLengthPx() const { return focal_px_; }
  double cx() const { return cx_; }
  double cy() const { return cy_; }

  /// Renders the view from the body pose (position in the world,
  /// orientation world <- body): a CV_8UC3 BGR image.
  cv::Mat render(const Eigen::Vector3d& position_m,
                 const Eigen::Quaterniond& world_from_body) const;

  /// Pose of the optical frame in the world (world <- optical).
  Eigen::Isometry3d worldFromOptical(const Eigen::Vector3d& position_m,
                                     const Eigen::Quaterniond& world_from_body) const;

  /// Pixel (u, v) of a world point, or nullopt if it is behind the near
  /// plane. The pixel may lie outside the image.
  std::optional<Eigen::Vector2d> project(const Eigen::Vector3d& point_m,
                                         const Eigen::Vector3d& position_m,
                                         const Eigen::Quaterniond& world_from_body) const;

 private:
  Camera(const world::World& world, CameraConfig config);

  const world::World* world_;
  CameraConfig config_;
  double focal_px_ = 0.0;
  double cx_ = 0.0;
  double cy_ = 0.0;
  cv::Mat u_grid_;  ///< CV_32F, u of each pixel
  cv::Mat v_grid_;  ///< CV_32F, v of each pixel
  /// Per marker, its texture (CV_8UC1) at decreasing resolutions; empty if
  /// the text could not be encoded (the marker is drawn plain white).
  std::vector<std::vector<cv::Mat>> marker_mips_;
};

/// Encodes a BGR (CV_8UC3) or grey (CV_8UC1) image as "jpeg" (or "jpg";
/// quality clamped to 1..100) or "png" (compressed for speed), with
/// behaviorlib::image_codec; kInvalidArgument for other formats, an empty
/// image or another image type.
absl::StatusOr<std::string> encodeImage(const cv::Mat& bgr, std::string_view format,
                                        int jpeg_quality = 90);

/// The distinct texts of the QR codes found in an image (BGR or grey):
/// OpenCV contrib's WeChatQRCode (without its CNN models) on the whole image,
/// plus on each further code located by cv::QRCodeDetector::detectMulti.
/// About 10 to 30 ms for 640 x 480. Thread-safe.
std::vector<std::string> decodeQr(const cv::Mat& image);

}  // namespace behaviorlib::sim
