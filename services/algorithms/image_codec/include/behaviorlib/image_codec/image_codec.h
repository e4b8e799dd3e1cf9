#pragma once

// Image codec: JPEG with libjpeg-turbo's TurboJPEG API and PNG with libpng's
// simplified API, on 8-bit cv::Mat images (BGR or grey). It replaces OpenCV's
// imgcodecs, whose Debian package pulls GDAL, GDCM, OpenEXR and Poppler into
// every image that runs our programs (~150 MB) where the camera images need
// only JPEG and PNG.
//
//   absl::StatusOr<std::string> jpeg = encodeJpeg(bgr, 90);
//   absl::StatusOr<std::string> png = encodePng(bgr);        // lossless, fast
//   absl::StatusOr<cv::Mat> image = decodeToBgr(*jpeg);      // CV_8UC3
//   absl::StatusOr<cv::Mat> gray = decodeToGray(bytes);      // CV_8UC1
//
// Decoding takes bytes from outside (the channel, a file) and is safe on
// hostile input: the format is told by the data's signature, not by what the
// sender claims; the header's size is checked against DecodeLimits before
// any pixel memory is allocated; a JPEG that libjpeg warns about (truncated
// or corrupt data) is refused rather than padded with grey, and progressive
// JPEGs are limited in their number of scans. Every refusal is
// kInvalidArgument with a message that says why (the library's own message
// included). PNG images with an alpha channel are composited on black; 16-bit
// PNGs come back as 8-bit; colour JPEGs decode to grey from their luma.
//
// Every function is thread-safe (each call has its own codec state).

#include <cstddef>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace behaviorlib::image_codec {

enum class ImageFormat { kJpeg, kPng };

/// "jpeg" or "png".
std::string_view formatName(ImageFormat format);

/// The format of encoded data from its signature (JPEG: FF D8 FF; PNG: the
/// 8-byte PNG signature), or nullopt for anything else.
std::optional<ImageFormat> sniffFormat(std::string_view data);

/// What decoding accepts. The defaults fit any camera image and keep a
/// forged header from allocating more than 64 MiB.
struct DecodeLimits {
  /// Largest accepted width and height.
  int max_side_px = 16384;
  /// Largest decoded image: width x height x channels of the output (or of
  /// a JPEG's components, where it has more).
  std::size_t max_decoded_bytes = std::size_t{64} << 20;
};

/// JPEG of an 8-bit BGR (CV_8UC3) or grey (CV_8UC1) image, 4:2:0 chroma
/// subsampling for colour. `quality` is 1..100 (kInvalidArgument otherwise,
/// and for an empty image or another type).
absl::StatusOr<std::string> encodeJpeg(const cv::Mat& image, int quality = 90);

/// PNG of an 8-bit BGR (CV_8UC3) or grey (CV_8UC1) image, compressed for
/// speed (no filters, zlib level 3: live streams) rather than size.
absl::StatusOr<std::string> encodePng(const cv::Mat& image);

/// A JPEG or PNG image as 8-bit BGR (CV_8UC3); grey images are expanded.
absl::StatusOr<cv::Mat> decodeToBgr(std::string_view data, const DecodeLimits& limits = {});

/// A JPEG or PNG image as 8-bit grey (CV_8UC1); colour images are reduced to
/// their luminance.
absl::StatusOr<cv::Mat> decodeToGray(std::string_view data, const DecodeLimits& limits = {});

}  // namespace behaviorlib::image_codec
