#include "libccmd/sensors/pixel_formats.h"

#include <turbojpeg.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <opencv2/imgproc.hpp>

namespace ccmd {

Status CheckPlane(const PlaneGeometry& plane, int bytes_per_pixel, std::size_t size) {
  if (plane.width < 1 || plane.height < 1 || plane.width > kMaxImageSide ||
      plane.height > kMaxImageSide) {
    return OutOfRange("image size " + std::to_string(plane.width) + "x" +
                      std::to_string(plane.height) + " outside 1.." +
                      std::to_string(kMaxImageSide));
  }
  const std::size_t row_bytes = static_cast<std::size_t>(plane.width) * bytes_per_pixel;
  if (plane.stride < 0 || static_cast<std::size_t>(plane.stride) < row_bytes) {
    return Corrupt("row stride " + std::to_string(plane.stride) + " bytes is shorter than a row (" +
                   std::to_string(row_bytes) + " bytes)");
  }
  // The last row need not be padded to the stride.
  const std::size_t needed =
      static_cast<std::size_t>(plane.stride) * (plane.height - 1) + row_bytes;
  if (size < needed) {
    return Corrupt("frame of " + std::to_string(size) + " bytes is too short for " +
                   std::to_string(plane.width) + "x" + std::to_string(plane.height) + " (needs " +
                   std::to_string(needed) + ")");
  }
  return Status::Ok();
}

namespace {

// Wraps device memory without copying; the conversions below always write a new image.
cv::Mat WrapPlane(const std::uint8_t* data, const PlaneGeometry& plane, int type) {
  return cv::Mat(plane.height, plane.width, type, const_cast<std::uint8_t*>(data),
                 static_cast<std::size_t>(plane.stride));
}

Status ConvertYuv422(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                     int code, cv::Mat* bgr) {
  CCMD_RETURN_IF_ERROR(CheckPlane(plane, 2, size));
  if (plane.width % 2 != 0) {
    return Corrupt("4:2:2 image width " + std::to_string(plane.width) + " is odd");
  }
  cv::Mat converted;  // a fresh buffer: the caller may still hold the previous frame
  cv::cvtColor(WrapPlane(data, plane, CV_8UC2), converted, code);
  *bgr = converted;
  return Status::Ok();
}

}  // namespace

Status ConvertYuyvToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                        cv::Mat* bgr) {
  return ConvertYuv422(data, size, plane, cv::COLOR_YUV2BGR_YUYV, bgr);
}

Status ConvertUyvyToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                        cv::Mat* bgr) {
  return ConvertYuv422(data, size, plane, cv::COLOR_YUV2BGR_UYVY, bgr);
}

Status ConvertRgb24ToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                         cv::Mat* bgr) {
  CCMD_RETURN_IF_ERROR(CheckPlane(plane, 3, size));
  cv::Mat converted;
  cv::cvtColor(WrapPlane(data, plane, CV_8UC3), converted, cv::COLOR_RGB2BGR);
  *bgr = converted;
  return Status::Ok();
}

Status ConvertZ16ToMillimetres(const std::uint8_t* data, std::size_t size,
                               const PlaneGeometry& plane, double unit_m, cv::Mat* depth_mm) {
  CCMD_RETURN_IF_ERROR(CheckPlane(plane, 2, size));
  if (!(unit_m > 0) || unit_m > 1.0) {
    return InvalidArgument("depth unit " + std::to_string(unit_m) + " m is not in (0, 1]");
  }
  cv::Mat out(plane.height, plane.width, CV_16UC1);
  const double scale = unit_m * 1000.0;
  const bool identity = std::fabs(scale - 1.0) < 1e-12;
  for (int y = 0; y < plane.height; ++y) {
    const std::uint8_t* row = data + static_cast<std::size_t>(plane.stride) * y;
    std::uint16_t* dst = out.ptr<std::uint16_t>(y);
    for (int x = 0; x < plane.width; ++x) {
      // Explicit little-endian assembly: device buffers are little-endian whatever the host.
      const unsigned raw = row[2 * x] | (static_cast<unsigned>(row[2 * x + 1]) << 8);
      if (identity) {
        dst[x] = static_cast<std::uint16_t>(raw);
        continue;
      }
      const double mm = std::round(raw * scale);
      dst[x] = mm > 65535.0 ? 0 : static_cast<std::uint16_t>(mm);
    }
  }
  *depth_mm = out;
  return Status::Ok();
}

