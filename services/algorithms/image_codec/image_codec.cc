#include "behaviorlib/image_codec/image_codec.h"

#include <png.h>
#include <turbojpeg.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <sstream>

#include "absl/status/status.h"

namespace behaviorlib::image_codec {
namespace {

constexpr unsigned char kJpegSignature[] = {0xFF, 0xD8, 0xFF};
constexpr unsigned char kPngSignature[] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};

/// Streams every argument into one string. (Debian's Abseil has its own
/// absl::string_view, so absl::StrCat does not take std::string_view.)
template <typename... Args>
std::string strCat(const Args&... args) {
  std::ostringstream out;
  (out << ... << args);
  return out.str();
}

struct TjDeleter {
  void operator()(void* handle) const { tjDestroy(handle); }
};
using TjHandle = std::unique_ptr<void, TjDeleter>;

/// OK for an 8-bit one- or three-channel image small enough for both
/// libraries (their sizes and strides are ints).
absl::Status checkEncodable(const cv::Mat& image, std::string_view function) {
  if (image.empty()) return absl::InvalidArgumentError(strCat(function, ": empty image"));
  if (image.type() != CV_8UC1 && image.type() != CV_8UC3) {
    return absl::InvalidArgumentError(strCat(function, ": unsupported image type ",
                                             cv::typeToString(image.type()),
                                             " (expected CV_8UC1 grey or CV_8UC3 BGR)"));
  }
  if (image.dims != 2 ||
      image.step[0] > static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    return absl::InvalidArgumentError(
        strCat(function, ": image of ", image.cols, "x", image.rows, " is too large to encode"));
  }
  return absl::OkStatus();
}

/// OK if an image of `width` x `height` x `channels` is within `limits`.
absl::Status checkDecodedSize(std::string_view format, long long width, long long height,
                              int channels, const DecodeLimits& limits) {
  if (width <= 0 || height <= 0) {
    return absl::InvalidArgumentError(strCat(
        "cannot decode the ", format, " image: its header gives a size of ", width, "x", height));
  }
  if (width > limits.max_side_px || height > limits.max_side_px) {
    return absl::InvalidArgumentError(strCat("refusing to decode a ", format, " image of ", width,
                                             "x", height, ": larger than ", limits.max_side_px,
                                             " px per side"));
  }
  // Both sides are at most max_side_px (an int): no overflow in 64 bits.
  const unsigned long long bytes = static_cast<unsigned long long>(width) *
                                   static_cast<unsigned long long>(height) *
                                   static_cast<unsigned long long>(channels);
  if (bytes > limits.max_decoded_bytes) {
    return absl::InvalidArgumentError(strCat(
        "refusing to decode a ", format, " image of ", width, "x", height, ": it would take ",
        bytes, " bytes, more than the limit of ", limits.max_decoded_bytes));
  }
  return absl::OkStatus();
}

absl::StatusOr<cv::Mat> decodeJpeg(std::string_view data, int channels,
                                   const DecodeLimits& limits) {
  const TjHandle handle(tjInitDecompress());
  if (handle == nullptr) {
    return absl::InternalError(strCat("cannot start the JPEG decoder: ", tjGetErrorStr2(nullptr)));
  }
  const auto* bytes = reinterpret_cast<const unsigned char*>(data.data());
  int width = 0;
  int height = 0;
  int subsampling = 0;
  int colorspace = 0;
  if (tjDecompressHeader3(handle.get(), bytes, data.size(), &width, &height, &subsampling,
                          &colorspace) != 0) {
    return absl::InvalidArgumentError(
        strCat("cannot decode the jpeg image: ", tjGetErrorStr2(handle.get())));
  }
  // A stream that ends before its frame header (or holds only tables) reads
  // as a size of 0 x 0.
  if (width <= 0 || height <= 0) {
    return absl::InvalidArgumentError(
        "cannot decode the jpeg image: the data ends before a frame header gives its size");
  }
  // libjpeg holds a progressive image's coefficients for every component in
  // memory: count the larger of the source's components and the output's.
  const int components = colorspace == TJCS_GRAY                              ? 1
                         : colorspace == TJCS_CMYK || colorspace == TJCS_YCCK ? 4
                                                                              : 3;
  if (absl::Status size =
          checkDecodedSize("jpeg", width, height, std::max(channels, components), limits);
      !size.ok()) {
    return size;
  }
  cv::Mat image(height, width, channels == 1 ? CV_8UC1 : CV_8UC3);
  // Warnings (truncated or corrupt data) stop decoding: such an image is
  // refused, not returned with grey where its data is missing.
  const int flags = TJFLAG_STOPONWARNING | TJFLAG_LIMITSCANS;
  if (tjDecompress2(handle.get(), bytes, data.size(), image.data, width,
                    static_cast<int>(image.step[0]), height, channels == 1 ? TJPF_GRAY : TJPF_BGR,
                    flags) != 0) {
    return absl::InvalidArgumentError(
        strCat("cannot decode the jpeg image: ", tjGetErrorStr2(handle.get())));
  }
  return image;
}

absl::StatusOr<cv::Mat> decodePng(std::string_view data, int channels, const DecodeLimits& limits) {
  png_image png;
  std::memset(&png, 0, sizeof(png));
  png.version = PNG_IMAGE_VERSION;
  if (png_image_begin_read_from_memory(&png, data.data(), data.size()) == 0) {
    // On failure libpng has freed its state already.
    return absl::InvalidArgumentError(strCat("cannot decode the png image: ", png.message));
  }
  if (absl::Status size = checkDecodedSize("png", png.width, png.height, channels, limits);
      !size.ok()) {
    png_image_free(&png);
    return size;
  }
  png.format = channels == 1 ? PNG_FORMAT_GRAY : PNG_FORMAT_BGR;
  cv::Mat image(static_cast<int>(png.height), static_cast<int>(png.width),
                channels == 1 ? CV_8UC1 : CV_8UC3);
  const png_color black = {0, 0, 0};
  // png_image_finish_read frees libpng's state, whether it succeeds or not.
  if (png_image_finish_read(&png, &black, image.data, static_cast<png_int_32>(image.step[0]),
                            nullptr) == 0) {
    return absl::InvalidArgumentError(strCat("cannot decode the png image: ", png.message));
  }
  return image;
}

absl::StatusOr<cv::Mat> decode(std::string_view data, int channels, const DecodeLimits& limits) {
  if (data.empty()) return absl::InvalidArgumentError("cannot decode an image without data");
  const std::optional<ImageFormat> format = sniffFormat(data);
  if (!format.has_value()) {
    std::ostringstream head;
    head << std::hex;
    for (std::size_t i = 0; i < data.size() && i < 4; ++i) {
      head << (i ? " " : "") << static_cast<int>(static_cast<unsigned char>(data[i]));
    }
    return absl::InvalidArgumentError(strCat("cannot decode the image: ", data.size(),
                                             " bytes that are neither JPEG nor PNG (they begin ",
                                             head.str(), ")"));
  }
  return *format == ImageFormat::kJpeg ? decodeJpeg(data, channels, limits)
                                       : decodePng(data, channels, limits);
}

}  // namespace

