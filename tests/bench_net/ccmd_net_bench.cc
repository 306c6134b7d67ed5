// ccmd_net_bench: a bounded load test of the transport. N agents (AgentLink, in this
// process) send keyframes of a given size at a given rate (default: the paper's highest,
// 5.5 keyframes/s of about 60 kB) to a real ccmd_server process for a fixed time. Reports
// the server's CPU (from /proc/PID/stat) and memory (VmHWM, VmRSS), and the end-to-end
// latency per message: from Send() on the agent to the acknowledgement that the server has
// journaled (and, by default, synced) it.
//
// Two references are measured in the same run, with the same agents, rate and messages:
//   raw     each agent on its own TCP connection to a minimal in-process receiver that
//           reads each message and answers 8 bytes (no framing, checks, journal or threads)
//   nosync  ccmd_server --no-fsync (journaled, acknowledged after write(), no fdatasync)
// and the results are given as ratios to them. Then the default server twice:
//   fsync   keyless (loopback): frames carry a CRC only
//   key     with a pre-shared key: every frame tagged (protocol version 2); the server's
//           statistics give the CPU time spent on tags and its share of the server's CPU
//
//   ccmd_net_bench [--agents 8] [--seconds 30] [--rate 5.5] [--bytes 60000] [--json OUT]

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/socket.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"
#include "proto/messages.h"
#include "tests/bench_net/bench_keyframe.h"

namespace ccmd {
namespace {

struct Config {
  int agents = 8;
  double seconds = 30;
  double rate = 5.5;
  std::size_t bytes = 60000;
};

struct Result {
  std::string name;
  std::uint64_t messages = 0;
  std::vector<double> latency_ms;
  double server_cpu_percent = 0;  // of one core, over the sending window
  double server_peak_rss_mb = 0;
  double server_rss_mb = 0;
  double seconds = 0;
  // The server's own accounting (stats JSON), averaged over the agents.
  double accounted_bytes_per_s = 0;
  double accounted_keyframe_hz = 0;
  double accounted_keyframe_bytes = 0;
  // With a key: the server's own measure of its CPU time on frame tags, and its share.
  double auth_cpu_seconds = 0;
  double auth_cpu_share = 0;
  double Percentile(double p) const {
    if (latency_ms.empty()) return 0;
    std::vector<double> v = latency_ms;
    const std::size_t k =
        std::min(v.size() - 1, static_cast<std::size_t>(p * (v.size() - 1) + 0.5));
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
    return v[k];
  }
};

struct ProcStats {
  double cpu_seconds = 0;
  double rss_mb = 0, hwm_mb = 0;
};

ProcStats ReadProc(pid_t pid) {
  ProcStats s;
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  const std::size_t close = text.rfind(')');
  if (close != std::string::npos) {
    std::istringstream rest(text.substr(close + 2));
    std::string field;
    // Fields after the command: state(3) ... utime(14) stime(15).
    for (int i = 3; i <= 15 && rest >> field; ++i) {
      if (i == 14 || i == 15) s.cpu_seconds += std::stod(field) / sysconf(_SC_CLK_TCK);
    }
  }
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) s.rss_mb = std::stod(line.substr(6)) / 1024;
    if (line.rfind("VmHWM:", 0) == 0) s.hwm_mb = std::stod(line.substr(6)) / 1024;
  }
  return s;
}

