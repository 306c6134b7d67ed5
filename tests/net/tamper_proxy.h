#pragma once

// A man in the middle for attack tests: forwards 127.0.0.1:port() to a target port frame by
// frame and hands every frame to a hook, which decides what goes on (unchanged, altered,
// dropped) and may inject frames in either direction. It knows the framing (PROTOCOL.md)
// but no key: whatever it forges, it cannot tag correctly.

#include <poll.h>
#include <sys/socket.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"
#include "proto/crc32c.h"
#include "proto/frame.h"
#include "tests/net/loopback_proxy.h"

namespace ccmd::nettest {

// One frame as it travels: header, payload and, if flagged, the tag.
struct WireFrame {
  std::vector<std::uint8_t> bytes;
  std::uint8_t type() const { return bytes[5]; }
  std::uint32_t payload_size() const {
    return bytes[8] | (bytes[9] << 8) | (bytes[10] << 16) |
           (static_cast<std::uint32_t>(bytes[11]) << 24);
  }
  bool tagged() const { return (bytes[7] & 0x80) != 0; }
  std::uint8_t* payload() { return bytes.data() + kFrameHeaderSize; }
  // After editing the payload: fresh CRCs, so only the tag can tell.
  void Reseal() {
    PutLe32(12, Crc32c(payload(), payload_size()));
    PutLe32(16, Crc32c(bytes.data(), 16));
  }
  void PutLe32(std::size_t at, std::uint32_t v) {
    for (int i = 0; i < 4; ++i) bytes[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
  }
};

// The best a forger without the key can do: a well-formed frame, tagged if the session is,
// with a tag of its choosing.
inline WireFrame ForgeFrame(std::uint8_t type, const std::vector<std::uint8_t>& payload,
                            bool tagged) {
  WireFrame f;
  AppendFrame(type, tagged ? kFrameTagged : 0, payload, &f.bytes);
  if (tagged) f.bytes.insert(f.bytes.end(), kFrameTagSize, 0xA5);
  return f;
}

// Called for every frame. `from_agent` tells the direction; push to *forward what goes on
// in that direction (the frame itself to pass it) and to *back what goes to the sender.
using TamperHook =
    std::function<void(bool from_agent, WireFrame frame, std::vector<WireFrame>* forward,
                       std::vector<WireFrame>* back)>;

class TamperProxy : public LoopbackProxy {
 public:
  explicit TamperProxy(TamperHook hook) : hook_(std::move(hook)) {}
  ~TamperProxy() override { Stop(); }

 protected:
  std::function<void()> NewPump(UniqueFd agent, UniqueFd server) override {
    auto pair =
        std::make_shared<std::pair<UniqueFd, UniqueFd>>(std::move(agent), std::move(server));
    return [this, pair] { Pump(std::move(pair->first), std::move(pair->second)); };
  }

 private:
  struct Side {
    UniqueFd fd;
    std::vector<std::uint8_t> in;
  };

  void Pump(UniqueFd agent_fd, UniqueFd server_fd) {
    Side sides[2];
    sides[0].fd = std::move(agent_fd);
    sides[1].fd = std::move(server_fd);
    std::vector<std::uint8_t> buffer(64 << 10);
    while (!stopping()) {
      pollfd fds[3] = {
          {sides[0].fd.get(), POLLIN, 0}, {sides[1].fd.get(), POLLIN, 0}, {wake_fd(), POLLIN, 0}};
      ::poll(fds, 3, -1);
      if (stopping()) return;
      for (int from = 0; from < 2; ++from) {
        if (!(fds[from].revents & (POLLIN | POLLHUP | POLLERR))) continue;
        StatusOr<std::size_t> n = ReadSome(sides[from].fd.get(), buffer.data(), buffer.size());
        if (!n.ok()) return;  // either side closed: both close here
        Side& s = sides[from];
        s.in.insert(s.in.end(), buffer.begin(), buffer.begin() + static_cast<std::ptrdiff_t>(*n));
        if (!Forward(from == 0, &s, sides[1 - from].fd.get(), s.fd.get())) return;
      }
    }
  }

  // Cuts whole frames off the front of side->in and passes them through the hook.
  bool Forward(bool from_agent, Side* side, int to_fd, int back_fd) {
    while (side->in.size() >= kFrameHeaderSize) {
      WireFrame f;
      f.bytes.assign(side->in.begin(), side->in.begin() + kFrameHeaderSize);
      const std::size_t total =
          kFrameHeaderSize + f.payload_size() + (f.tagged() ? kFrameTagSize : 0);
      if (side->in.size() < total) return true;
      f.bytes.assign(side->in.begin(), side->in.begin() + static_cast<std::ptrdiff_t>(total));
      side->in.erase(side->in.begin(), side->in.begin() + static_cast<std::ptrdiff_t>(total));
      std::vector<WireFrame> forward, back;
      hook_(from_agent, std::move(f), &forward, &back);
      for (const WireFrame& w : forward) {
        if (!WriteFully(to_fd, w.bytes.data(), w.bytes.size())) return false;
      }
      for (const WireFrame& w : back) {
        if (!WriteFully(back_fd, w.bytes.data(), w.bytes.size())) return false;
      }
    }
    return true;
  }

  TamperHook hook_;
};

}  // namespace ccmd::nettest
