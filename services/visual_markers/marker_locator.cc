#include "visual_markers/marker_locator.h"

#include <algorithm>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/objdetect.hpp>
#include <opencv2/wechat_qrcode.hpp>

namespace behaviorlib::markers {

struct MarkerLocator::Impl {
  cv::QRCodeDetector detector;
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
  // WeChatQRCode decodes fast (~1.5 ms a frame) but, without its CNN models,
  // treats the whole image as one candidate: its corners are the image's,
  // and with several codes in view it may decode none. cv::QRCodeDetector
  // locates every code with the symbol's corners (top-left, top-right,
  // bottom-right, bottom-left) but cannot decode on Debian (no quirc) and
  // costs ~12 ms (detectMulti). So: locate every code; one code that WeChat
  // decoded on the whole image is paired at once, otherwise each located
  // code is decoded from a crop around it.
  std::vector<std::string> texts;
  try {
    texts = impl_->decoder.detectAndDecode(gray);
  } catch (const cv::Exception&) {
    texts.clear();
  }
  texts.erase(std::remove(texts.begin(), texts.end(), std::string()), texts.end());

  // OpenCV 4.6's locator is fragile on crisp synthetic edges and on lone
  // codes: detectMulti on the image, then on a lightly blurred copy, then
  // (a code was decoded but not located) detect() on both.
  std::vector<cv::Point2f> corners;
  cv::Mat blurred;
  cv::GaussianBlur(gray, blurred, cv::Size(3, 3), 0);
  auto locate = [&](bool multi) {
    for (const cv::Mat* candidate : {&gray, &blurred}) {
      try {
        if (multi ? impl_->detector.detectMulti(*candidate, corners)
                  : impl_->detector.detect(*candidate, corners)) {
          return;
        }
      } catch (const cv::Exception&) {
      }
      corners.clear();
    }
  };
  locate(/*multi=*/true);
  if (corners.empty() && !texts.empty()) locate(/*multi=*/false);
  if (corners.size() == 4 && texts.size() == 1) {
    out.emplace_back(texts.front(), corners);
    return out;
  }
  const cv::Rect whole(0, 0, gray.cols, gray.rows);
  for (size_t i = 0; i + 3 < corners.size(); i += 4) {
    std::vector<cv::Point2f> quad(corners.begin() + static_cast<long>(i),
                                  corners.begin() + static_cast<long>(i) + 4);
    cv::Rect region = cv::boundingRect(quad);
    const int margin = std::max(region.width, region.height) / 4 + 4;
    region = cv::Rect(region.x - margin, region.y - margin, region.width + 2 * margin,
                      region.height + 2 * margin) &
             whole;
    if (region.area() <= 0) continue;
    std::vector<std::string> found;
    try {
      found = impl_->decoder.detectAndDecode(gray(region));
    } catch (const cv::Exception&) {
      continue;
    }
    if (found.empty() || found.front().empty()) continue;
    out.emplace_back(found.front(), std::move(quad));
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
