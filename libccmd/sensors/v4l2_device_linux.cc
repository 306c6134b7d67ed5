// The real V4L2 device: kernel ioctls on a /dev/video* node, memory-mapped buffers and
// poll(2) with a timeout, so a camera that stops sending never blocks the caller forever.

#include <errno.h>
#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>

#include "libccmd/sensors/pixel_formats.h"
#include "libccmd/sensors/v4l2_device.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

// Bounds on what a driver may report, so a misbehaving one cannot make us loop for long.
constexpr int kMaxFormats = 64;
constexpr int kMaxSizes = 64;
constexpr int kMaxIntervals = 32;
constexpr int kMaxBuffers = 32;

int Xioctl(int fd, unsigned long request, void* arg) {
  int result;
  do {
    result = ioctl(fd, request, arg);
  } while (result == -1 && errno == EINTR);
  return result;
}

// Maps errno to the codes v4l2_device.h promises.
Status ErrnoStatus(const std::string& path, const std::string& what, int error) {
  const std::string message = path + ": " + what + ": " + std::strerror(error);
  switch (error) {
    case ENOENT:
      return NotFound(message + " (is the camera plugged in? ccmd_camera --list shows the nodes)");
    case ENODEV:
    case ENXIO:
      return Unavailable(message + " (camera unplugged?)");
    case EBUSY:
      return Unavailable(message + " (device busy: another program is using it)");
    case EACCES:
    case EPERM:
      return PermissionDenied(message + " (add your user to the 'video' group)");
    default:
      return IoError(message);
  }
}

std::string CString(const unsigned char* text, std::size_t size) {
  return std::string(reinterpret_cast<const char*>(text),
                     strnlen(reinterpret_cast<const char*>(text), size));
}

class LinuxV4l2Device : public V4l2Device {
 public:
  LinuxV4l2Device(std::string path, int fd) : path_(std::move(path)), fd_(fd) {}
  ~LinuxV4l2Device() override { Close(); }