std::string_view formatName(ImageFormat format) {
  switch (format) {
    case ImageFormat::kJpeg:
      return "jpeg";
    case ImageFormat::kPng:
      return "png";
  }
  return "unknown";
}

std::optional<ImageFormat> sniffFormat(std::string_view data) {
  auto startsWith = [data](const unsigned char* signature, std::size_t size) {
    return data.size() >= size && std::memcmp(data.data(), signature, size) == 0;
  };
  if (startsWith(kJpegSignature, sizeof(kJpegSignature))) return ImageFormat::kJpeg;
  if (startsWith(kPngSignature, sizeof(kPngSignature))) return ImageFormat::kPng;
  return std::nullopt;
}

absl::StatusOr<std::string> encodeJpeg(const cv::Mat& image, int quality) {
  if (absl::Status ok = checkEncodable(image, "encodeJpeg"); !ok.ok()) return ok;
  if (quality < 1 || quality > 100) {
    return absl::InvalidArgumentError(
        strCat("encodeJpeg: quality ", quality, " is outside 1..100"));
  }
  const TjHandle handle(tjInitCompress());
  if (handle == nullptr) {
    return absl::InternalError(
        strCat("encodeJpeg: cannot start the JPEG encoder: ", tjGetErrorStr2(nullptr)));
  }
  const bool gray = image.channels() == 1;
  const int subsampling = gray ? TJSAMP_GRAY : TJSAMP_420;
  // tjBufSize is the worst case: compress straight into the string.
  const unsigned long capacity = tjBufSize(image.cols, image.rows, subsampling);
  if (capacity == static_cast<unsigned long>(-1)) {
    return absl::InvalidArgumentError(
        strCat("encodeJpeg: image of ", image.cols, "x", image.rows, " is too large for JPEG"));
  }
  std::string out(capacity, '\0');
  auto* buffer = reinterpret_cast<unsigned char*>(out.data());
  unsigned long size = capacity;
  if (tjCompress2(handle.get(), image.data, image.cols, static_cast<int>(image.step[0]), image.rows,
                  gray ? TJPF_GRAY : TJPF_BGR, &buffer, &size, subsampling, quality,
                  TJFLAG_NOREALLOC) != 0) {
    return absl::InternalError(strCat("encodeJpeg: ", tjGetErrorStr2(handle.get())));
  }
  out.resize(size);
  return out;
}

absl::StatusOr<std::string> encodePng(const cv::Mat& image) {
  if (absl::Status ok = checkEncodable(image, "encodePng"); !ok.ok()) return ok;
  png_image png;
  std::memset(&png, 0, sizeof(png));
  png.version = PNG_IMAGE_VERSION;
  png.width = static_cast<png_uint_32>(image.cols);
  png.height = static_cast<png_uint_32>(image.rows);
  png.format = image.channels() == 1 ? PNG_FORMAT_GRAY : PNG_FORMAT_BGR;
  png.flags = PNG_IMAGE_FLAG_FAST;  // the stream is live
  // The bound libpng gives for any compression: one pass, then shrink.
  png_alloc_size_t size = PNG_IMAGE_PNG_SIZE_MAX(png);
  std::string out(size, '\0');
  // For 8-bit samples the row stride (in components) is the step in bytes.
  if (png_image_write_to_memory(&png, out.data(), &size, /*convert_to_8_bit=*/0, image.data,
                                static_cast<png_int_32>(image.step[0]), nullptr) == 0) {
    return absl::InternalError(strCat("encodePng: ", png.message));
  }
  out.resize(size);
  return out;
}

absl::StatusOr<cv::Mat> decodeToBgr(std::string_view data, const DecodeLimits& limits) {
  return decode(data, 3, limits);
}

absl::StatusOr<cv::Mat> decodeToGray(std::string_view data, const DecodeLimits& limits) {
  return decode(data, 1, limits);
}

}  // namespace behaviorlib::image_codec
