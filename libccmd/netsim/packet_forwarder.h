#pragma once

// The shaped link's delay, jitter and loss stage. The kernel here has no netem, so a
// user-space bridge joins the two interfaces of the link's namespace: raw packet sockets
// (AF_PACKET) read every Ethernet frame arriving on one side, a DelayLine per direction
// decides whether it is lost and when it leaves, and due frames are written to the other
// side, where tc's tbf (the rate limiter) queues them or, when its queue is full, drops
// them. TCP between agents and server thus meets real packet loss, delay and a bottleneck,
// and recovers as it would on a radio link. One owned thread, joined by Stop().

#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"
#include "libccmd/netsim/delay_line.h"
#include "libccmd/netsim/link_spec.h"
#include "libccmd/util/json.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ForwardedDirectionStats {
  DelayLineStats line;
  std::uint64_t rate_drops = 0;    // refused by the rate limiter (its queue was full)
  std::uint64_t socket_drops = 0;  // the kernel dropped them before this stage read them
};

struct PacketForwarderStats {
  ForwardedDirectionStats uplink;    // agents -> server
  ForwardedDirectionStats downlink;  // server -> agents
  Json ToJson() const;
};

class PacketForwarder {
 public:
  // Enters the network namespace at `netns_path` on the forwarding thread, binds raw sockets
  // to the two interfaces there and returns once they are ready (or why they are not).
  static StatusOr<std::unique_ptr<PacketForwarder>> Start(const std::string& netns_path,
                                                          const std::string& agents_interface,
                                                          const std::string& server_interface,
                                                          const LinkSpec& spec);
  ~PacketForwarder() { Stop(); }
  PacketForwarder(const PacketForwarder&) = delete;
  PacketForwarder& operator=(const PacketForwarder&) = delete;

  void Stop();
  PacketForwarderStats stats() const;

 private:
  explicit PacketForwarder(const LinkSpec& spec);
  Status Open(const std::string& agents_interface, const std::string& server_interface);
  void Run();
  // Reads what arrived on side `from` into its delay line. Mutex held.
  void Receive(int from);
  // Writes every due frame of direction `from` to the other side. Mutex held.
  void SendDue(int from, double now);

  WakeFd wake_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  UniqueFd sockets_[2];  // 0: agents side, 1: server side

  mutable std::mutex mutex_;
  DelayLine lines_[2];  // indexed by the side a frame came from
  ForwardedDirectionStats stats_[2];
  std::vector<std::uint8_t> buffer_;  // one received frame
};

}  // namespace ccmd