// Starts ccmd_server; returns its pid and port.
bool StartServer(const std::vector<std::string>& extra, pid_t* pid, std::uint16_t* port,
                 const std::string& log_path) {
  std::vector<std::string> args = {CCMD_SERVER_PATH, "--listen", "127.0.0.1:0"};
  args.insert(args.end(), extra.begin(), extra.end());
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  int out[2];
  if (::pipe2(out, O_CLOEXEC) != 0) return false;
  const int log = ::open(log_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  *pid = ::fork();
  if (*pid == 0) {
    ::dup2(out[1], 1);
    ::dup2(log, 2);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(out[1]);
  ::close(log);
  std::string line;
  char c;
  while (::read(out[0], &c, 1) == 1) {
    if (c != '\n') {
      line.push_back(c);
      continue;
    }
    if (line.find("listening on") != std::string::npos) {
      *port = static_cast<std::uint16_t>(std::stoi(line.substr(line.rfind(':') + 1)));
      ::close(out[0]);
      return true;
    }
    line.clear();
  }
  ::close(out[0]);
  return false;
}

// Paces `send` at `rate` per second for `seconds`; each agent starts at a different phase.
template <typename SendFn>
void Pace(const Config& config, int agent, SendFn&& send) {
  const double period = 1.0 / config.rate;
  const auto start = std::chrono::steady_clock::now() +
                     std::chrono::duration<double>(period * agent / config.agents);
  const int count = static_cast<int>(config.seconds * config.rate);
  for (int i = 0; i < count; ++i) {
    std::this_thread::sleep_until(start + std::chrono::duration<double>(period * i));
    send(i);
  }
}

Result RunServer(const Config& config, const std::string& name, bool fsync, bool keyed,
                 const std::vector<std::vector<std::uint8_t>>& messages, const std::string& tmp) {
  Result r;
  r.name = name;
  const std::string journal = tmp + "/journal_" + name;
  pid_t pid = -1;
  std::uint16_t port = 0;
  std::vector<std::string> args = {"--journal",    journal,
                                   "--max-agents", std::to_string(config.agents),
                                   "--log-level",  "warning"};
  const std::string stats_path = tmp + "/stats_" + name + ".json";
  args.push_back("--stats");
  args.push_back(stats_path);
  if (!fsync) args.push_back("--no-fsync");
  const std::string key = "ccmd-net-bench-key-0123456789abcdef";
  if (keyed) {
    const std::string key_path = tmp + "/bench.key";
    if (!WriteFileAtomic(key_path, key).ok()) std::exit(1);
    ::chmod(key_path.c_str(), 0600);
    args.push_back("--psk-file");
    args.push_back(key_path);
  }
  if (!StartServer(args, &pid, &port, tmp + "/server_" + name + ".log")) {
    std::fprintf(stderr, "cannot start ccmd_server\n");
    std::exit(1);
  }
  std::mutex mutex;
  std::vector<std::vector<double>> sent_at(config.agents);
  std::vector<double> latencies;
  std::vector<std::unique_ptr<AgentLink>> links;
  for (int a = 0; a < config.agents; ++a) {
    sent_at[a].resize(static_cast<std::size_t>(config.seconds * config.rate) + 2);
    AgentLinkOptions o;
    o.server = "127.0.0.1:" + std::to_string(port);
    o.name = "bench" + std::to_string(a);
    o.camera = {525, 525, 319.5, 239.5, 640, 480, 5000};
    if (keyed) o.psk = key;
    o.on_acked = [&, a](std::uint64_t first, std::uint64_t last) {
      const double now = MonotonicSeconds();
      std::lock_guard<std::mutex> lock(mutex);
      for (std::uint64_t k = first; k <= last; ++k)
        latencies.push_back((now - sent_at[a][k]) * 1e3);
    };
    links.push_back(AgentLink::Create(o).value());
  }
  const ProcStats before = ReadProc(pid);
  const double t0 = MonotonicSeconds();
  std::vector<std::thread> threads;
  for (int a = 0; a < config.agents; ++a) {
    threads.emplace_back([&, a] {
      Pace(config, a, [&](int i) {
        {
          std::lock_guard<std::mutex> lock(mutex);
          sent_at[a][i + 1] = MonotonicSeconds();
        }
        links[a]->Send(MessageType::kKeyframe, messages[(a * 7 + i) % messages.size()]).value();
      });
    });
  }
  for (auto& t : threads) t.join();
  for (auto& l : links) {
    if (!l->Flush(30).ok()) std::fprintf(stderr, "flush failed\n");
  }
  r.seconds = MonotonicSeconds() - t0;
  const ProcStats after = ReadProc(pid);
  links.clear();
  ::kill(pid, SIGTERM);
  int status;
  ::waitpid(pid, &status, 0);
  r.server_cpu_percent = 100 * (after.cpu_seconds - before.cpu_seconds) / r.seconds;
  r.server_peak_rss_mb = after.hwm_mb;
  r.server_rss_mb = after.rss_mb;
  r.latency_ms = std::move(latencies);
  r.messages = r.latency_ms.size();
  if (StatusOr<Json> stats = ReadJsonFile(stats_path); stats.ok() && stats->Get("agents")) {
    if (const Json* auth = stats->Get("authentication")) {
      r.auth_cpu_seconds = auth->Get("cpu_seconds")->number();
      const Json* share = auth->Get("cpu_share");
      r.auth_cpu_share = share && !share->is_null() ? share->number() : 0;
    }
    const auto& agents = stats->Get("agents")->array();
    for (const Json& a : agents) {
      r.accounted_bytes_per_s += a.Get("average_traffic_bytes_per_s")->number() / agents.size();
      r.accounted_keyframe_hz += a.Get("keyframe_rate_hz")->number() / agents.size();
      r.accounted_keyframe_bytes += a.Get("average_keyframe_bytes")->number() / agents.size();
    }
  }
  return r;
}

// The floor: one TCP connection per agent to a receiver thread that reads each message
// and answers 8 bytes.
Result RunRaw(const Config& config, const std::vector<std::vector<std::uint8_t>>& messages) {
  Result r;
  r.name = "raw";
  bool loopback;
  UniqueFd listener = ListenTcp(HostPort{"127.0.0.1", 0}, 64, &loopback).value();
  const std::uint16_t port = LocalPort(listener.get()).value();
  const std::size_t size = messages[0].size();
  std::vector<std::thread> receivers;
  std::vector<UniqueFd> clients;
  for (int a = 0; a < config.agents; ++a) {
    clients.push_back(ConnectTcp(HostPort{"127.0.0.1", port}, 5).value());
    int fd = -1;
    while (fd < 0) {
      pollfd p{listener.get(), POLLIN, 0};
      ::poll(&p, 1, 1000);
      fd = ::accept4(listener.get(), nullptr, nullptr, SOCK_CLOEXEC);
    }
    receivers.emplace_back([fd, size] {
      std::vector<std::uint8_t> buffer(size);
      const std::uint64_t ack = 1;
      while (true) {
        std::size_t got = 0;
        while (got < size) {
          const ssize_t n = ::read(fd, buffer.data() + got, size - got);
          if (n <= 0) {
            ::close(fd);
            return;
          }
          got += static_cast<std::size_t>(n);
        }
        if (::write(fd, &ack, sizeof(ack)) != sizeof(ack)) break;
      }
      ::close(fd);
    });
  }
  std::mutex mutex;
  std::vector<double> latencies;
  std::vector<std::thread> threads;
  const double t0 = MonotonicSeconds();
  for (int a = 0; a < config.agents; ++a) {
    threads.emplace_back([&, a] {
      const int fd = clients[a].get();
      // Blocking for simplicity: the receiver always drains.
      const int flags = ::fcntl(fd, F_GETFL);
      ::fcntl(fd, F_SETFL, flags & ~O_NONBLOCK);
      Pace(config, a, [&](int i) {
        const auto& m = messages[(a * 7 + i) % messages.size()];
        const double start = MonotonicSeconds();
        std::size_t done = 0;
        while (done < m.size()) {
          const ssize_t n = ::write(fd, m.data() + done, m.size() - done);
          if (n <= 0) return;
          done += static_cast<std::size_t>(n);
        }
        std::uint64_t ack;
        if (::read(fd, &ack, sizeof(ack)) != sizeof(ack)) return;
        std::lock_guard<std::mutex> lock(mutex);
        latencies.push_back((MonotonicSeconds() - start) * 1e3);
      });
    });
  }
  for (auto& t : threads) t.join();
  r.seconds = MonotonicSeconds() - t0;
  clients.clear();
  for (auto& t : receivers) t.join();
  r.latency_ms = std::move(latencies);
  r.messages = r.latency_ms.size();
  return r;
}

}  // namespace
}  // namespace ccmd

