// The shaped evaluation link for real: namespaces, veth pairs, tbf and the forwarding stage
// are built, measured with TCP and UDP traffic, and removed. Needs root (CI has it); skips
// with a notice otherwise.

#include "libccmd/netsim/netns_link.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <arpa/inet.h>
#include <algorithm>
#include <atomic>
#include <fstream>
#include <sstream>
#include <thread>

#include "libccmd/net/socket.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

using Side = NetnsLink::Side;

#define CCMD_REQUIRE_ROOT()                                                          \
  if (::geteuid() != 0) {                                                            \
    GTEST_SKIP() << "not root: network namespaces cannot be created here; skipping"; \
  }

bool NamespaceExists(const std::string& name) { return FileExists("/run/netns/" + name); }

// A TCP connection from the agents' namespace to a listener in the server's.
struct Connection {
  UniqueFd client, server;
};

Connection Connect(const NetnsLink& link) {
  Connection c;
  UniqueFd listener;
  std::uint16_t port = 0;
  EXPECT_TRUE(link.RunIn(Side::kServer,
                         [&]() -> Status {
                           bool loopback;
                           CCMD_ASSIGN_OR_RETURN(
                               listener,
                               ListenTcp(HostPort{link.address(Side::kServer), 0}, 4, &loopback));
                           CCMD_ASSIGN_OR_RETURN(port, LocalPort(listener.get()));
                           return Status::Ok();
                         })
                  .ok());
  EXPECT_TRUE(link.RunIn(Side::kAgents,
                         [&]() -> Status {
                           CCMD_ASSIGN_OR_RETURN(
                               c.client,
                               ConnectTcp(HostPort{link.address(Side::kServer), port}, 10.0));
                           return Status::Ok();
                         })
                  .ok());
  pollfd p{listener.get(), POLLIN, 0};
  EXPECT_EQ(::poll(&p, 1, 10000), 1);
  c.server = UniqueFd(::accept4(listener.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC));
  EXPECT_TRUE(c.server.valid());
  return c;
}

void WriteAll(int fd, const std::uint8_t* data, std::size_t size) {
  while (size > 0) {
    auto n = WriteSome(fd, data, size);
    ASSERT_TRUE(n.ok());
    data += *n;
    size -= *n;
    if (size > 0) {
      pollfd p{fd, POLLOUT, 0};
      ::poll(&p, 1, 1000);
    }
  }
}

void ReadExactly(int fd, std::size_t size) {
  std::uint8_t buffer[256];
  while (size > 0) {
    pollfd p{fd, POLLIN, 0};
    ASSERT_EQ(::poll(&p, 1, 5000), 1);
    auto n = ReadSome(fd, buffer, std::min(size, sizeof(buffer)));
    ASSERT_TRUE(n.ok());
    size -= *n;
  }
}

TEST(NetnsLinkTest, RefusesClearlyWithoutRoot) {
  if (::geteuid() != 0) {
    const Status s = CheckNetnsLinkAvailable();
    EXPECT_EQ(s.code(), StatusCode::kPermissionDenied);
    EXPECT_NE(s.message().find("root"), std::string::npos);
    return;
  }
  // As root: a child drops to an unprivileged user and must be refused.
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    if (::setresuid(65534, 65534, 65534) != 0) ::_exit(2);
    auto link = NetnsLink::Create(*ParseLinkSpec("rate=1mbit"));
    const bool refused = !link.ok() && link.status().code() == StatusCode::kPermissionDenied &&
                         link.status().message().find("root") != std::string::npos;
    ::_exit(refused ? 0 : 1);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
}

