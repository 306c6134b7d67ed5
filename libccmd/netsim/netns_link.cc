#include "libccmd/netsim/netns_link.h"

#include <fcntl.h>
#include <linux/ethtool.h>
#include <linux/sockios.h>
#include <net/if.h>
#include <sched.h>
#include <signal.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <thread>

#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/random.h"
#include "libccmd/util/string_util.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status NetnsLinkOptions::Validate() const { return Status::Ok(); }  // any program path may be tried

void NetnsLinkOptions::Describe(OptionsWriter* out) const {
  out->Add("ip_program", ip_program);
  out->Add("tc_program", tc_program);
  out->Add("watchdog", watchdog);
}
namespace {

constexpr int kAttempts = 5;  // run ids tried before giving up on name collisions

std::string FindProgram(const std::string& given, const std::string& name) {
  if (!given.empty()) return given;
  for (const char* dir : {"/usr/sbin/", "/sbin/", "/usr/bin/", "/bin/"}) {
    const std::string path = dir + name;
    if (::access(path.c_str(), X_OK) == 0) return path;
  }
  return "";
}

// Runs a program to completion; its stdout and stderr together in *output.
int RunCapture(const std::vector<std::string>& argv, std::string* output) {
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) return -1;
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    return -1;
  }
  if (pid == 0) {
    ::dup2(fds[1], 1);
    ::dup2(fds[1], 2);
    ::execv(args[0], args.data());
    ::_exit(127);
  }
  ::close(fds[1]);
  char chunk[4096];
  ssize_t n;
  while ((n = ::read(fds[0], chunk, sizeof(chunk))) != 0) {
    if (n < 0) {
      if (errno == EINTR) continue;
      break;
    }
    if (output) output->append(chunk, static_cast<std::size_t>(n));
  }
  ::close(fds[0]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

std::string Join(const std::vector<std::string>& argv) {
  std::string text;
  for (const std::string& a : argv) text += (text.empty() ? "" : " ") + a;
  return text;
}

// veth offloads leave checksums to the "hardware" and hand over 64 kB super-frames; a
// raw-socket bridge needs ordinary, complete frames. Turning transmit checksumming off
// also turns segmentation offload off.
Status DisableOffloads(const std::string& interface) {
  const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return IoError("socket: " + std::string(std::strerror(errno)));
  ethtool_value value{};
  value.cmd = ETHTOOL_STXCSUM;
  value.data = 0;
  ifreq request{};
  std::snprintf(request.ifr_name, sizeof(request.ifr_name), "%s", interface.c_str());
  request.ifr_data = reinterpret_cast<char*>(&value);
  const int result = ::ioctl(fd, SIOCETHTOOL, &request);
  const int error = errno;
  ::close(fd);
  if (result != 0)
    return IoError("turning checksum offload off on " + interface + ": " + std::strerror(error));
  return Status::Ok();
}

std::string NetnsPath(const std::string& name) { return "/run/netns/" + name; }

}  // namespace

Status RunInNetns(const std::string& netns_path, const std::function<Status()>& fn) {
  Status result;
  std::thread thread([&] {
    const int fd = ::open(netns_path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
      result = IoError("cannot open " + netns_path + ": " + std::strerror(errno));
      return;
    }
    const int entered = ::setns(fd, CLONE_NEWNET);
    ::close(fd);
    if (entered != 0) {
      result = IoError("cannot enter " + netns_path + ": " + std::strerror(errno));
      return;
    }
    result = fn();
  });
  thread.join();
  return result;
}

Status CheckNetnsLinkAvailable(const NetnsLinkOptions& options) {
  if (::geteuid() != 0) {
    return PermissionDenied(
        "a shaped link needs root: it creates network namespaces, veth pairs and tc qdiscs "
        "(run as root, e.g. with sudo, or leave out --link to run on loopback)");
  }
  if (FindProgram(options.ip_program, "ip").empty() ||
      FindProgram(options.tc_program, "tc").empty()) {
    return NotFound(
        "iproute2's ip and tc are needed for a shaped link (apt-get install iproute2; "
        "scripts/setup.sh installs it)");
  }
  return Status::Ok();
}

