#pragma once

// The device layer under V4L2Source: one video capture node, memory-mapped streaming.
// The capture loop (v4l2_source.h) only talks to this interface; OpenLinuxV4l2Device() is the
// real one (ioctl/mmap/poll in v4l2_device_linux.cc), and tests substitute a fake.
//
// Error codes, which the capture loop and the retry wrapper rely on:
//   NotFound          no such node (nothing plugged in, wrong path)
//   PermissionDenied  the node exists but cannot be opened (not in the "video" group)
//   Unavailable       transient: device busy (another program streams from it), device
//                     unplugged mid-run (ENODEV), no frame within the timeout
//   Unsupported       the node is not a streaming capture device, or the format/size asked
//                     for is not offered
//   IoError           any other system-call failure

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

// FOURCC codes as V4L2 defines them (little-endian character order).
constexpr std::uint32_t MakeFourcc(char a, char b, char c, char d) {
  return static_cast<std::uint32_t>(static_cast<unsigned char>(a)) |
         (static_cast<std::uint32_t>(static_cast<unsigned char>(b)) << 8) |
         (static_cast<std::uint32_t>(static_cast<unsigned char>(c)) << 16) |
         (static_cast<std::uint32_t>(static_cast<unsigned char>(d)) << 24);
}
inline constexpr std::uint32_t kFourccYuyv = MakeFourcc('Y', 'U', 'Y', 'V');
inline constexpr std::uint32_t kFourccMjpeg = MakeFourcc('M', 'J', 'P', 'G');
inline constexpr std::uint32_t kFourccZ16 = MakeFourcc('Z', '1', '6', ' ');

// The format the driver agreed to (it may adjust what was asked for).
struct V4l2Format {
  std::uint32_t fourcc = 0;
  int width = 0;
  int height = 0;
  int stride = 0;              // bytesperline (0 for compressed formats)
  std::size_t image_size = 0;  // sizeimage: largest frame the driver will deliver
};

// One size of one pixel format, with its frame rates (empty if the driver does not say).
struct V4l2Mode {
  std::uint32_t fourcc = 0;
  std::string description;  // "YUYV 4:2:2", "Motion-JPEG", "Z16"
  int width = 0;
  int height = 0;
  std::vector<double> fps;
};

struct V4l2DeviceInfo {
  std::string path;
  std::string driver;              // "uvcvideo"
  std::string card;                // "Intel(R) RealSense(TM) Depth Camera 435: Depth"
  std::string bus;                 // "usb-0000:00:14.0-2"
  bool streaming_capture = false;  // a video capture node with streaming I/O
  std::vector<V4l2Mode> modes;
};

// A filled buffer, valid until it is given back with Requeue(index).
struct V4l2Buffer {
  int index = -1;
  const std::uint8_t* data = nullptr;
  std::size_t bytes_used = 0;
  double timestamp = 0;        // seconds, the driver's timestamp (CLOCK_MONOTONIC for UVC)
  std::uint32_t sequence = 0;  // driver frame counter (gaps = frames the driver dropped)
  bool error = false;          // V4L2_BUF_FLAG_ERROR: the data may be damaged
};

class V4l2Device {
 public:
  virtual ~V4l2Device() = default;

  // Capabilities and every (format, size, rate) the node offers.
  virtual StatusOr<V4l2DeviceInfo> Query() = 0;

  // VIDIOC_S_FMT. Unsupported if the driver substitutes another format or size.
  virtual StatusOr<V4l2Format> SetFormat(std::uint32_t fourcc, int width, int height) = 0;

  // VIDIOC_S_PARM; returns the rate the driver chose (0 if it cannot set one).
  virtual StatusOr<double> SetFrameRate(double fps) = 0;

  // Requests and maps `buffer_count` buffers, queues them all and starts streaming.
  virtual Status Start(int buffer_count) = 0;

  // Waits up to `timeout` seconds for a filled buffer.
  virtual StatusOr<V4l2Buffer> Dequeue(double timeout) = 0;

  // Gives a buffer back to the driver.
  virtual Status Requeue(int index) = 0;

  // Stops streaming, unmaps, closes. Safe to call twice; the destructor calls it.
  virtual void Close() = 0;
};

using V4l2DeviceOpener = std::function<StatusOr<std::unique_ptr<V4l2Device>>(const std::string&)>;

// The real device: open(2) on a /dev/video* node.
StatusOr<std::unique_ptr<V4l2Device>> OpenLinuxV4l2Device(const std::string& path);

// /dev/video* nodes present now, sorted by number.
std::vector<std::string> ListV4l2DeviceNodes();

}  // namespace ccmd