MjpegDecoder::MjpegDecoder() : handle_(tjInitDecompress()) {}

MjpegDecoder::~MjpegDecoder() {
  if (handle_ != nullptr) tjDestroy(static_cast<tjhandle>(handle_));
}

Status MjpegDecoder::Decode(const std::uint8_t* data, std::size_t size, int expected_width,
                            int expected_height, cv::Mat* bgr) {
  const Status status = DecodeOnce(data, size, expected_width, expected_height, bgr);
  if (!status.ok() && handle_ != nullptr) {
    // After some failures (a header cut before its scan) TurboJPEG 2.1 leaves the handle in
    // a state where the next, valid frame reads as 0x0; a fresh handle is cheap.
    tjDestroy(static_cast<tjhandle>(handle_));
    handle_ = tjInitDecompress();
  }
  return status;
}

Status MjpegDecoder::DecodeOnce(const std::uint8_t* data, std::size_t size, int expected_width,
                                int expected_height, cv::Mat* bgr) {
  if (handle_ == nullptr) return Internal("TurboJPEG decompressor could not be created");
  if (data == nullptr || size < 4) return Corrupt("MJPEG frame is empty");
  if (size > (1ull << 28)) return OutOfRange("MJPEG frame of " + std::to_string(size) + " bytes");
  tjhandle tj = static_cast<tjhandle>(handle_);
  int width = 0, height = 0, subsampling = 0, colorspace = 0;
  if (tjDecompressHeader3(tj, data, static_cast<unsigned long>(size), &width, &height, &subsampling,
                          &colorspace) != 0) {
    return Corrupt(std::string("MJPEG header: ") + tjGetErrorStr2(tj));
  }
  if (width != expected_width || height != expected_height) {
    return Corrupt("MJPEG frame is " + std::to_string(width) + "x" + std::to_string(height) +
                   ", the stream was set to " + std::to_string(expected_width) + "x" +
                   std::to_string(expected_height));
  }
  cv::Mat out(height, width, CV_8UC3);
  // STOPONWARNING: a truncated USB transfer decodes with a grey tail and only a warning;
  // such a frame must be dropped, not tracked.
  if (tjDecompress2(tj, data, static_cast<unsigned long>(size), out.data, width,
                    static_cast<int>(out.step[0]), height, TJPF_BGR, TJFLAG_STOPONWARNING) != 0) {
    return Corrupt(std::string("MJPEG frame: ") + tjGetErrorStr2(tj));
  }
  *bgr = out;
  return Status::Ok();
}

cv::Mat ResizeColorToDepth(const cv::Mat& bgr, const cv::Size& depth_size) {
  if (bgr.size() == depth_size || depth_size.width <= 0 || depth_size.height <= 0) return bgr;
  const bool shrinking = bgr.cols >= depth_size.width && bgr.rows >= depth_size.height;
  cv::Mat resized;
  cv::resize(bgr, resized, depth_size, 0, 0, shrinking ? cv::INTER_AREA : cv::INTER_LINEAR);
  return resized;
}

std::string FourccToString(std::uint32_t fourcc) {
  std::string text(4, ' ');
  for (int i = 0; i < 4; ++i) {
    const char c = static_cast<char>((fourcc >> (8 * i)) & 0xff);
    text[i] = (c >= 32 && c < 127) ? c : '?';
  }
  return text;
}

}  // namespace ccmd