StatusOr<std::unique_ptr<NetnsLink>> NetnsLink::Create(const LinkSpec& spec,
                                                       const NetnsLinkOptions& options) {
  CCMD_RETURN_IF_ERROR(spec.Validate());
  CCMD_RETURN_IF_ERROR(CheckNetnsLinkAvailable(options));
  std::uint64_t state =
      static_cast<std::uint64_t>(::getpid()) ^
      static_cast<std::uint64_t>(std::chrono::steady_clock::now().time_since_epoch().count());
  Status last;
  for (int attempt = 0; attempt < kAttempts; ++attempt) {
    const std::uint32_t id = static_cast<std::uint32_t>(SplitMix64(&state) & 0xFFFFFF);
    char hex[8];
    std::snprintf(hex, sizeof(hex), "%06x", id);
    std::unique_ptr<NetnsLink> link(new NetnsLink());
    link->spec_ = spec;
    link->ip_ = FindProgram(options.ip_program, "ip");
    link->tc_ = FindProgram(options.tc_program, "tc");
    const std::string prefix = std::string("ccmd-") + hex;
    link->names_[0] = prefix + "-agents";
    link->names_[1] = prefix + "-link";
    link->names_[2] = prefix + "-server";
    // Interface names have at most 15 characters.
    const std::string short_prefix = std::string("cm") + hex;
    link->interfaces_[0] = short_prefix + "a";
    link->interfaces_[1] = short_prefix + "la";
    link->interfaces_[2] = short_prefix + "ls";
    link->interfaces_[3] = short_prefix + "s";
    const std::string subnet =
        "10." + std::to_string((id >> 8) & 0xFF) + "." + std::to_string(id & 0xFF) + ".";
    link->addresses_[0] = subnet + "1";
    link->addresses_[2] = subnet + "2";
    if (FileExists(NetnsPath(link->names_[0])) || FileExists(NetnsPath(link->names_[1])) ||
        FileExists(NetnsPath(link->names_[2]))) {
      link->closed_ = true;  // someone else's: never touch it
      continue;
    }
    if (options.watchdog) CCMD_RETURN_IF_ERROR(link->StartWatchdog());
    last = link->Build();
    if (last.ok()) return link;
    link->Close().IgnoreError();
  }
  return last.ok() ? Unavailable("no free network namespace names after " +
                                 std::to_string(kAttempts) + " tries")
                   : last;
}

NetnsLink::~NetnsLink() { Close().IgnoreError(); }

Status NetnsLink::Run(const std::vector<std::string>& argv) const {
  std::string output;
  const int code = RunCapture(argv, &output);
  if (code != 0) {
    std::string message = "`";
    message += Join(argv);
    message += "` failed (exit " + std::to_string(code) + "): ";
    message += Trim(output);
    return IoError(message);
  }
  return Status::Ok();
}

Status NetnsLink::Build() {
  const std::string &a = names_[0], &l = names_[1], &s = names_[2];
  for (const std::string& ns : {a, l, s}) CCMD_RETURN_IF_ERROR(Run({ip_, "netns", "add", ns}));
  CCMD_RETURN_IF_ERROR(Run({ip_, "link", "add", interfaces_[0], "netns", a, "type", "veth", "peer",
                            "name", interfaces_[1], "netns", l}));
  CCMD_RETURN_IF_ERROR(Run({ip_, "link", "add", interfaces_[3], "netns", s, "type", "veth", "peer",
                            "name", interfaces_[2], "netns", l}));
  const std::pair<std::string, std::string> ends[4] = {
      {a, interfaces_[0]}, {l, interfaces_[1]}, {l, interfaces_[2]}, {s, interfaces_[3]}};
  // No IPv6 link-local addresses: nothing but the run's own traffic crosses the link.
  for (const auto& [ns, interface] : ends) {
    CCMD_RETURN_IF_ERROR(
        Run({ip_, "-n", ns, "link", "set", "dev", interface, "addrgenmode", "none"}));
  }
  CCMD_RETURN_IF_ERROR(
      Run({ip_, "-n", a, "addr", "add", addresses_[0] + "/24", "dev", interfaces_[0]}));
  CCMD_RETURN_IF_ERROR(
      Run({ip_, "-n", s, "addr", "add", addresses_[2] + "/24", "dev", interfaces_[3]}));
  CCMD_RETURN_IF_ERROR(RunInNetns(NetnsPath(a), [&] { return DisableOffloads(interfaces_[0]); }));
  CCMD_RETURN_IF_ERROR(RunInNetns(NetnsPath(s), [&] { return DisableOffloads(interfaces_[3]); }));
  for (const std::string& ns : {a, s})
    CCMD_RETURN_IF_ERROR(Run({ip_, "-n", ns, "link", "set", "dev", "lo", "up"}));
  for (const auto& [ns, interface] : ends) {
    CCMD_RETURN_IF_ERROR(Run({ip_, "-n", ns, "link", "set", "dev", interface, "up"}));
  }
  if (spec_.shapes_rate()) {
    // The bucket holds 4 ms of the rate and at least two full frames; the queue in front of
    // it holds spec.queue_s of the rate (tbf's latency), beyond which tbf drops.
    const long rate = std::lround(spec_.rate_bytes_per_s);
    const long burst = std::max<long>(2 * 1514, std::lround(spec_.rate_bytes_per_s * 0.004));
    const long latency_us = std::lround(spec_.queue_s * 1e6);
    for (const std::string& interface : {interfaces_[1], interfaces_[2]}) {
      CCMD_RETURN_IF_ERROR(
          Run({tc_, "-n", l, "qdisc", "add", "dev", interface, "root", "tbf", "rate",
               std::to_string(rate) + "bps", "burst", std::to_string(burst), "latency",
               std::to_string(latency_us) + "us"}));
    }
  }
  CCMD_ASSIGN_OR_RETURN(
      forwarder_, PacketForwarder::Start(NetnsPath(l), interfaces_[1], interfaces_[2], spec_));
  return Status::Ok();
}

