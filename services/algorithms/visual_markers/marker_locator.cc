#include "behaviorlib/visual_markers/marker_locator.h"

#include <algorithm>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/objdetect.hpp>
#include <opencv2/wechat_qrcode.hpp>

#include "behaviorlib/visual_markers/qr_finder.h"

namespace behaviorlib::markers {

struct MarkerLocator::Impl {
  cv::wechat_qrcode::WeChatQRCode decoder;
};

MarkerLocator::MarkerLocator(CameraModel camera, double marker_size_m)
    : camera_(std::move(camera)), marker_size_m_(marker_size_m), impl_(std::make_unique<Impl>()) {}

MarkerLocator::~MarkerLocator() = default;

double MarkerLocator::symbolSideM(const std::string& text) {
  auto it = modules_.find(text);
  if (it == modules_.end()) {
    int modules = 0;
    try {
      cv::Mat code;
      cv::QRCodeEncoder::create()->encode(text, code);
      modules = code.empty() ? 0 : code.cols - 4;  // the encoder adds a 2-module border
    } catch (const cv::Exception&) {
      modules = 0;
    }
    it = modules_.emplace(text, modules).first;
  }
  if (it->second <= 0) return marker_size_m_;
  return marker_size_m_ * it->second / (it->second + 8.0);
}

std::vector<std::pair<std::string, std::vector<cv::Point2f>>> MarkerLocator::decode(
    const cv::Mat& image) {
  std::vector<std::pair<std::string, std::vector<cv::Point2f>>> out;
  if (image.empty()) return out;
  cv::Mat gray;
  if (image.channels() == 3) {
    cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  } else {
    gray = image;
  }
  // Codes are located by their finder patterns (qr_finder.h); each is warped
  // upright and decoded alone by WeChatQRCode. Without its CNN models (not
  // packaged) WeChatQRCode treats its input as one candidate: given a whole
  // frame it decodes at most one code and cannot say where it is; given a
  // crop of the frame it tries scales and binarisers for ~20 ms. (Debian's
  // OpenCV has no quirc, so cv::QRCodeDetector cannot decode.)
  for (const QrQuad& quad : findQrSymbols(gray)) {
    std::vector<cv::Point2f> corners(quad.corners.begin(), quad.corners.end());
    // The symbol warped upright onto a white square of 4 px per module with
    // its 4-module quiet zone: clean input whatever the view.
    const float span_px =
        static_cast<float>(cv::norm(corners[1] - corners[0]) + cv::norm(corners[3] - corners[0]));
    const float modules =
        quad.modules > 0
            ? static_cast<float>(quad.modules)
            : std::clamp(std::round(3.5f * span_px / quad.finder_side_px), 21.0f, 177.0f);
    constexpr float kModulePx = 4.0f;
    const float lo = 4 * kModulePx - 0.5f, hi = (4 + modules) * kModulePx - 0.5f;
    const std::vector<cv::Point2f> upright = {{lo, lo}, {hi, lo}, {hi, hi}, {lo, hi}};
    const int side = static_cast<int>((modules + 8) * kModulePx);
    cv::Mat symbol;
    cv::warpPerspective(gray, symbol, cv::getPerspectiveTransform(corners, upright),
                        cv::Size(side, side), cv::INTER_LINEAR, cv::BORDER_CONSTANT,
                        cv::Scalar(255));
    std::vector<std::string> found;
    try {
      found = impl_->decoder.detectAndDecode(symbol);
    } catch (const cv::Exception&) {
      continue;
    }
    if (found.empty() || found.front().empty()) continue;
    out.emplace_back(found.front(), std::move(corners));
  }
  return out;
}

std::vector<LocatedMarker> MarkerLocator::locate(const cv::Mat& image,
                                                 const Eigen::Quaterniond& world_from_body,
                                                 const Eigen::Vector3d& body_position_m) {
  std::vector<LocatedMarker> located;
  const cv::Matx33d K(camera_.fx_px, 0, camera_.cx_px, 0, camera_.fy_px, camera_.cy_px, 0, 0, 1);
  for (const auto& [text, quad] : decode(image)) {
    const double h = 0.5 * symbolSideM(text);
    // IPPE_SQUARE's order: top-left, top-right, bottom-right, bottom-left
    // (the order of the detector's corners).
    const std::vector<cv::Point3f> object = {{static_cast<float>(-h), static_cast<float>(h), 0},
                                             {static_cast<float>(h), static_cast<float>(h), 0},
                                             {static_cast<float>(h), static_cast<float>(-h), 0},
                                             {static_cast<float>(-h), static_cast<float>(-h), 0}};
    cv::Vec3d rvec, tvec;
    bool ok = false;
    try {
      ok =
          cv::solvePnP(object, quad, K, cv::noArray(), rvec, tvec, false, cv::SOLVEPNP_IPPE_SQUARE);
    } catch (const cv::Exception&) {
      ok = false;
    }
    if (!ok || !std::isfinite(tvec[2]) || tvec[2] <= 0) continue;
    std::vector<cv::Point2f> reprojected;
    cv::projectPoints(object, rvec, tvec, K, cv::noArray(), reprojected);
    double error = 0;
    for (int i = 0; i < 4; ++i) error += cv::norm(reprojected[i] - quad[i]);

    LocatedMarker m;
    m.text = text;
    for (const auto& c : quad) m.center_px += Eigen::Vector2d(c.x, c.y) / 4.0;
    m.position_optical_m = {tvec[0], tvec[1], tvec[2]};
    m.range_m = m.position_optical_m.norm();
    const Eigen::Vector3d in_body =
        camera_.position_in_body_m + camera_.body_from_optical * m.position_optical_m;
    m.position_world_m = body_position_m + world_from_body * in_body;
    m.reprojection_error_px = error / 4.0;
    located.push_back(m);
  }
  return located;
}

}  // namespace behaviorlib::markers