TEST(NetnsLinkTest, RateAndDelayAreWhatWasAskedAndEverythingIsRemoved) {
  CCMD_REQUIRE_ROOT();
  auto spec = ParseLinkSpec("rate=2mbit,delay=20ms");
  ASSERT_TRUE(spec.ok());
  std::string names[3];
  {
    auto link = NetnsLink::Create(*spec);
    ASSERT_TRUE(link.ok()) << link.status().ToString();
    for (Side side : {Side::kAgents, Side::kLink, Side::kServer}) {
      names[static_cast<int>(side)] = (*link)->namespace_name(side);
      EXPECT_TRUE(NamespaceExists((*link)->namespace_name(side)));
    }
    Connection c = Connect(**link);
    ASSERT_TRUE(c.client.valid() && c.server.valid());

    // Round trip of one byte each way: the delay is added in each direction.
    std::vector<double> rtts;
    const std::uint8_t byte = 7;
    for (int i = 0; i < 10; ++i) {
      const Stopwatch watch;
      WriteAll(c.client.get(), &byte, 1);
      ReadExactly(c.server.get(), 1);
      WriteAll(c.server.get(), &byte, 1);
      ReadExactly(c.client.get(), 1);
      rtts.push_back(watch.ElapsedSeconds());
    }
    std::sort(rtts.begin(), rtts.end());
    EXPECT_GE(rtts[5], 0.040);
    EXPECT_LT(rtts[5], 0.060);

    // Bulk transfer for 3 s; the rate is measured after the first 0.5 s (slow start).
    std::atomic<bool> stop{false};
    std::thread sender([&] {
      std::vector<std::uint8_t> chunk(16384, 1);
      while (!stop.load()) {
        auto n = WriteSome(c.client.get(), chunk.data(), chunk.size());
        if (!n.ok()) return;
        if (*n == 0) {
          pollfd p{c.client.get(), POLLOUT, 0};
          ::poll(&p, 1, 100);
        }
      }
    });
    std::vector<std::uint8_t> buffer(1 << 16);
    const Stopwatch watch;
    double counted = 0;
    while (watch.ElapsedSeconds() < 3.0) {
      pollfd p{c.server.get(), POLLIN, 0};
      ::poll(&p, 1, 100);
      auto n = ReadSome(c.server.get(), buffer.data(), buffer.size());
      ASSERT_TRUE(n.ok());
      if (watch.ElapsedSeconds() >= 0.5) counted += *n;
    }
    stop.store(true);
    sender.join();
    const double goodput = counted / 2.5;
    // TCP's payload is 1448 of each 1514-byte frame (headers and timestamps); the tbf rate
    // counts whole frames.
    const double wire_rate = goodput * 1514 / 1448;
    EXPECT_NEAR(wire_rate, spec->rate_bytes_per_s, 0.15 * spec->rate_bytes_per_s)
        << "goodput " << goodput << " B/s";
    const PacketForwarderStats stats = (*link)->forwarder_stats();
    EXPECT_GT(stats.uplink.line.left_bytes, counted);
    EXPECT_EQ(stats.uplink.line.lost, 0u);
    ASSERT_TRUE((*link)->Close().ok());
    for (const std::string& name : names) EXPECT_FALSE(NamespaceExists(name)) << name;
  }
}

TEST(NetnsLinkTest, LossIsWhatWasAsked) {
  CCMD_REQUIRE_ROOT();
  auto link = NetnsLink::Create(*ParseLinkSpec("delay=1ms,loss=0.1,seed=3"));
  ASSERT_TRUE(link.ok()) << link.status().ToString();
  // A TCP connection first: both sides learn each other's Ethernet address (retrying what the
  // link loses), so the datagrams below meet only the link's own loss.
  Connection c = Connect(**link);
  ASSERT_TRUE(c.client.valid());
  UniqueFd receiver, sender;
  std::uint16_t port = 0;
  ASSERT_TRUE(
      (*link)
          ->RunIn(Side::kServer,
                  [&]() -> Status {
                    receiver =
                        UniqueFd(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0));
                    const int size = 16 << 20;
                    ::setsockopt(receiver.get(), SOL_SOCKET, SO_RCVBUFFORCE, &size, sizeof(size));
                    sockaddr_in a{};
                    a.sin_family = AF_INET;
                    ::inet_pton(AF_INET, (*link)->address(Side::kServer).c_str(), &a.sin_addr);
                    if (::bind(receiver.get(), reinterpret_cast<sockaddr*>(&a), sizeof(a)) != 0)
                      return IoError("bind");
                    socklen_t len = sizeof(a);
                    ::getsockname(receiver.get(), reinterpret_cast<sockaddr*>(&a), &len);
                    port = ntohs(a.sin_port);
                    return Status::Ok();
                  })
          .ok());
  ASSERT_TRUE((*link)
                  ->RunIn(Side::kAgents,
                          [&]() -> Status {
                            sender = UniqueFd(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
                            return Status::Ok();
                          })
                  .ok());
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_port = htons(port);
  ::inet_pton(AF_INET, (*link)->address(Side::kServer).c_str(), &to.sin_addr);
  constexpr int kDatagrams = 3000;
  const std::vector<std::uint8_t> datagram(200, 5);
  for (int i = 0; i < kDatagrams; ++i) {
    ASSERT_EQ(::sendto(sender.get(), datagram.data(), datagram.size(), 0,
                       reinterpret_cast<sockaddr*>(&to), sizeof(to)),
              200);
  }
  // Count until nothing more can arrive (the link's delay is 1 ms; 1 s of silence ends it).
  int received = 0;
  std::uint8_t buffer[512];
  while (true) {
    pollfd p{receiver.get(), POLLIN, 0};
    if (::poll(&p, 1, 1000) <= 0) break;
    while (::recv(receiver.get(), buffer, sizeof(buffer), 0) > 0) ++received;
  }
  // Binomial: sigma = sqrt(3000 * 0.09) = 16 datagrams; 5 sigma is 82.
  EXPECT_NEAR(received, 0.9 * kDatagrams, 82);
  const PacketForwarderStats stats = (*link)->forwarder_stats();
  EXPECT_NEAR(static_cast<double>(stats.uplink.line.lost) / stats.uplink.line.arrived, 0.1, 0.03);
}

