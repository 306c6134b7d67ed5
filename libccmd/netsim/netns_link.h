#pragma once

// A shaped network for one evaluation run, made of three network namespaces that exist
// only for that run:
//
//   <name>-agents  10.X.Y.1 --veth-- <name>-link --veth-- 10.X.Y.2  <name>-server
//
// The agents' and the server's namespaces each hold one end of a veth pair and loopback;
// the link namespace holds the two other ends and no address at all. A PacketForwarder
// bridges them there (delay, jitter, loss) and tc's tbf on each of its two egress sides sets
// the rate, so the link is the same in both directions. Nothing here has a route to
// anything else: processes run inside the namespaces reach each other and nothing more.
//
// Names and addresses come from a random run id (several runs may coexist). Close(), the
// destructor, and a watchdog process started first (it outlives this one if it is killed)
// stop every process left in the namespaces and delete them. Needs root.
//
//   CCMD_ASSIGN_OR_RETURN(auto link, NetnsLink::Create(spec));
//   Subprocess::Start(link->Command(NetnsLink::Side::kServer, {server, "--listen",
//   link->address(kServer) + ":0", ...}), ...);

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "libccmd/netsim/link_spec.h"
#include "libccmd/netsim/packet_forwarder.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct NetnsLinkOptions {
  std::string
      ip_program;  // iproute2's ip and tc; "" = looked up in /usr/sbin, /sbin, /usr/bin, /bin
  std::string tc_program;
  bool watchdog = true;  // tests that kill nothing may turn it off

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class NetnsLink {
 public:
  enum class Side { kAgents = 0, kLink = 1, kServer = 2 };

  static StatusOr<std::unique_ptr<NetnsLink>> Create(const LinkSpec& spec,
                                                     const NetnsLinkOptions& options = {});
  ~NetnsLink();
  NetnsLink(const NetnsLink&) = delete;
  NetnsLink& operator=(const NetnsLink&) = delete;

  // Stops the forwarder, kills every process still inside the namespaces and deletes them.
  // Idempotent; returns the first error (the rest is still attempted).
  Status Close();

  // `argv` (argv[0] a path) run inside a namespace: "ip netns exec NAME argv...".
  std::vector<std::string> Command(Side side, const std::vector<std::string>& argv) const;
  // Runs `fn` on a thread that has entered the namespace (sockets it opens stay there).
  Status RunIn(Side side, const std::function<Status()>& fn) const;

  const std::string& address(Side side) const;  // "" for the link
  const std::string& namespace_name(Side side) const;
  const LinkSpec& spec() const { return spec_; }
  PacketForwarderStats forwarder_stats() const;
  Json ToJson() const;

 private:
  NetnsLink() = default;
  Status Build();
  Status StartWatchdog();
  Status Run(const std::vector<std::string>& argv) const;

  LinkSpec spec_;
  std::string ip_, tc_;
  std::string names_[3];
  std::string interfaces_[4];  // agents end, link's agents side, link's server side, server end
  std::string addresses_[3];
  std::unique_ptr<PacketForwarder> forwarder_;
  int watchdog_pid_ = -1;
  int watchdog_fd_ = -1;
  bool closed_ = false;
};

// Ok when this process can build a NetnsLink (root, iproute2 present); else why not.
Status CheckNetnsLinkAvailable(const NetnsLinkOptions& options = {});

// Runs `fn` on a thread inside the network namespace at `netns_path` (/run/netns/NAME).
Status RunInNetns(const std::string& netns_path, const std::function<Status()>& fn);

}  // namespace ccmd
