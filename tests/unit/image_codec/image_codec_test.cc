#include "behaviorlib/image_codec/image_codec.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cstdint>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <string>
#include <vector>

namespace behaviorlib::image_codec {
namespace {

using ::testing::HasSubstr;

/// A smooth BGR test card (gradients and flat blocks): what JPEG is for.
cv::Mat testCard(int width = 96, int height = 64) {
  cv::Mat bgr(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const bool block = (x / 16 + y / 16) % 2 == 0;
      bgr.at<cv::Vec3b>(y, x) =
          cv::Vec3b(static_cast<uint8_t>(255 * x / width), static_cast<uint8_t>(255 * y / height),
                    static_cast<uint8_t>(block ? 200 : 60));
    }
  }
  return bgr;
}

/// Uniform noise: the worst case for compression, exact only losslessly.
cv::Mat noise(int type, int width = 37, int height = 23) {
  cv::Mat image(height, width, type);
  cv::RNG rng(7);
  rng.fill(image, cv::RNG::UNIFORM, 0, 256);
  return image;
}

double meanAbsDiff(const cv::Mat& a, const cv::Mat& b) {
  return cv::norm(a, b, cv::NORM_L1) / static_cast<double>(a.total() * a.channels());
}

std::string asString(const std::vector<uint8_t>& bytes) {
  return std::string(bytes.begin(), bytes.end());
}

std::vector<uint8_t> asBytes(const std::string& data) {
  return std::vector<uint8_t>(data.begin(), data.end());
}

uint32_t crc32(const std::string& data, size_t begin, size_t end) {
  uint32_t crc = 0xFFFFFFFFu;
  for (size_t i = begin; i < end; ++i) {
    crc ^= static_cast<uint8_t>(data[i]);
    for (int bit = 0; bit < 8; ++bit) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
  }
  return ~crc;
}

void putBigEndian16(std::string& data, size_t at, uint16_t value) {
  data[at] = static_cast<char>(value >> 8);
  data[at + 1] = static_cast<char>(value & 0xFF);
}

void putBigEndian32(std::string& data, size_t at, uint32_t value) {
  for (int i = 0; i < 4; ++i) data[at + i] = static_cast<char>((value >> (24 - 8 * i)) & 0xFF);
}

/// A JPEG whose frame header (SOF0) claims `width` x `height`.
std::string jpegClaiming(uint16_t width, uint16_t height) {
  absl::StatusOr<std::string> jpeg = encodeJpeg(testCard(), 90);
  EXPECT_TRUE(jpeg.ok()) << jpeg.status();
  std::string data = jpeg.value_or("");
  const size_t sof = data.find("\xFF\xC0");
  EXPECT_NE(sof, std::string::npos) << "no baseline frame header";
  if (sof == std::string::npos) return data;
  // FF C0, length (2), precision (1), height (2), width (2).
  putBigEndian16(data, sof + 5, height);
  putBigEndian16(data, sof + 7, width);
  return data;
}

/// A PNG whose IHDR claims `width` x `height` (with a correct CRC).
std::string pngClaiming(uint32_t width, uint32_t height) {
  absl::StatusOr<std::string> png = encodePng(testCard());
  EXPECT_TRUE(png.ok()) << png.status();
  std::string data = png.value_or("");
  EXPECT_EQ(data.substr(12, 4), "IHDR");
  // Signature (8), length (4), "IHDR" (4), width (4), height (4), 5 more
  // bytes, CRC over type and data.
  putBigEndian32(data, 16, width);
  putBigEndian32(data, 20, height);
  putBigEndian32(data, 29, crc32(data, 12, 29));
  return data;
}

TEST(ImageCodecTest, JpegRoundTripsBgrWithinTolerance) {
  const cv::Mat bgr = testCard();
  absl::StatusOr<std::string> jpeg = encodeJpeg(bgr, 95);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  EXPECT_EQ(sniffFormat(*jpeg), ImageFormat::kJpeg);
  absl::StatusOr<cv::Mat> decoded = decodeToBgr(*jpeg);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_EQ(decoded->type(), CV_8UC3);
  ASSERT_EQ(decoded->size(), bgr.size());
  // The test card's hard colour edges cost 4:2:0 chroma subsampling about 3.4
  // grey levels on average (the same with OpenCV's encoder).
  EXPECT_LT(meanAbsDiff(*decoded, bgr), 5.0);
  // Lower quality: smaller, still close.
  absl::StatusOr<std::string> small = encodeJpeg(bgr, 30);
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_LT(small->size(), jpeg->size());
  absl::StatusOr<cv::Mat> rough = decodeToBgr(*small);
  ASSERT_TRUE(rough.ok()) << rough.status();
  EXPECT_LT(meanAbsDiff(*rough, bgr), 10.0);
}

TEST(ImageCodecTest, JpegRoundTripsGrayWithinTolerance) {
  cv::Mat gray(48, 80, CV_8UC1);
  for (int y = 0; y < gray.rows; ++y) {
    for (int x = 0; x < gray.cols; ++x) gray.at<uint8_t>(y, x) = static_cast<uint8_t>(3 * x + y);
  }
  absl::StatusOr<std::string> jpeg = encodeJpeg(gray, 95);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  absl::StatusOr<cv::Mat> decoded = decodeToGray(*jpeg);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_EQ(decoded->type(), CV_8UC1);
  ASSERT_EQ(decoded->size(), gray.size());
  EXPECT_LT(meanAbsDiff(*decoded, gray), 2.0);
  // A grey JPEG decodes to BGR with three equal channels.
  absl::StatusOr<cv::Mat> bgr = decodeToBgr(*jpeg);
  ASSERT_TRUE(bgr.ok()) << bgr.status();
  std::vector<cv::Mat> channels;
  cv::split(*bgr, channels);
  EXPECT_EQ(cv::norm(channels[0], *decoded, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(channels[2], *decoded, cv::NORM_INF), 0.0);
}

TEST(ImageCodecTest, PngRoundTripsExactly) {
  for (int type : {CV_8UC3, CV_8UC1}) {
    const cv::Mat image = noise(type);
    absl::StatusOr<std::string> png = encodePng(image);
    ASSERT_TRUE(png.ok()) << png.status();
    EXPECT_EQ(sniffFormat(*png), ImageFormat::kPng);
    absl::StatusOr<cv::Mat> decoded = type == CV_8UC3 ? decodeToBgr(*png) : decodeToGray(*png);
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    ASSERT_EQ(decoded->type(), type);
    ASSERT_EQ(decoded->size(), image.size());
    EXPECT_EQ(cv::norm(*decoded, image, cv::NORM_INF), 0.0) << cv::typeToString(type);
  }
}

TEST(ImageCodecTest, PngConvertsBetweenGrayAndBgr) {
  const cv::Mat gray = noise(CV_8UC1);
  absl::StatusOr<std::string> png = encodePng(gray);
  ASSERT_TRUE(png.ok()) << png.status();
  absl::StatusOr<cv::Mat> bgr = decodeToBgr(*png);
  ASSERT_TRUE(bgr.ok()) << bgr.status();
  std::vector<cv::Mat> channels;
  cv::split(*bgr, channels);
  for (const cv::Mat& channel : channels) EXPECT_EQ(cv::norm(channel, gray, cv::NORM_INF), 0.0);
  // A colour PNG whose pixels are all grey reduces to those grey levels.
  cv::Mat grey_bgr;
  cv::merge(std::vector<cv::Mat>{gray, gray, gray}, grey_bgr);
  absl::StatusOr<std::string> colour = encodePng(grey_bgr);
  ASSERT_TRUE(colour.ok()) << colour.status();
  absl::StatusOr<cv::Mat> back = decodeToGray(*colour);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_LE(cv::norm(*back, gray, cv::NORM_INF), 1.0);
}

TEST(ImageCodecTest, EncodesARegionOfALargerImage) {
  const cv::Mat whole = noise(CV_8UC3, 64, 40);
  const cv::Mat region = whole(cv::Rect(5, 3, 31, 17));
  ASSERT_FALSE(region.isContinuous());
  absl::StatusOr<std::string> png = encodePng(region);
  ASSERT_TRUE(png.ok()) << png.status();
  absl::StatusOr<cv::Mat> decoded = decodeToBgr(*png);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(cv::norm(*decoded, region, cv::NORM_INF), 0.0);
  absl::StatusOr<std::string> jpeg = encodeJpeg(testCard()(cv::Rect(8, 8, 40, 24)), 95);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  absl::StatusOr<cv::Mat> card = decodeToBgr(*jpeg);
  ASSERT_TRUE(card.ok()) << card.status();
  EXPECT_LT(meanAbsDiff(*card, testCard()(cv::Rect(8, 8, 40, 24))), 5.0);
}

// Agreement with OpenCV's imgcodecs, which the consumers used before.
TEST(ImageCodecTest, AgreesWithOpenCv) {
  const cv::Mat bgr = testCard();
  absl::StatusOr<std::string> png = encodePng(bgr);
  ASSERT_TRUE(png.ok()) << png.status();
  const cv::Mat by_opencv = cv::imdecode(asBytes(*png), cv::IMREAD_COLOR);
  EXPECT_EQ(cv::norm(by_opencv, bgr, cv::NORM_INF), 0.0);

  absl::StatusOr<std::string> jpeg = encodeJpeg(bgr, 90);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  const cv::Mat jpeg_by_opencv = cv::imdecode(asBytes(*jpeg), cv::IMREAD_COLOR);
  ASSERT_EQ(jpeg_by_opencv.size(), bgr.size());
  absl::StatusOr<cv::Mat> jpeg_by_us = decodeToBgr(*jpeg);
  ASSERT_TRUE(jpeg_by_us.ok()) << jpeg_by_us.status();
  EXPECT_LT(meanAbsDiff(*jpeg_by_us, jpeg_by_opencv), 1.0);

  std::vector<uint8_t> opencv_png;
  ASSERT_TRUE(cv::imencode(".png", bgr, opencv_png));
  absl::StatusOr<cv::Mat> decoded = decodeToBgr(asString(opencv_png));
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(cv::norm(*decoded, bgr, cv::NORM_INF), 0.0);
  std::vector<uint8_t> opencv_jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", bgr, opencv_jpeg, {cv::IMWRITE_JPEG_QUALITY, 95}));
  decoded = decodeToBgr(asString(opencv_jpeg));
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_LT(meanAbsDiff(*decoded, bgr), 5.0);
  const cv::Mat gray_by_opencv = cv::imdecode(opencv_jpeg, cv::IMREAD_GRAYSCALE);
  absl::StatusOr<cv::Mat> gray = decodeToGray(asString(opencv_jpeg));
  ASSERT_TRUE(gray.ok()) << gray.status();
  EXPECT_LE(cv::norm(*gray, gray_by_opencv, cv::NORM_INF), 2.0);
}

TEST(ImageCodecTest, PngWithAlphaIsCompositedOnBlack) {
  cv::Mat bgra(4, 4, CV_8UC4, cv::Scalar(10, 20, 30, 255));
  bgra.at<cv::Vec4b>(0, 0) = cv::Vec4b(200, 200, 200, 0);  // fully transparent
  std::vector<uint8_t> png;
  ASSERT_TRUE(cv::imencode(".png", bgra, png));
  absl::StatusOr<cv::Mat> bgr = decodeToBgr(asString(png));
  ASSERT_TRUE(bgr.ok()) << bgr.status();
  EXPECT_EQ(bgr->at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 0));
  EXPECT_EQ(bgr->at<cv::Vec3b>(3, 3), cv::Vec3b(10, 20, 30));
}

TEST(ImageCodecTest, RefusesWhatIsNotAnImage) {
  absl::StatusOr<cv::Mat> empty = decodeToBgr("");
  EXPECT_EQ(empty.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(empty.status().message()), HasSubstr("without data"));

  absl::StatusOr<cv::Mat> garbage = decodeToGray("not an image at all");
  EXPECT_EQ(garbage.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(garbage.status().message()), HasSubstr("neither JPEG nor PNG"));
  EXPECT_FALSE(sniffFormat("not an image at all").has_value());

  // The right signatures followed by garbage.
  absl::StatusOr<cv::Mat> fake_jpeg = decodeToBgr(std::string("\xFF\xD8\xFF\xE0garbage", 11));
  EXPECT_EQ(fake_jpeg.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(fake_jpeg.status().message()), HasSubstr("cannot decode the jpeg image"));
  absl::StatusOr<cv::Mat> fake_png =
      decodeToBgr(std::string("\x89PNG\r\n\x1A\n", 8) + "garbage garbage garbage");
  EXPECT_EQ(fake_png.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(fake_png.status().message()), HasSubstr("cannot decode the png image"));
}

TEST(ImageCodecTest, RefusesTruncatedImages) {
  absl::StatusOr<std::string> jpeg = encodeJpeg(testCard(), 90);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  absl::StatusOr<std::string> png = encodePng(noise(CV_8UC3));
  ASSERT_TRUE(png.ok()) << png.status();
  for (size_t keep : {size_t{3}, size_t{20}, jpeg->size() / 2, jpeg->size() - 2}) {
    absl::StatusOr<cv::Mat> decoded = decodeToBgr(jpeg->substr(0, keep));
    EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument) << keep;
    EXPECT_THAT(std::string(decoded.status().message()), HasSubstr("cannot decode the jpeg image"))
        << keep;
  }
  // Cut inside the image data (the last 20 bytes are the IDAT's checksums
  // and the 12-byte IEND chunk).
  for (size_t keep : {size_t{8}, size_t{33}, png->size() / 2, png->size() - 20}) {
    absl::StatusOr<cv::Mat> decoded = decodeToGray(png->substr(0, keep));
    EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument) << keep;
    EXPECT_THAT(std::string(decoded.status().message()), HasSubstr("cannot decode the png image"))
        << keep;
  }
  // Without only its IEND chunk a PNG still has all its pixels: it decodes.
  EXPECT_TRUE(decodeToGray(png->substr(0, png->size() - 12)).ok());
}

