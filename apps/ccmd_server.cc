// ccmd_server: accepts agents over TCP, authenticates them with the deployment's pre-shared
// key, journals every message before acknowledging it, and hands the messages to the
// back-end. For now the back-end is a consumer that counts and logs.
//
//   ccmd_server --listen 0.0.0.0:7420 --journal run/journal --psk-file ccmd.key --stats s.json
//   ccmd_server --resume run/journal --psk-file ccmd.key      # after a crash or a stop
//
// Prints "ccmd_server: listening on HOST:PORT" on stdout once it serves. SIGINT/SIGTERM stop
// it cleanly: agents get a bye, everything received is journaled and delivered, the stats
// file is written, exit code 0.

#include <signal.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>

#include "apps/app_common.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/server.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace {

// Stand-in for the back-end: counts what it is given and logs the agents' sessions.
class CountingConsumer : public ccmd::MessageConsumer {
 public:
  void OnAgentKnown(const ccmd::AgentDescription& agent, bool from_journal) override {
    CCMD_LOG(INFO) << "back-end: agent " << agent.id << " '" << agent.name << "' "
                   << (from_journal ? "restored from the journal" : "is new") << " ("
                   << ccmd::DescribeCamera(agent.camera) << ")";
  }
  void OnAgentConnected(ccmd::AgentId agent, std::uint64_t last) override {
    CCMD_LOG(DEBUG) << "back-end: agent " << agent << " session, stored up to " << last;
  }
  void OnAgentDisconnected(ccmd::AgentId agent, const std::string& reason) override {
    std::lock_guard<std::mutex> lock(mutex_);
    CCMD_LOG(INFO) << "back-end: agent " << agent << " left (" << reason << "); " << counts_[agent]
                   << " messages so far";
  }
  void OnMessage(ccmd::DeliveredMessage m) override {
    std::lock_guard<std::mutex> lock(mutex_);
    ++counts_[m.agent];
    CCMD_LOG(DEBUG) << "back-end: agent " << m.agent << " message " << m.seq << " type "
                    << int{m.type} << ", " << m.payload.size() << " bytes";
  }
  void OnReplayFinished(std::uint64_t n) override {
    CCMD_LOG(INFO) << "back-end: journal replay delivered " << n << " messages";
  }

 private:
  std::mutex mutex_;
  std::map<ccmd::AgentId, std::uint64_t> counts_;
};

ccmd::Status WriteStats(const ccmd::Server& server, const std::string& path) {
  if (path.empty()) return ccmd::Status::Ok();
  return ccmd::WriteJsonFile(server.StatsJson(), path);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "CCMD server: accepts agents over TCP, journals and acknowledges their messages and\n"
      "hands them to the back-end. Without a key it listens on loopback only."};
  ccmd::ServerOptions options;
  std::string journal, resume, psk_file, stats_path;
  double stats_interval = 5.0;
  bool no_fsync = false;
  std::string log_level;
  app.add_option("--listen", options.listen, "HOST:PORT to listen on (0.0.0.0:PORT for a LAN)")
      ->capture_default_str();
  app.add_option("--journal", journal, "Folder for the per-agent journals (new run)");
  app.add_option("--resume", resume,
                 "Folder of an earlier run's journals: replay them, then continue there");
  app.add_option("--psk-file", psk_file,
                 "Pre-shared key file (else $CCMD_PSK; without either: loopback only)");
  app.add_option("--max-agents", options.max_agents, "Agents the server registers")
      ->check(CLI::Range(1, 65535))
      ->capture_default_str();
  app.add_option("--stats", stats_path, "Traffic statistics JSON, rewritten periodically");
  app.add_option("--stats-interval", stats_interval, "Seconds between statistics writes")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--max-frame-bytes", options.max_payload_bytes, "Largest frame payload")
      ->check(CLI::Range(1024u, 1u << 30))
      ->capture_default_str();
  app.add_option("--handshake-timeout", options.handshake_timeout_s, "Seconds")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--idle-timeout", options.idle_timeout_s, "Seconds")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--agent-memory", options.per_agent_memory_bytes,
                 "Bytes received from one agent and not yet journaled before reading pauses")
      ->capture_default_str();
  app.add_flag("--no-fsync", no_fsync,
               "Acknowledge after write() without fdatasync (survives a process crash, not a "
               "power cut)");
  app.add_option("--log-level", log_level, "debug, info, warning or error");
  CLI11_PARSE(app, argc, argv);

  if (!log_level.empty()) {
    ccmd::LogLevel level;
    if (!ccmd::ParseLogLevel(log_level, &level)) {
      std::fprintf(stderr, "ccmd_server: unknown log level '%s'\n", log_level.c_str());
      return 2;
    }
    ccmd::SetMinLogLevel(level);
  }
  if (journal.empty() && resume.empty()) {
    std::fprintf(stderr, "ccmd_server: give --journal DIR (a new run) or --resume DIR\n");
    return 2;
  }
  if (!journal.empty() && !resume.empty() && journal != resume) {
    std::fprintf(stderr,
                 "ccmd_server: --resume continues the journals where they are; give the same "
                 "folder to --journal, or leave --journal out\n");
    return 2;
  }
  options.journal_dir = resume.empty() ? journal : resume;
  options.resume = !resume.empty();
  options.fsync = !no_fsync;
  // Heartbeat often enough that a quiet agent never looks dead.
  options.heartbeat_interval_s = std::min(options.heartbeat_interval_s, options.idle_timeout_s / 3);
  auto psk = ccmd::ResolvePsk(psk_file);
  if (!psk.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", psk.status().ToString().c_str());
    return 2;
  }
  options.psk = *psk;

  // Block the stop signals in every thread; the main thread waits for them below.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  CountingConsumer consumer;
  ccmd::Server server(options, &consumer);
  if (ccmd::Status s = server.Start(); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", s.ToString().c_str());
    return 1;
  }
  const std::size_t colon = options.listen.rfind(':');
  std::printf("ccmd_server: listening on %s:%u\n", options.listen.substr(0, colon).c_str(),
              unsigned{server.port()});
  std::fflush(stdout);

  int exit_code = 0;
  while (true) {
    timespec wait{};
    wait.tv_sec = static_cast<time_t>(stats_interval);
    wait.tv_nsec = static_cast<long>((stats_interval - std::floor(stats_interval)) * 1e9);
    const int sig = sigtimedwait(&signals, nullptr, &wait);
    if (sig == SIGINT || sig == SIGTERM) {
      CCMD_LOG(INFO) << "stopping on " << (sig == SIGINT ? "SIGINT" : "SIGTERM");
      break;
    }
    if (ccmd::Status s = WriteStats(server, stats_path); !s.ok()) {
      CCMD_LOG(WARNING) << "cannot write statistics: " << s.ToString();
    }
  }
  server.Stop();
  if (ccmd::Status s = WriteStats(server, stats_path); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: cannot write statistics: %s\n", s.ToString().c_str());
    exit_code = 1;
  }
  return exit_code;
}
