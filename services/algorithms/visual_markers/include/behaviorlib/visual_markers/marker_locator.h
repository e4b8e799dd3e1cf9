#pragma once

// MarkerLocator: PAY_ATTENTION_TO_QR_CODES's perception. Finds the QR codes
// in a camera image, decodes them, and estimates each code's position in the
// world from its four corners (cv::solvePnP, IPPE for squares), the camera
// model and the vehicle's pose.
//
// Marker convention (the simulator's, and the usual one for printed
// markers): `marker_size_m` is the side of the printed square including the
// 4-module white quiet zone; the code itself is what OpenCV's QRCodeEncoder
// makes of the text with its default settings (the symbol's module count is
// found by encoding the decoded text again).
//
//   MarkerLocator locator(camera, 1.0);
//   for (const LocatedMarker& m : locator.locate(bgr, world_from_body, position)) ...
//
// Codes are located by their finder patterns (qr_finder.h, ~1 ms a frame)
// and decoded by OpenCV contrib's WeChatQRCode one at a time, each warped
// upright (~0.4 ms): Debian's OpenCV lacks quirc, so cv::QRCodeDetector
// cannot decode, and it took 6-12 ms a frame to locate. Not thread-safe (one
// locator per thread).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <map>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace behaviorlib::markers {

/// Pinhole camera and its mounting, as CameraInfo describes it.
struct CameraModel {
  int width_px = 640;
  int height_px = 480;
  double fx_px = 554.3, fy_px = 554.3;
  double cx_px = 319.5, cy_px = 239.5;
  /// Optical frame (x right, y down, z forward) in the body frame (FLU).
  Eigen::Vector3d position_in_body_m = Eigen::Vector3d::Zero();
  Eigen::Quaterniond body_from_optical = Eigen::Quaterniond(
      (Eigen::Matrix3d() << 0, 0, 1, -1, 0, 0, 0, -1, 0).finished());  ///< looking along body +x
};

struct LocatedMarker {
  std::string text;
  Eigen::Vector2d center_px = Eigen::Vector2d::Zero();
  /// Marker centre in the camera's optical frame and in the world.
  Eigen::Vector3d position_optical_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d position_world_m = Eigen::Vector3d::Zero();
  /// Distance from the camera (m).
  double range_m = 0.0;
  /// Mean reprojection error of the corners (px): large means a bad fit.
  double reprojection_error_px = 0.0;
};

class MarkerLocator {
 public:
  MarkerLocator(CameraModel camera, double marker_size_m);
  ~MarkerLocator();

  /// Codes found in `image` (BGR or grey) seen from the vehicle's pose.
  std::vector<LocatedMarker> locate(const cv::Mat& image, const Eigen::Quaterniond& world_from_body,
                                    const Eigen::Vector3d& body_position_m);
  /// Codes decoded in `image` with their corner quads (pixels), no pose.
  std::vector<std::pair<std::string, std::vector<cv::Point2f>>> decode(const cv::Mat& image);

  const CameraModel& camera() const { return camera_; }
  double markerSizeM() const { return marker_size_m_; }
  /// Side of the code's symbol (without quiet zone) for `text` (m).
  double symbolSideM(const std::string& text);

 private:
  struct Impl;
  CameraModel camera_;
  double marker_size_m_;
  std::map<std::string, int> modules_;  // text -> symbol modules
  std::unique_ptr<Impl> impl_;
};

}  // namespace behaviorlib::markers