Status NetnsLink::StartWatchdog() {
  // A shell that waits for this process to close (or lose) the pipe, then removes what the
  // run made. It ignores the terminal's signals so that Ctrl-C cannot kill it first.
  std::string script = "trap '' INT TERM HUP QUIT; read _; ";
  for (const std::string& ns : names_) {
    script += "for p in $(" + ip_ + " netns pids " + ns +
              " 2>/dev/null); do kill -9 $p 2>/dev/null; done; " + ip_ + " netns del " + ns +
              " 2>/dev/null; ";
  }
  script += "exit 0";
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) return IoError("pipe: " + std::string(std::strerror(errno)));
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    return IoError("fork: " + std::string(std::strerror(errno)));
  }
  if (pid == 0) {
    ::setsid();
    ::dup2(fds[0], 0);
    const int null = ::open("/dev/null", O_WRONLY);
    if (null >= 0) {
      ::dup2(null, 1);
      ::dup2(null, 2);
    }
    ::execl("/bin/sh", "sh", "-c", script.c_str(), static_cast<char*>(nullptr));
    ::_exit(127);
  }
  ::close(fds[0]);
  watchdog_pid_ = pid;
  watchdog_fd_ = fds[1];
  return Status::Ok();
}

Status NetnsLink::Close() {
  if (closed_) return Status::Ok();
  closed_ = true;
  Status first;
  auto note = [&](const Status& s) {
    if (first.ok() && !s.ok()) first = s;
  };
  if (forwarder_) forwarder_->Stop();
  for (const std::string& ns : names_) {
    if (ns.empty() || !FileExists(NetnsPath(ns))) continue;
    std::string pids;
    RunCapture({ip_, "netns", "pids", ns}, &pids);
    for (const std::string& p : Split(pids, '\n')) {
      auto pid = ParseInt(Trim(p));
      if (pid.ok() && *pid > 0 && *pid != ::getpid()) ::kill(static_cast<pid_t>(*pid), SIGKILL);
    }
    note(Run({ip_, "netns", "del", ns}));
  }
  if (watchdog_fd_ >= 0) {
    ::close(watchdog_fd_);  // the watchdog finds nothing left to do and exits
    watchdog_fd_ = -1;
    int status;
    while (::waitpid(watchdog_pid_, &status, 0) < 0 && errno == EINTR) {
    }
  }
  return first;
}

std::vector<std::string> NetnsLink::Command(Side side, const std::vector<std::string>& argv) const {
  std::vector<std::string> command = {ip_, "netns", "exec", names_[static_cast<int>(side)]};
  command.insert(command.end(), argv.begin(), argv.end());
  return command;
}

Status NetnsLink::RunIn(Side side, const std::function<Status()>& fn) const {
  return RunInNetns(NetnsPath(names_[static_cast<int>(side)]), fn);
}

const std::string& NetnsLink::address(Side side) const {
  return addresses_[static_cast<int>(side)];
}
const std::string& NetnsLink::namespace_name(Side side) const {
  return names_[static_cast<int>(side)];
}

PacketForwarderStats NetnsLink::forwarder_stats() const {
  return forwarder_ ? forwarder_->stats() : PacketForwarderStats{};
}

Json NetnsLink::ToJson() const {
  Json j;
  j["spec"] = spec_.ToString();
  j["agents_namespace"] = names_[0];
  j["link_namespace"] = names_[1];
  j["server_namespace"] = names_[2];
  j["agents_address"] = addresses_[0];
  j["server_address"] = addresses_[2];
  j["forwarder"] = forwarder_stats().ToJson();
  return j;
}

}  // namespace ccmd
