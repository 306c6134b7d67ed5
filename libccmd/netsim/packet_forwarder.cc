#include "libccmd/netsim/packet_forwarder.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <linux/if_packet.h>
#include <net/ethernet.h>
#include <net/if.h>
#include <poll.h>
#include <sched.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <future>
#include <vector>

#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

// Large enough for any frame a veth delivers with its offloads off (MTU 1500) and for jumbo
// frames should someone raise the MTU.
constexpr std::size_t kMaxFrameBytes = 65536;
// Socket buffers: a burst at a high rate must not overflow the kernel's queue before this
// stage reads it, and the rate limiter's queue must fill before the socket's send buffer does.
constexpr int kSocketBufferBytes = 8 << 20;
// Frames read per side per round, so that due frames leave on time under a flood.
constexpr int kMaxReadsPerRound = 256;

DelayLineOptions LineOptions(const LinkSpec& spec, std::uint64_t direction) {
  DelayLineOptions o;
  o.delay_s = spec.delay_s;
  o.jitter_s = spec.jitter_s;
  o.loss = spec.loss;
  o.seed = MixSeed(spec.seed, direction);
  return o;
}

StatusOr<UniqueFd> OpenPacketSocket(const std::string& interface) {
  UniqueFd fd(::socket(AF_PACKET, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, htons(ETH_P_ALL)));
  if (!fd.valid()) return IoError("packet socket: " + std::string(std::strerror(errno)));
  const unsigned index = ::if_nametoindex(interface.c_str());
  if (index == 0) return NotFound("no interface " + interface + " in the link namespace");
  sockaddr_ll address{};
  address.sll_family = AF_PACKET;
  address.sll_protocol = htons(ETH_P_ALL);
  address.sll_ifindex = static_cast<int>(index);
  if (::bind(fd.get(), reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
    return IoError("bind to " + interface + ": " + std::strerror(errno));
  }
  // Frames this stage writes on an interface would come back to its own socket as outgoing.
  const int one = 1;
  ::setsockopt(fd.get(), SOL_PACKET, PACKET_IGNORE_OUTGOING, &one, sizeof(one));
  ::setsockopt(fd.get(), SOL_SOCKET, SO_RCVBUFFORCE, &kSocketBufferBytes,
               sizeof(kSocketBufferBytes));
  ::setsockopt(fd.get(), SOL_SOCKET, SO_SNDBUFFORCE, &kSocketBufferBytes,
               sizeof(kSocketBufferBytes));
  return fd;
}

Json DirectionJson(const ForwardedDirectionStats& s) {
  Json j;
  j["packets"] = s.line.arrived;
  j["bytes"] = s.line.arrived_bytes;
  j["lost"] = s.line.lost;
  j["overflow"] = s.line.overflow;
  j["rate_drops"] = s.rate_drops;
  j["socket_drops"] = s.socket_drops;
  j["forwarded"] = s.line.left;
  j["forwarded_bytes"] = s.line.left_bytes;
  j["loss_measured"] = s.line.arrived ? static_cast<double>(s.line.lost) / s.line.arrived : 0.0;
  return j;
}

}  // namespace

Json PacketForwarderStats::ToJson() const {
  Json j;
  j["uplink"] = DirectionJson(uplink);
  j["downlink"] = DirectionJson(downlink);
  return j;
}

PacketForwarder::PacketForwarder(const LinkSpec& spec)
    : lines_{DelayLine(LineOptions(spec, 0)), DelayLine(LineOptions(spec, 1))} {}

StatusOr<std::unique_ptr<PacketForwarder>> PacketForwarder::Start(
    const std::string& netns_path, const std::string& agents_interface,
    const std::string& server_interface, const LinkSpec& spec) {
  CCMD_RETURN_IF_ERROR(spec.Validate());
  std::unique_ptr<PacketForwarder> forwarder(new PacketForwarder(spec));
  if (!forwarder->wake_.valid()) return IoError("eventfd: " + std::string(std::strerror(errno)));
  std::promise<Status> ready;
  std::future<Status> opened = ready.get_future();
  PacketForwarder* f = forwarder.get();
  forwarder->thread_ = std::thread(
      [f, netns_path, agents_interface, server_interface, ready = std::move(ready)]() mutable {
        // The namespace is a property of this thread only; sockets stay in it once created.
        const int ns = ::open(netns_path.c_str(), O_RDONLY | O_CLOEXEC);
        if (ns < 0) {
          ready.set_value(IoError("cannot open " + netns_path + ": " + std::strerror(errno)));
          return;
        }
        const int entered = ::setns(ns, CLONE_NEWNET);
        ::close(ns);
        if (entered != 0) {
          ready.set_value(IoError("cannot enter " + netns_path + ": " + std::strerror(errno)));
          return;
        }
        const Status s = f->Open(agents_interface, server_interface);
        ready.set_value(s);
        if (s.ok()) f->Run();
      });
  const Status s = opened.get();
  if (!s.ok()) {
    forwarder->thread_.join();
    return s;
  }
  return forwarder;
}