TEST(ImageCodecTest, RefusesOversizedHeadersBeforeDecoding) {
  for (const std::string& data : {jpegClaiming(20000, 20000), pngClaiming(20000, 20000)}) {
    absl::StatusOr<cv::Mat> decoded = decodeToBgr(data);
    EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(decoded.status().message()), HasSubstr("20000x20000"));
    EXPECT_THAT(std::string(decoded.status().message()),
                HasSubstr("larger than 16384 px per side"));
  }
  // Within the side limit, beyond the memory limit (12000 x 12000 x 3).
  for (const std::string& data : {jpegClaiming(12000, 12000), pngClaiming(12000, 12000)}) {
    absl::StatusOr<cv::Mat> decoded = decodeToBgr(data);
    EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(decoded.status().message()), HasSubstr("more than the limit"));
  }
  // A forged PNG of width 0 (libpng refuses it itself).
  EXPECT_EQ(decodeToBgr(pngClaiming(0, 10)).status().code(), absl::StatusCode::kInvalidArgument);
  // Custom limits.
  absl::StatusOr<std::string> png = encodePng(testCard(96, 64));
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_FALSE(decodeToGray(*png, DecodeLimits{.max_side_px = 64}).ok());
  EXPECT_TRUE(decodeToGray(*png, DecodeLimits{.max_side_px = 96}).ok());
  EXPECT_FALSE(decodeToGray(*png, DecodeLimits{.max_decoded_bytes = 96 * 64 - 1}).ok());
  EXPECT_TRUE(decodeToGray(*png, DecodeLimits{.max_decoded_bytes = 96 * 64}).ok());
}