  StatusOr<V4l2DeviceInfo> Query() override {
    if (fd_ < 0) return IoError(path_ + ": closed");
    v4l2_capability cap{};
    if (Xioctl(fd_, VIDIOC_QUERYCAP, &cap) != 0) {
      if (errno == ENOTTY || errno == EINVAL) return Unsupported(path_ + " is not a V4L2 device");
      return ErrnoStatus(path_, "VIDIOC_QUERYCAP", errno);
    }
    V4l2DeviceInfo info;
    info.path = path_;
    info.driver = CString(cap.driver, sizeof(cap.driver));
    info.card = CString(cap.card, sizeof(cap.card));
    info.bus = CString(cap.bus_info, sizeof(cap.bus_info));
    const std::uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    info.streaming_capture = (caps & V4L2_CAP_VIDEO_CAPTURE) && (caps & V4L2_CAP_STREAMING);
    if (!info.streaming_capture) return info;  // metadata nodes etc.: nothing to enumerate

    for (int f = 0; f < kMaxFormats; ++f) {
      v4l2_fmtdesc desc{};
      desc.index = f;
      desc.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      if (Xioctl(fd_, VIDIOC_ENUM_FMT, &desc) != 0) break;
      const std::string description = CString(desc.description, sizeof(desc.description));
      for (int s = 0; s < kMaxSizes; ++s) {
        v4l2_frmsizeenum size{};
        size.index = s;
        size.pixel_format = desc.pixelformat;
        if (Xioctl(fd_, VIDIOC_ENUM_FRAMESIZES, &size) != 0) break;
        std::vector<std::pair<int, int>> sizes;
        if (size.type == V4L2_FRMSIZE_TYPE_DISCRETE) {
          sizes.emplace_back(size.discrete.width, size.discrete.height);
        } else {  // stepwise/continuous: report the extremes only
          sizes.emplace_back(size.stepwise.min_width, size.stepwise.min_height);
          sizes.emplace_back(size.stepwise.max_width, size.stepwise.max_height);
        }
        for (const auto& [w, h] : sizes) {
          V4l2Mode mode;
          mode.fourcc = desc.pixelformat;
          mode.description = description;
          mode.width = w;
          mode.height = h;
          for (int i = 0; i < kMaxIntervals; ++i) {
            v4l2_frmivalenum interval{};
            interval.index = i;
            interval.pixel_format = desc.pixelformat;
            interval.width = w;
            interval.height = h;
            if (Xioctl(fd_, VIDIOC_ENUM_FRAMEINTERVALS, &interval) != 0) break;
            if (interval.type != V4L2_FRMIVAL_TYPE_DISCRETE) break;
            if (interval.discrete.numerator > 0) {
              mode.fps.push_back(static_cast<double>(interval.discrete.denominator) /
                                 interval.discrete.numerator);
            }
          }
          info.modes.push_back(std::move(mode));
        }
        if (size.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;
      }
    }
    return info;
  }

  StatusOr<V4l2Format> SetFormat(std::uint32_t fourcc, int width, int height) override {
    if (fd_ < 0) return IoError(path_ + ": closed");
    v4l2_format format{};
    format.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    format.fmt.pix.pixelformat = fourcc;
    format.fmt.pix.width = static_cast<std::uint32_t>(width);
    format.fmt.pix.height = static_cast<std::uint32_t>(height);
    format.fmt.pix.field = V4L2_FIELD_NONE;
    if (Xioctl(fd_, VIDIOC_S_FMT, &format) != 0) {
      if (errno == EINVAL) {
        return Unsupported(path_ + " does not offer " + FourccToString(fourcc) +
                           " (ccmd_camera --list shows what it offers)");
      }
      return ErrnoStatus(path_, "VIDIOC_S_FMT", errno);
    }
    // Drivers silently substitute the nearest format they have: that is an error here,
    // since the conversion and the intrinsics depend on exactly what was asked for.
    if (format.fmt.pix.pixelformat != fourcc || static_cast<int>(format.fmt.pix.width) != width ||
        static_cast<int>(format.fmt.pix.height) != height) {
      return Unsupported(path_ + " does not offer " + FourccToString(fourcc) + " at " +
                         std::to_string(width) + "x" + std::to_string(height) + " (it proposes " +
                         FourccToString(format.fmt.pix.pixelformat) + " " +
                         std::to_string(format.fmt.pix.width) + "x" +
                         std::to_string(format.fmt.pix.height) + ")");
    }
    V4l2Format result;
    result.fourcc = format.fmt.pix.pixelformat;
    result.width = static_cast<int>(format.fmt.pix.width);
    result.height = static_cast<int>(format.fmt.pix.height);
    result.stride = static_cast<int>(format.fmt.pix.bytesperline);
    result.image_size = format.fmt.pix.sizeimage;
    return result;
  }

  StatusOr<double> SetFrameRate(double fps) override {
    if (fd_ < 0) return IoError(path_ + ": closed");
    v4l2_streamparm parm{};
    parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (Xioctl(fd_, VIDIOC_G_PARM, &parm) != 0) return 0.0;
    if (!(parm.parm.capture.capability & V4L2_CAP_TIMEPERFRAME)) return 0.0;
    parm.parm.capture.timeperframe.numerator = 1000;
    parm.parm.capture.timeperframe.denominator =
        static_cast<std::uint32_t>(std::lround(fps * 1000));
    if (Xioctl(fd_, VIDIOC_S_PARM, &parm) != 0) return ErrnoStatus(path_, "VIDIOC_S_PARM", errno);
    const auto& tpf = parm.parm.capture.timeperframe;
    return tpf.numerator > 0 ? static_cast<double>(tpf.denominator) / tpf.numerator : 0.0;
  }

  Status Start(int buffer_count) override {
    if (fd_ < 0) return IoError(path_ + ": closed");
    v4l2_requestbuffers request{};
    request.count = static_cast<std::uint32_t>(std::clamp(buffer_count, 2, kMaxBuffers));
    request.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    request.memory = V4L2_MEMORY_MMAP;
    if (Xioctl(fd_, VIDIOC_REQBUFS, &request) != 0) {
      if (errno == EINVAL) return Unsupported(path_ + " does not support memory-mapped streaming");
      return ErrnoStatus(path_, "VIDIOC_REQBUFS", errno);
    }
    if (request.count < 2 || request.count > kMaxBuffers) {
      return IoError(path_ + ": driver granted " + std::to_string(request.count) + " buffers");
    }
    for (std::uint32_t i = 0; i < request.count; ++i) {
      v4l2_buffer buffer{};
      buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      buffer.memory = V4L2_MEMORY_MMAP;
      buffer.index = i;
      if (Xioctl(fd_, VIDIOC_QUERYBUF, &buffer) != 0)
        return ErrnoStatus(path_, "VIDIOC_QUERYBUF", errno);
      void* start =
          mmap(nullptr, buffer.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, buffer.m.offset);
      if (start == MAP_FAILED) return ErrnoStatus(path_, "mmap", errno);
      buffers_.push_back({start, buffer.length});
      if (Xioctl(fd_, VIDIOC_QBUF, &buffer) != 0) return ErrnoStatus(path_, "VIDIOC_QBUF", errno);
    }
    v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (Xioctl(fd_, VIDIOC_STREAMON, &type) != 0)
      return ErrnoStatus(path_, "VIDIOC_STREAMON", errno);
    streaming_ = true;
    return Status::Ok();
  }

  StatusOr<V4l2Buffer> Dequeue(double timeout) override {
    if (fd_ < 0 || !streaming_) return IoError(path_ + ": not streaming");
    const double deadline = MonotonicSeconds() + timeout;
    while (true) {
      v4l2_buffer buffer{};
      buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      buffer.memory = V4L2_MEMORY_MMAP;
      if (Xioctl(fd_, VIDIOC_DQBUF, &buffer) == 0) {
        if (buffer.index >= buffers_.size()) {
          return IoError(path_ + ": driver returned buffer " + std::to_string(buffer.index));
        }
        V4l2Buffer result;
        result.index = static_cast<int>(buffer.index);
        result.data = static_cast<const std::uint8_t*>(buffers_[buffer.index].start);
        // Never trust bytesused beyond the mapping; 0 from old drivers means "whole buffer".
        const std::size_t length = buffers_[buffer.index].length;
        result.bytes_used =
            buffer.bytesused == 0 ? length : std::min<std::size_t>(buffer.bytesused, length);
        result.timestamp = buffer.timestamp.tv_sec + buffer.timestamp.tv_usec * 1e-6;
        result.sequence = buffer.sequence;
        result.error = (buffer.flags & V4L2_BUF_FLAG_ERROR) != 0;
        return result;
      }
      if (errno == EIO) {
        // The V4L2 spec: an internal error or signal loss; the driver may have stopped
        // capturing and the buffer may be unusable. Transient: the source is reopened.
        return Unavailable(path_ + ": VIDIOC_DQBUF: " + std::strerror(EIO) +
                           " (device error; reopening)");
      }
      if (errno != EAGAIN) return ErrnoStatus(path_, "VIDIOC_DQBUF", errno);
      const double left = deadline - MonotonicSeconds();
      if (left <= 0) {
        return Unavailable(path_ + ": no frame within " + std::to_string(timeout) + " s");
      }
      pollfd fds{fd_, POLLIN, 0};
      const int ready = poll(&fds, 1, static_cast<int>(std::ceil(left * 1000)));
      if (ready < 0 && errno != EINTR) return ErrnoStatus(path_, "poll", errno);
      // POLLERR/POLLHUP: the next DQBUF reports why (ENODEV when unplugged).
    }
  }

  Status Requeue(int index) override {
    if (fd_ < 0) return IoError(path_ + ": closed");
    if (index < 0 || static_cast<std::size_t>(index) >= buffers_.size()) {
      return InvalidArgument(path_ + ": no buffer " + std::to_string(index));
    }
    v4l2_buffer buffer{};
    buffer.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buffer.memory = V4L2_MEMORY_MMAP;
    buffer.index = static_cast<std::uint32_t>(index);
    if (Xioctl(fd_, VIDIOC_QBUF, &buffer) != 0) return ErrnoStatus(path_, "VIDIOC_QBUF", errno);
    return Status::Ok();
  }

  void Close() override {
    if (fd_ < 0) return;
    if (streaming_) {
      v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      Xioctl(fd_, VIDIOC_STREAMOFF, &type);  // fails harmlessly on an unplugged device
      streaming_ = false;
    }
    for (const Mapping& m : buffers_) munmap(m.start, m.length);
    buffers_.clear();
    ::close(fd_);
    fd_ = -1;
  }

 private:
  struct Mapping {
    void* start;
    std::size_t length;
  };
  std::string path_;
  int fd_;
  bool streaming_ = false;
  std::vector<Mapping> buffers_;
};

}  // namespace

StatusOr<std::unique_ptr<V4l2Device>> OpenLinuxV4l2Device(const std::string& path) {
  // Non-blocking: DQBUF returns EAGAIN and Dequeue() waits in poll() with a timeout.
  const int fd = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) return ErrnoStatus(path, "open", errno);
  return std::unique_ptr<V4l2Device>(new LinuxV4l2Device(path, fd));
}

std::vector<std::string> ListV4l2DeviceNodes() {
  std::vector<std::pair<int, std::string>> nodes;
  std::error_code error;
  for (const auto& entry : std::filesystem::directory_iterator("/dev", error)) {
    const std::string name = entry.path().filename().string();
    if (name.size() <= 5 || name.compare(0, 5, "video") != 0) continue;
    const std::string number = name.substr(5);
    if (!std::all_of(number.begin(), number.end(), ::isdigit) || number.size() > 6) continue;
    nodes.emplace_back(std::stoi(number), entry.path().string());
  }
  std::sort(nodes.begin(), nodes.end());
  std::vector<std::string> paths;
  for (auto& [number, path] : nodes) paths.push_back(std::move(path));
  return paths;
}

}  // namespace ccmd
