#pragma once

// A scripted V4L2 node behind the same interface as the real device: a test fills a FakeNode
// with the modes it offers and the frames it will deliver, and inspects afterwards what the
// capture loop did with it (formats set, buffers given back, closes).

#include <deque>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "libccmd/sensors/v4l2_device.h"

namespace ccmd::testing {

struct FakeFrame {
  double timestamp = 0;
  std::vector<std::uint8_t> data;
  bool error = false;
  std::uint32_t sequence = 0;
};

struct FakeNode {
  V4l2DeviceInfo info;
  Status open_error;             // returned by the opener when not ok
  std::deque<FakeFrame> frames;  // delivered in order
  int unplug_after = -1;         // Dequeue fails with ENODEV after this many frames (-1: never)
  int stride_padding = 0;        // extra bytes per row reported in bytesperline

  // Observations.
  int opens = 0;
  int closes = 0;
  int delivered = 0;
  int outstanding = 0;  // dequeued and not yet given back
  V4l2Format format;
  bool started = false;
};

class FakeV4l2Device : public V4l2Device {
 public:
  explicit FakeV4l2Device(FakeNode* node) : node_(node) { ++node_->opens; }
  ~FakeV4l2Device() override { Close(); }

  StatusOr<V4l2DeviceInfo> Query() override { return node_->info; }

  StatusOr<V4l2Format> SetFormat(std::uint32_t fourcc, int width, int height) override {
    for (const V4l2Mode& m : node_->info.modes) {
      if (m.fourcc == fourcc && m.width == width && m.height == height) {
        V4l2Format f;
        f.fourcc = fourcc;
        f.width = width;
        f.height = height;
        f.stride = fourcc == kFourccMjpeg ? 0 : width * 2 + node_->stride_padding;
        f.image_size = static_cast<std::size_t>(f.stride > 0 ? f.stride : width * 2) * height;
        node_->format = f;
        return f;
      }
    }
    return Unsupported("fake: format not offered");
  }

  StatusOr<double> SetFrameRate(double fps) override { return fps; }

  Status Start(int buffer_count) override {
    slots_.assign(buffer_count, {});
    busy_.assign(buffer_count, false);
    node_->started = true;
    return Status::Ok();
  }

  StatusOr<V4l2Buffer> Dequeue(double) override {
    if (closed_) return IoError("fake: closed");
    if (node_->unplug_after >= 0 && node_->delivered >= node_->unplug_after) {
      return Unavailable(node_->info.path + ": VIDIOC_DQBUF: No such device (camera unplugged?)");
    }
    int slot = -1;
    for (std::size_t i = 0; i < busy_.size(); ++i) {
      if (!busy_[i]) {
        slot = static_cast<int>(i);
        break;
      }
    }
    // Out of frames, or every buffer still held by the caller: the real device times out.
    if (node_->frames.empty() || slot < 0) {
      return Unavailable(node_->info.path + ": no frame within 2 s");
    }
    FakeFrame frame = std::move(node_->frames.front());
    node_->frames.pop_front();
    slots_[slot] = std::move(frame.data);
    busy_[slot] = true;
    ++node_->outstanding;
    ++node_->delivered;
    V4l2Buffer buffer;
    buffer.index = slot;
    buffer.data = slots_[slot].data();
    buffer.bytes_used = slots_[slot].size();
    buffer.timestamp = frame.timestamp;
    buffer.sequence = frame.sequence;
    buffer.error = frame.error;
    return buffer;
  }

  Status Requeue(int index) override {
    if (index < 0 || static_cast<std::size_t>(index) >= busy_.size() || !busy_[index]) {
      return InvalidArgument("fake: buffer " + std::to_string(index) + " is not dequeued");
    }
    busy_[index] = false;
    --node_->outstanding;
    return Status::Ok();
  }

  void Close() override {
    if (closed_) return;
    closed_ = true;
    ++node_->closes;
  }

 private:
  FakeNode* node_;
  bool closed_ = false;
  std::vector<std::vector<std::uint8_t>> slots_;
  std::vector<bool> busy_;
};

// Opens fake nodes by path; unknown paths are NotFound like a missing /dev node.
inline V4l2DeviceOpener FakeOpener(std::map<std::string, FakeNode*> nodes) {
  return [nodes](const std::string& path) -> StatusOr<std::unique_ptr<V4l2Device>> {
    const auto it = nodes.find(path);
    if (it == nodes.end()) return NotFound(path + ": open: No such file or directory");
    if (!it->second->open_error.ok()) return it->second->open_error;
    return std::unique_ptr<V4l2Device>(new FakeV4l2Device(it->second));
  };
}

inline V4l2Mode Mode(std::uint32_t fourcc, int width, int height) {
  V4l2Mode m;
  m.fourcc = fourcc;
  m.width = width;
  m.height = height;
  m.fps = {30.0};
  return m;
}

}  // namespace ccmd::testing