int main(int argc, char** argv) {
  using namespace ccmd;
  CLI::App app{"Load test of the transport: N agents at a fixed keyframe rate to ccmd_server."};
  Config config;
  std::string json_path;
  app.add_option("--agents", config.agents, "Agents")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  app.add_option("--seconds", config.seconds, "Sending time per configuration")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--rate", config.rate, "Keyframes per second per agent")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--bytes", config.bytes, "Keyframe message size")->capture_default_str();
  app.add_option("--json", json_path, "Write the results as JSON");
  CLI11_PARSE(app, argc, argv);
  SetMinLogLevel(LogLevel::WARNING);

  char tmp_template[] = "/tmp/ccmd_net_bench_XXXXXX";
  const std::string tmp = ::mkdtemp(tmp_template);
  std::vector<std::vector<std::uint8_t>> messages;
  for (int k = 0; k < 16; ++k) messages.push_back(bench::MakeKeyframe(k + 1, config.bytes));
  std::printf("%d agents x %.1f keyframes/s x %zu bytes for %.0f s (%.0f kB/s in total)\n",
              config.agents, config.rate, messages[0].size(), config.seconds,
              config.agents * config.rate * messages[0].size() / 1e3);

  std::vector<Result> results;
  results.push_back(RunRaw(config, messages));
  results.push_back(RunServer(config, "nosync", false, false, messages, tmp));
  results.push_back(RunServer(config, "fsync", true, false, messages, tmp));
  results.push_back(RunServer(config, "key", true, true, messages, tmp));
  std::system(("rm -rf " + tmp).c_str());

  const Result& raw = results[0];
  std::printf(
      "\n| configuration | messages | latency median ms | p99 ms | max ms | p99 / raw p99 |"
      " server CPU %% of a core | server peak RSS MB |\n|---|---|---|---|---|---|---|---|\n");
  Json out = Json::MakeObject();
  for (const Result& r : results) {
    const double max =
        r.latency_ms.empty() ? 0 : *std::max_element(r.latency_ms.begin(), r.latency_ms.end());
    const bool server = r.name != "raw";
    std::printf("| %s | %llu | %.2f | %.2f | %.2f | %.1f | %s | %s |\n", r.name.c_str(),
                static_cast<unsigned long long>(r.messages), r.Percentile(0.5), r.Percentile(0.99),
                max, r.Percentile(0.99) / raw.Percentile(0.99),
                server ? std::to_string(r.server_cpu_percent).substr(0, 5).c_str() : "-",
                server ? std::to_string(r.server_peak_rss_mb).substr(0, 5).c_str() : "-");
    Json j = Json::MakeObject();
    j["messages"] = r.messages;
    j["latency_median_ms"] = r.Percentile(0.5);
    j["latency_p99_ms"] = r.Percentile(0.99);
    j["latency_max_ms"] = max;
    j["seconds"] = r.seconds;
    if (server) {
      j["server_cpu_percent_of_core"] = r.server_cpu_percent;
      j["server_peak_rss_mb"] = r.server_peak_rss_mb;
      j["server_rss_mb"] = r.server_rss_mb;
    }
    out[r.name] = j;
  }
  std::printf(
      "\nServer accounting (stats JSON, mean over agents; per agent over its connected "
      "time):\n| configuration | traffic kB/s | keyframe rate Hz | keyframe bytes | "
      "tag CPU s | tag share of server CPU |\n|---|---|---|---|---|---|\n");
  for (const Result& r : results) {
    if (r.name == "raw") continue;
    std::printf("| %s | %.1f | %.3f | %.0f | %.3f | %.2f %% |\n", r.name.c_str(),
                r.accounted_bytes_per_s / 1e3, r.accounted_keyframe_hz, r.accounted_keyframe_bytes,
                r.auth_cpu_seconds, 100 * r.auth_cpu_share);
    out[r.name]["auth_cpu_seconds"] = r.auth_cpu_seconds;
    out[r.name]["auth_cpu_share"] = r.auth_cpu_share;
    out[r.name]["accounted_traffic_bytes_per_s"] = r.accounted_bytes_per_s;
    out[r.name]["accounted_keyframe_rate_hz"] = r.accounted_keyframe_hz;
    out[r.name]["accounted_keyframe_bytes"] = r.accounted_keyframe_bytes;
  }
  out["agents"] = config.agents;
  out["rate_hz"] = config.rate;
  out["message_bytes"] = messages[0].size();
  if (!json_path.empty()) {
    if (Status s = WriteJsonFile(out, json_path); !s.ok()) {
      std::fprintf(stderr, "%s\n", s.ToString().c_str());
      return 1;
    }
  }
  const std::uint64_t expected = static_cast<std::uint64_t>(config.agents) *
                                 static_cast<std::uint64_t>(config.seconds * config.rate);
  for (const Result& r : results) {
    if (r.messages != expected) {
      std::fprintf(stderr, "%s: %llu of %llu messages acknowledged\n", r.name.c_str(),
                   static_cast<unsigned long long>(r.messages),
                   static_cast<unsigned long long>(expected));
      return 1;
    }
  }
  return 0;
}
