#pragma once

// Camera pixel formats converted to the frame layout every module uses (RgbdFrame: colour
// 8-bit BGR, depth uint16 millimetres with 0 = no depth).
//
// Buffers come straight from devices (V4L2 mmap buffers, OpenNI2 frames) and are treated as
// untrusted: every size is checked against the declared geometry and against limits before
// a byte is read, and a bad buffer is an error Status, never a crash.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include <opencv2/core/mat.hpp>

#include "libccmd/util/status.h"

namespace ccmd {

// Largest image side accepted from a device (8K); protects allocations sized from headers.
inline constexpr int kMaxImageSide = 8192;

// Geometry of one packed image plane as a driver describes it.
struct PlaneGeometry {
  int width = 0;
  int height = 0;
  int stride = 0;  // bytes from one row to the next (V4L2 bytesperline); >= width * bytes/pixel
};

// Checks sizes, stride and that `size` bytes cover every row of the plane.
Status CheckPlane(const PlaneGeometry& plane, int bytes_per_pixel, std::size_t size);

// YUYV 4:2:2 (V4L2_PIX_FMT_YUYV, OpenNI2 PIXEL_FORMAT_YUYV): Y0 U Y1 V per pixel pair,
// ITU-R BT.601 with limited ("studio") range, as UVC cameras deliver it. Width must be even.
Status ConvertYuyvToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                        cv::Mat* bgr);

// UYVY 4:2:2 (OpenNI2 PIXEL_FORMAT_YUV422): U Y0 V Y1.
Status ConvertUyvyToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                        cv::Mat* bgr);

// Packed RGB 8:8:8 (OpenNI2 PIXEL_FORMAT_RGB888, V4L2_PIX_FMT_RGB24).
Status ConvertRgb24ToBgr(const std::uint8_t* data, std::size_t size, const PlaneGeometry& plane,
                         cv::Mat* bgr);

// 16-bit depth (V4L2 Z16 as a RealSense exposes it, OpenNI2 DEPTH_1_MM / DEPTH_100_UM):
// little-endian units of `unit_m` metres, 0 = no depth. Values are converted to whole
// millimetres (rounded); depths that do not fit 16-bit millimetres become 0.
Status ConvertZ16ToMillimetres(const std::uint8_t* data, std::size_t size,
                               const PlaneGeometry& plane, double unit_m, cv::Mat* depth_mm);

// Motion-JPEG frames (V4L2_PIX_FMT_MJPEG) decoded with TurboJPEG. One decoder per stream:
// it keeps its TurboJPEG handle and is not thread-safe. Frames whose header size differs from
// the negotiated one are rejected (a corrupt header must not size an allocation), and so are
// truncated or damaged frames (TurboJPEG warnings), so the caller can drop them.
class MjpegDecoder {
 public:
  MjpegDecoder();
  ~MjpegDecoder();
  MjpegDecoder(const MjpegDecoder&) = delete;
  MjpegDecoder& operator=(const MjpegDecoder&) = delete;

  Status Decode(const std::uint8_t* data, std::size_t size, int expected_width, int expected_height,
                cv::Mat* bgr);

 private:
  Status DecodeOnce(const std::uint8_t* data, std::size_t size, int expected_width,
                    int expected_height, cv::Mat* bgr);
  void* handle_ = nullptr;  // tjhandle
};

// Colour larger than depth (1920x1080 colour with 640x480 depth, as in the paper's D435 set-up)
// is resampled to the depth resolution before it is coded; RgbdFrame allows larger colour,
// but every live source hands out frames with colour at the depth size. Area averaging when
// shrinking (no aliasing), bilinear when growing. Returns `bgr` itself if sizes match.
cv::Mat ResizeColorToDepth(const cv::Mat& bgr, const cv::Size& depth_size);

// FOURCC code as text ("YUYV", "MJPG", "Z16 "), for messages.
std::string FourccToString(std::uint32_t fourcc);

}  // namespace ccmd