TEST(NetnsLinkTest, WatchdogRemovesEverythingWhenTheOwnerIsKilled) {
  CCMD_REQUIRE_ROOT();
  int fds[2];
  ASSERT_EQ(::pipe2(fds, O_CLOEXEC), 0);  // the programs the child runs do not keep it open
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    ::close(fds[0]);
    auto link = NetnsLink::Create(*ParseLinkSpec("rate=1mbit,delay=5ms"));
    if (!link.ok()) ::_exit(1);
    // A process living in the agents' namespace, as an agent would.
    const pid_t inside = ::fork();
    if (inside == 0) {
      std::vector<std::string> argv = (*link)->Command(Side::kAgents, {"/bin/sleep", "1000"});
      std::vector<char*> args;
      for (auto& a : argv) args.push_back(a.data());
      args.push_back(nullptr);
      ::execv(args[0], args.data());
      ::_exit(127);
    }
    // Report only once the process has entered the namespace: killed before, its `ip netns
    // exec` could enter it after the watchdog listed the namespace's processes, and the
    // escaped `sleep` would hold the test's output open until ctest's timeout.
    struct stat want, have;
    if (::stat(("/run/netns/" + (*link)->namespace_name(Side::kAgents)).c_str(), &want) != 0) {
      ::_exit(1);
    }
    const std::string inside_ns = "/proc/" + std::to_string(inside) + "/ns/net";
    const Stopwatch entering;
    while (::stat(inside_ns.c_str(), &have) != 0 || have.st_ino != want.st_ino ||
           have.st_dev != want.st_dev) {
      if (entering.ElapsedSeconds() > 30) ::_exit(1);
      std::this_thread::sleep_for(std::chrono::milliseconds(5));  // polling another process
    }
    const std::string report =
        (*link)->namespace_name(Side::kAgents) + " " + (*link)->namespace_name(Side::kLink) + " " +
        (*link)->namespace_name(Side::kServer) + " " + std::to_string(inside) + "\n";
    if (::write(fds[1], report.data(), report.size()) < 0) ::_exit(1);
    ::pause();  // until killed
    ::_exit(0);
  }
  ::close(fds[1]);
  std::string report;
  char c;
  while (::read(fds[0], &c, 1) == 1 && c != '\n') report += c;
  ::close(fds[0]);
  std::istringstream in(report);
  std::string names[3];
  int inside = 0;
  in >> names[0] >> names[1] >> names[2] >> inside;
  ASSERT_FALSE(names[2].empty()) << "the child could not build a link";
  for (const std::string& name : names) EXPECT_TRUE(NamespaceExists(name)) << name;
  ASSERT_EQ(::kill(pid, SIGKILL), 0);
  int status;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  // The watchdog notices at once; give it 10 s on a loaded machine.
  const Stopwatch watch;
  auto gone = [&] {
    for (const std::string& name : names) {
      if (NamespaceExists(name)) return false;
    }
    return true;
  };
  while (!gone() && watch.ElapsedSeconds() < 10) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));  // polling an outside process
  }
  EXPECT_TRUE(gone());
  // The process inside was killed (it may linger as a zombie until its new parent reaps it).
  std::ifstream stat("/proc/" + std::to_string(inside) + "/stat");
  std::string text;
  if (std::getline(stat, text)) {
    const std::size_t close = text.rfind(')');
    ASSERT_NE(close, std::string::npos);
    EXPECT_EQ(text.substr(close + 2, 1), "Z");
  }
}

}  // namespace
}  // namespace ccmd