TEST(ImageCodecTest, CorruptedImagesNeverCrash) {
  absl::StatusOr<std::string> jpeg = encodeJpeg(testCard(), 80);
  ASSERT_TRUE(jpeg.ok()) << jpeg.status();
  absl::StatusOr<std::string> png = encodePng(testCard());
  ASSERT_TRUE(png.ok()) << png.status();
  std::mt19937 rng(11);
  int refused = 0;
  for (const std::string* original : {&*jpeg, &*png}) {
    for (int i = 0; i < 300; ++i) {
      std::string data = *original;
      const int flips = 1 + static_cast<int>(rng() % 8);
      for (int f = 0; f < flips; ++f) {
        data[rng() % data.size()] = static_cast<char>(rng() & 0xFF);
      }
      absl::StatusOr<cv::Mat> decoded = i % 2 ? decodeToBgr(data) : decodeToGray(data);
      if (decoded.ok()) {
        EXPECT_FALSE(decoded->empty());
      } else {
        ++refused;
        EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument) << decoded.status();
      }
    }
  }
  EXPECT_GT(refused, 0);
}

TEST(ImageCodecTest, RefusesWhatItCannotEncode) {
  EXPECT_EQ(encodeJpeg(cv::Mat()).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(encodePng(cv::Mat()).status().code(), absl::StatusCode::kInvalidArgument);
  const cv::Mat deep(4, 4, CV_16UC1, cv::Scalar(1000));
  EXPECT_THAT(std::string(encodePng(deep).status().message()), HasSubstr("unsupported image type"));
  const cv::Mat bgra(4, 4, CV_8UC4, cv::Scalar(1, 2, 3, 4));
  EXPECT_EQ(encodeJpeg(bgra).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(encodeJpeg(testCard(), 0).status().message()),
              HasSubstr("outside 1..100"));
  EXPECT_FALSE(encodeJpeg(testCard(), 101).ok());
  EXPECT_TRUE(encodeJpeg(testCard(), 1).ok());
  EXPECT_TRUE(encodeJpeg(testCard(), 100).ok());
}

TEST(ImageCodecTest, NamesFormats) {
  EXPECT_EQ(formatName(ImageFormat::kJpeg), "jpeg");
  EXPECT_EQ(formatName(ImageFormat::kPng), "png");
}

}  // namespace
}  // namespace behaviorlib::image_codec
