#pragma once

// QR symbol finder: the corners of every QR code in a grey image, from its
// three finder patterns (the nested 7-5-3 module squares), without decoding.
//
// Used instead of cv::QRCodeDetector, which on a 640x480 frame costs 6 to
// 12 ms (it upscales the frame to 512 rows and scans it line by line) where
// this costs about 2 ms: a local-mean threshold, one contour tree, finder
// patterns as contours with a grandchild of the expected area ratio, grouped
// in threes as right isosceles triangles. Each finder's edges are straight
// lines fitted to its contour (sub-pixel); the symbol's fourth corner is
// where the right edge of the top-right finder meets the bottom edge of the
// bottom-left one (exact under perspective for a flat code, no distortion).
//
//   for (const QrQuad& quad : findQrSymbols(gray)) ...  // TL, TR, BR, BL

#include <array>
#include <opencv2/core.hpp>
#include <vector>

namespace behaviorlib::markers {

/// Corners of one symbol (without its quiet zone), in the symbol's own
/// order: top-left, top-right, bottom-right, bottom-left. Pixel centres are
/// at integer coordinates.
struct QrQuad {
  std::array<cv::Point2f, 4> corners;
  /// Mean finder-pattern side (px): 7 modules.
  float finder_side_px = 0;
  /// Modules across the symbol (21 + 4 (version - 1)) as estimated from the
  /// finders' spacing; 0 when it could not be told.
  int modules = 0;
};

/// Every symbol whose three finder patterns are in view. `gray` is 8-bit,
/// one channel.
std::vector<QrQuad> findQrSymbols(const cv::Mat& gray);

}  // namespace behaviorlib::markers