Status PacketForwarder::Open(const std::string& agents_interface,
                             const std::string& server_interface) {
  CCMD_ASSIGN_OR_RETURN(sockets_[0], OpenPacketSocket(agents_interface));
  CCMD_ASSIGN_OR_RETURN(sockets_[1], OpenPacketSocket(server_interface));
  return Status::Ok();
}

void PacketForwarder::Stop() {
  stop_.store(true);
  wake_.Signal();
  if (thread_.joinable()) thread_.join();
}

PacketForwarderStats PacketForwarder::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  PacketForwarderStats s;
  s.uplink = stats_[0];
  s.downlink = stats_[1];
  s.uplink.line = lines_[0].stats();
  s.downlink.line = lines_[1].stats();
  return s;
}

void PacketForwarder::Receive(int from) {
  std::vector<std::uint8_t>& frame = buffer_;
  frame.resize(kMaxFrameBytes);
  for (int i = 0; i < kMaxReadsPerRound; ++i) {
    sockaddr_ll source{};
    socklen_t length = sizeof(source);
    const ssize_t n = ::recvfrom(sockets_[from].get(), frame.data(), frame.size(), MSG_DONTWAIT,
                                 reinterpret_cast<sockaddr*>(&source), &length);
    if (n <= 0) break;
    if (source.sll_pkttype == PACKET_OUTGOING) continue;
    lines_[from].Push(MonotonicSeconds(),
                      std::vector<std::uint8_t>(frame.begin(), frame.begin() + n));
  }
  tpacket_stats counts{};
  socklen_t size = sizeof(counts);
  if (::getsockopt(sockets_[from].get(), SOL_PACKET, PACKET_STATISTICS, &counts, &size) == 0) {
    stats_[from].socket_drops += counts.tp_drops;  // the kernel resets them on each read
  }
}

void PacketForwarder::SendDue(int from, double now) {
  std::vector<std::uint8_t> frame;
  const int to = 1 - from;
  while (lines_[from].PopDue(now, &frame)) {
    if (::send(sockets_[to].get(), frame.data(), frame.size(), MSG_DONTWAIT) < 0) {
      // ENOBUFS: tbf's queue is full, the rate limiter's drop; EAGAIN: our send buffer is.
      ++stats_[from].rate_drops;
    }
  }
}

void PacketForwarder::Run() {
  while (!stop_.load()) {
    double next_due;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      next_due = std::min(lines_[0].NextDue(), lines_[1].NextDue());
    }
    pollfd fds[3] = {
        {sockets_[0].get(), POLLIN, 0}, {sockets_[1].get(), POLLIN, 0}, {wake_.fd(), POLLIN, 0}};
    timespec timeout{};
    timespec* wait = nullptr;
    if (std::isfinite(next_due)) {
      const double left = std::max(0.0, next_due - MonotonicSeconds());
      timeout.tv_sec = static_cast<time_t>(left);
      timeout.tv_nsec = static_cast<long>((left - timeout.tv_sec) * 1e9);
      wait = &timeout;
    }
    if (::ppoll(fds, 3, wait, nullptr) < 0 && errno != EINTR) {
      CCMD_LOG(ERROR) << "link forwarder: poll: " << std::strerror(errno);
      return;
    }
    if (fds[2].revents & POLLIN) wake_.Drain();
    std::lock_guard<std::mutex> lock(mutex_);
    for (int side = 0; side < 2; ++side) {
      if (fds[side].revents & POLLIN) Receive(side);
    }
    const double now = MonotonicSeconds();
    SendDue(0, now);
    SendDue(1, now);
  }
}

}  // namespace ccmd
