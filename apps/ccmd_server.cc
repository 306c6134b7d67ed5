// ccmd_server: accepts agents over TCP, authenticates them with the deployment's pre-shared
// key, journals every message before acknowledging it, and hands the messages to the
// back-end (loop closure, map fusion, optimisation, dense map). Results go to --out.
//
//   ccmd_server --listen 0.0.0.0:7420 --journal run/journal --out run/results --psk-file ccmd.key
//   ccmd_server --resume run/journal --out run/results --psk-file ccmd.key   # after a crash
//
// Prints "ccmd_server: listening on HOST:PORT" on stdout once it serves; with --http, the line
// before it is "map view: http://HOST:PORT/..." (the live map view, docs/view.md).
// SIGINT/SIGTERM stop it cleanly: agents get a bye, everything received is journaled and
// delivered, the back-end finishes, the map, trajectories and statistics are written, exit
// code 0.

#include <signal.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>

#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/util/file_util.h"

#include "apps/app_common.h"
#include "libccmd/net/psk.h"
#include "libccmd/system/server_runtime.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/process_usage.h"
#include "libccmd/util/timer.h"

namespace {

ccmd::Status WriteStats(const ccmd::Json& json, const std::string& path) {
  if (path.empty()) return ccmd::Status::Ok();
  return ccmd::WriteJsonFile(json, path);
}

// The live map view's options (off unless --http is given).
struct ViewFlags {
  std::string http, token;
};

void AddViewOptions(CLI::App* app, ViewFlags* flags) {
  app->add_option(
      "--http", flags->http,
      "Serve the live map view (a web page) on HOST:PORT, e.g. 127.0.0.1:8080; a host other than "
      "loopback needs a token (one is made up and printed if --http-token is not given)");
  app->add_option("--http-token", flags->token,
                  "Access token of the map view (letters, digits, - _ .); the URL printed at "
                  "start-up carries it");
}

ccmd::Status ApplyViewOptions(const ViewFlags& flags, ccmd::ServerRuntimeOptions* runtime) {
  if (flags.http.empty()) {
    return flags.token.empty() ? ccmd::Status::Ok()
                               : ccmd::InvalidArgument("--http-token needs --http HOST:PORT");
  }
  ccmd::ViewServerOptions view;
  view.listen = flags.http;
  view.token = flags.token;
  view.web_dir = ccmd::app::WebDir();
  runtime->view = view;
  return view.Validate();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "CCMD server: accepts agents over TCP, journals and acknowledges their messages and\n"
      "hands them to the back-end. Without a key it listens on loopback only."};
  ccmd::ServerRuntimeOptions runtime;
  ccmd::ServerOptions& options = runtime.net;
  std::string journal, resume, psk_file, stats_path,
      vocabulary = ccmd::app::DefaultVocabularyPath();
  bool no_dense = false, no_gba = false, dense_every_point = false, no_culling = false;
  double stats_interval = 5.0;
  bool no_fsync = false;
  std::string log_level;
  ViewFlags view_flags;
  AddViewOptions(&app, &view_flags);
  app.add_option("--listen", options.listen, "HOST:PORT to listen on (0.0.0.0:PORT for a LAN)")
      ->capture_default_str();
  app.add_option("--journal", journal, "Folder for the per-agent journals (new run)");
  app.add_option("--resume", resume,
                 "Folder of an earlier run's journals: replay them, then continue there");
  app.add_option("--psk-file", psk_file,
                 "Pre-shared key file (else $CCMD_PSK; without either: loopback only)");
  app.add_option("--max-agents", options.max_agents,
                 "Agents active at once (connected, or gone less than --slot-timeout ago); new "
                 "names are refused while all are, registered agents are always served")
      ->check(CLI::Range(1, 65535))
      ->capture_default_str();
  app.add_option("--slot-timeout", options.slot_timeout_s,
                 "Seconds a disconnected agent keeps its slot before a new name may take it")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--out", runtime.output_dir,
                 "Results folder: map.ply, trajectory_fused.txt, trajectory_<agent>.txt, "
                 "server_stats.json, snapshots/ (default: the journal folder's name + .results)");
  app.add_option("--vocabulary", vocabulary,
                 "Place-recognition vocabulary (ccmd_vocab); missing: trained online")
      ->capture_default_str();
  app.add_flag("--no-dense", no_dense, "Do not build the dense map");
  app.add_flag(
      "--dense-every-point", dense_every_point,
      "Keep every back-projected point of every keyframe (no compaction after the filter window: "
      "about 30 bytes a point for the whole run)");
  app.add_flag("--no-global-ba", no_gba, "No global bundle adjustment after loops");
  app.add_flag("--no-culling", no_culling,
               "Keep every keyframe's sparse data (no keyframe culling: the sparse maps then grow "
               "with the time spent in a place, not with the place)");
  app.add_option("--culling-keep-recent", runtime.backend.culling.keep_recent,
                 "An agent's newest keyframes never culled: at least as many as the agents' local "
                 "maps hold (Tracking.maxKeyframes), whose points they may still link")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--snapshot-interval", runtime.snapshot_period_s,
                 "Seconds between dense-map snapshots (0: only at the end)")
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
  app.add_option("--idle-timeout", options.idle_timeout_s,
                 "Seconds without a complete frame before a session is closed")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--frame-timeout", options.frame_timeout_s,
                 "Seconds a frame may take to arrive once its header is in")
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
  ccmd::ConfigureAllocatorForLongRuns();  // resident memory that follows the live data

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

  if (runtime.output_dir.empty()) {
    std::string base = options.journal_dir;
    while (base.size() > 1 && base.back() == '/') base.pop_back();
    runtime.output_dir = base + ".results";
  }
  runtime.stats_period_s = stats_interval;
  if (ccmd::Status s = ApplyViewOptions(view_flags, &runtime); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", s.ToString().c_str());
    return 2;
  }
  runtime.backend.dense = !no_dense;
  runtime.backend.dense_options.compact_keyframes = !dense_every_point;
  runtime.backend.global_ba = !no_gba;
  runtime.backend.culling.enabled = !no_culling;
  if (!vocabulary.empty() && ccmd::FileExists(vocabulary)) {
    auto loaded = ccmd::Vocabulary::Load(vocabulary);
    if (!loaded.ok()) {
      std::fprintf(stderr, "ccmd_server: %s\n", loaded.status().ToString().c_str());
      return 2;
    }
    runtime.backend.place.vocabulary =
        std::make_shared<const ccmd::Vocabulary>(std::move(loaded).value());
    CCMD_LOG(INFO) << "vocabulary " << vocabulary << ": "
                   << runtime.backend.place.vocabulary->word_count() << " words";
  } else {
    CCMD_LOG(WARNING) << "no vocabulary at '" << vocabulary
                      << "': place recognition trains one online from the first keyframes";
  }

  // Whoever started us may have closed our stdout after reading the port line: a write to it
  // must not kill the server (the network code never raises SIGPIPE itself).
  signal(SIGPIPE, SIG_IGN);
  // Block the stop signals in every thread; the main thread waits for them below.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  if (const ccmd::Status valid = runtime.Validate(); !valid.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", valid.ToString().c_str());
    return 2;
  }
  ccmd::LogOptions("server", runtime);
  auto server = ccmd::ServerRuntime::Create(runtime);
  if (!server.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", server.status().ToString().c_str());
    return 2;
  }
  if (ccmd::Status s = (*server)->Start(); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", s.ToString().c_str());
    return 1;
  }
  if (const ccmd::ViewServer* view = (*server)->view())
    std::printf("map view: %s\n", view->url().c_str());
  const std::size_t colon = options.listen.rfind(':');
  std::printf("ccmd_server: listening on %s:%u\n", options.listen.substr(0, colon).c_str(),
              unsigned{(*server)->port()});
  std::printf("ccmd_server: results in %s\n", runtime.output_dir.c_str());
  std::fflush(stdout);

  int exit_code = 0;
  // Wake at least once a second for periodic work (statistics, dense snapshots).
  const double tick = std::min(1.0, stats_interval);
  double last_stats = ccmd::MonotonicSeconds();
  while (true) {
    timespec wait{};
    wait.tv_sec = static_cast<time_t>(tick);
    wait.tv_nsec = static_cast<long>((tick - std::floor(tick)) * 1e9);
    const int sig = sigtimedwait(&signals, nullptr, &wait);
    if (sig == SIGINT || sig == SIGTERM) {
      CCMD_LOG(INFO) << "stopping on " << (sig == SIGINT ? "SIGINT" : "SIGTERM");
      break;
    }
    (*server)->Tick();
    if (ccmd::MonotonicSeconds() - last_stats >= stats_interval) {
      last_stats = ccmd::MonotonicSeconds();
      if (ccmd::Status s = WriteStats((*server)->TransportStatsJson(), stats_path); !s.ok()) {
        CCMD_LOG(WARNING) << "cannot write statistics: " << s.ToString();
      }
    }
  }
  if (ccmd::Status s = (*server)->Stop(); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: writing results: %s\n", s.ToString().c_str());
    exit_code = 1;
  }
  if (ccmd::Status s = WriteStats((*server)->TransportStatsJson(), stats_path); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: cannot write statistics: %s\n", s.ToString().c_str());
    exit_code = 1;
  }
  std::printf("ccmd_server: results written to %s\n", runtime.output_dir.c_str());
  return exit_code;
}
