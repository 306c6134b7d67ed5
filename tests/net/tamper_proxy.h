#pragma once

// A man in the middle for attack tests: forwards 127.0.0.1:port() to a target port frame by
// frame and hands every frame to a hook, which decides what goes on (unchanged, altered,
// dropped) and may inject frames in either direction. It knows the framing (PROTOCOL.md)
// but no key: whatever it forges, it cannot tag correctly. Every thread is owned and joined
// by Stop().

#include <poll.h>
#include <sys/socket.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"
#include "proto/crc32c.h"
#include "proto/frame.h"

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

class TamperProxy {
 public:
  explicit TamperProxy(TamperHook hook) : hook_(std::move(hook)) {}
  ~TamperProxy() { Stop(); }

  bool Start(std::uint16_t target_port) {
    target_.store(target_port);
    bool loopback;
    StatusOr<UniqueFd> fd = ListenTcp(HostPort{"127.0.0.1", 0}, 16, &loopback);
    if (!fd.ok()) return false;
    listener_ = std::move(*fd);
    port_ = LocalPort(listener_.get()).value();
    acceptor_ = std::thread([this] { AcceptLoop(); });
    return true;
  }
  std::uint16_t port() const { return port_; }
  // A restarted server on a new port: later connections go there.
  void SetTarget(std::uint16_t port) { target_.store(port); }

  void Stop() {
    stop_.store(true);
    wake_.Signal();
    if (acceptor_.joinable()) acceptor_.join();
    std::lock_guard<std::mutex> lock(mutex_);
    for (std::thread& t : pumps_) t.join();
    pumps_.clear();
  }

 private:
  struct Side {
    UniqueFd fd;
    std::vector<std::uint8_t> in;
  };

  void AcceptLoop() {
    while (!stop_.load()) {
      pollfd fds[2] = {{listener_.get(), POLLIN, 0}, {wake_.fd(), POLLIN, 0}};
      ::poll(fds, 2, -1);
      if (stop_.load()) return;
      const int fd = ::accept4(listener_.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
      if (fd < 0) continue;
      UniqueFd agent(fd);
      StatusOr<UniqueFd> server = ConnectTcp(HostPort{"127.0.0.1", target_.load()}, 2.0);
      if (!server.ok()) continue;
      std::lock_guard<std::mutex> lock(mutex_);
      pumps_.emplace_back([this, a = std::move(agent), s = std::move(*server)]() mutable {
        Pump(std::move(a), std::move(s));
      });
    }
  }

  void Pump(UniqueFd agent_fd, UniqueFd server_fd) {
    Side sides[2];
    sides[0].fd = std::move(agent_fd);
    sides[1].fd = std::move(server_fd);
    std::vector<std::uint8_t> buffer(64 << 10);
    while (!stop_.load()) {
      pollfd fds[3] = {{sides[0].fd.get(), POLLIN, 0},
                       {sides[1].fd.get(), POLLIN, 0},
                       {wake_.fd(), POLLIN, 0}};
      ::poll(fds, 3, -1);
      if (stop_.load()) return;
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
        if (!WriteFully(to_fd, w.bytes)) return false;
      }
      for (const WireFrame& w : back) {
        if (!WriteFully(back_fd, w.bytes)) return false;
      }
    }
    return true;
  }

  bool WriteFully(int fd, const std::vector<std::uint8_t>& bytes) {
    std::size_t done = 0;
    while (done < bytes.size() && !stop_.load()) {
      StatusOr<std::size_t> n = WriteSome(fd, bytes.data() + done, bytes.size() - done);
      if (!n.ok()) return false;
      done += *n;
      if (done < bytes.size()) {
        pollfd p{fd, POLLOUT, 0};
        ::poll(&p, 1, 100);
      }
    }
    return done == bytes.size();
  }

  TamperHook hook_;
  std::mutex mutex_;
  UniqueFd listener_;
  std::uint16_t port_ = 0;
  std::atomic<std::uint16_t> target_{0};
  WakeFd wake_;
  std::atomic<bool> stop_{false};
  std::thread acceptor_;
  std::vector<std::thread> pumps_;
};

}  // namespace ccmd::nettest
