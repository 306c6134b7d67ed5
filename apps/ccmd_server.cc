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
// code 0. A second signal while that runs exits at once (128 + signal); the journal keeps
// everything acknowledged, and --resume takes the run up from it.

#include <signal.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>
#include <thread>

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

// Everything the command line sets; the runtime's own options are filled in place.
struct ServerArgs {
  ccmd::ServerRuntimeOptions runtime;
  std::string journal, resume, psk_file, stats_path, log_level,
      vocabulary = ccmd::app::DefaultVocabularyPath();
  bool no_dense = false, no_gba = false, dense_every_point = false, no_culling = false,
       no_fsync = false;
  double stats_interval = 5.0;
  ViewFlags view;
};

void AddOptions(CLI::App* app, ServerArgs* a) {
  ccmd::ServerOptions& net = a->runtime.net;
  AddViewOptions(app, &a->view);
  app->add_option("--listen", net.listen, "HOST:PORT to listen on (0.0.0.0:PORT for a LAN)")
      ->capture_default_str();
  app->add_option("--journal", a->journal, "Folder for the per-agent journals (new run)");
  app->add_option("--resume", a->resume,
                  "Folder of an earlier run's journals: replay them, then continue there");
  app->add_option("--psk-file", a->psk_file,
                  "Pre-shared key file (else $CCMD_PSK; without either: loopback only)");
  app->add_option("--max-agents", net.max_agents,
                  "Agents active at once (connected, or gone less than --slot-timeout ago); new "
                  "names are refused while all are, registered agents are always served")
      ->check(CLI::Range(1, 65535))
      ->capture_default_str();
  app->add_option("--slot-timeout", net.slot_timeout_s,
                  "Seconds a disconnected agent keeps its slot before a new name may take it")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app->add_option("--out", a->runtime.output_dir,
                  "Results folder: map.ply, trajectory_fused.txt, trajectory_<agent>.txt, "
                  "server_stats.json, snapshots/ (default: the journal folder's name + .results)");
  app->add_option("--vocabulary", a->vocabulary,
                  "Place-recognition vocabulary (ccmd_vocab); missing: trained online")
      ->capture_default_str();
  app->add_flag("--no-dense", a->no_dense, "Do not build the dense map");
  app->add_flag(
      "--dense-every-point", a->dense_every_point,
      "Keep every back-projected point of every keyframe (no compaction after the filter window: "
      "about 30 bytes a point for the whole run)");
  app->add_flag("--no-global-ba", a->no_gba, "No global bundle adjustment after loops");
  app->add_option("--final-global-ba-max-observations",
                  a->runtime.backend.final_global_ba_max_observations,
                  "On stopping, a map whose latest loop only windowed or abandoned global BAs "
                  "followed is optimised whole if it holds at most this many observations (about "
                  "1 kB each while it solves; 0: never)")
      ->check(CLI::Range(0, 100000000))
      ->capture_default_str();
  app->add_option("--idle-global-ba-seconds", a->runtime.backend.idle_global_ba_seconds,
                  "While running, a map whose agents have sent no keyframe for this long gets "
                  "that whole-map global BA too (same limit; 0: only on stopping)")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app->add_option("--idle-loop-seconds", a->runtime.backend.idle_loop_seconds,
                  "An agent that has sent no keyframe for this long (or whose session ended) gets "
                  "a loop still waiting for its next keyframe checked by both sides' neighbouring "
                  "keyframes instead (0: only when its session ends)")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app->add_flag("--no-culling", a->no_culling,
                "Keep every keyframe's sparse data (no keyframe culling: the sparse maps then grow "
                "with the time spent in a place, not with the place)");
  app->add_option("--culling-keep-recent", a->runtime.backend.culling.keep_recent,
                  "An agent's newest keyframes never culled: at least as many as the agents' local "
                  "maps hold (Tracking.maxKeyframes), whose points they may still link")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app->add_option("--snapshot-interval", a->runtime.snapshot_period_s,
                  "Seconds between dense-map snapshots (0: only at the end)")
      ->capture_default_str();
  app->add_option("--stats", a->stats_path, "Traffic statistics JSON, rewritten periodically");
  app->add_option("--stats-interval", a->stats_interval, "Seconds between statistics writes")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app->add_option("--max-frame-bytes", net.max_payload_bytes, "Largest frame payload")
      ->check(CLI::Range(1024u, 1u << 30))
      ->capture_default_str();
  app->add_option("--handshake-timeout", net.handshake_timeout_s, "Seconds")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app->add_option("--idle-timeout", net.idle_timeout_s,
                  "Seconds without a complete frame before a session is closed")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app->add_option("--frame-timeout", net.frame_timeout_s,
                  "Seconds a frame may take to arrive once its header is in")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app->add_option("--agent-memory", net.per_agent_memory_bytes,
                  "Bytes received from one agent and not yet journaled before reading pauses")
      ->capture_default_str();
  app->add_flag("--no-fsync", a->no_fsync,
                "Acknowledge after write() without fdatasync (survives a process crash, not a "
                "power cut)");
  app->add_option("--log-level", a->log_level, "debug, info, warning or error");
}

// Checks the arguments against each other and completes the runtime's options from them (the
// key, the results folder, the view); the vocabulary is loaded by LoadVocabulary.
ccmd::Status ApplyArgs(ServerArgs* a) {
  ccmd::ServerRuntimeOptions& runtime = a->runtime;
  ccmd::ServerOptions& net = runtime.net;
  if (!a->log_level.empty()) {
    ccmd::LogLevel level;
    if (!ccmd::ParseLogLevel(a->log_level, &level))
      return ccmd::InvalidArgument("unknown log level '" + a->log_level + "'");
    ccmd::SetMinLogLevel(level);
  }
  if (a->journal.empty() && a->resume.empty())
    return ccmd::InvalidArgument("give --journal DIR (a new run) or --resume DIR");
  if (!a->journal.empty() && !a->resume.empty() && a->journal != a->resume) {
    return ccmd::InvalidArgument(
        "--resume continues the journals where they are; give the same folder to --journal, or "
        "leave --journal out");
  }
  net.journal_dir = a->resume.empty() ? a->journal : a->resume;
  net.resume = !a->resume.empty();
  net.fsync = !a->no_fsync;
  // Heartbeat often enough that a quiet agent never looks dead.
  net.heartbeat_interval_s = std::min(net.heartbeat_interval_s, net.idle_timeout_s / 3);
  auto psk = ccmd::ResolvePsk(a->psk_file);
  if (!psk.ok()) return psk.status();
  net.psk = *psk;
  if (runtime.output_dir.empty()) {
    std::string base = net.journal_dir;
    while (base.size() > 1 && base.back() == '/') base.pop_back();
    runtime.output_dir = base + ".results";
  }
  runtime.stats_period_s = a->stats_interval;
  CCMD_RETURN_IF_ERROR(ApplyViewOptions(a->view, &runtime));
  runtime.backend.dense = !a->no_dense;
  runtime.backend.dense_options.compact_keyframes = !a->dense_every_point;
  runtime.backend.global_ba = !a->no_gba;
  runtime.backend.culling.enabled = !a->no_culling;
  return ccmd::Status::Ok();
}

// The vocabulary file if there is one (an unreadable one is an error); without it place
// recognition trains one online.
ccmd::Status LoadVocabulary(const std::string& path, ccmd::PlaceIndexOptions* place) {
  if (path.empty() || !ccmd::FileExists(path)) {
    CCMD_LOG(WARNING) << "no vocabulary at '" << path
                      << "': place recognition trains one online from the first keyframes";
    return ccmd::Status::Ok();
  }
  auto loaded = ccmd::Vocabulary::Load(path);
  if (!loaded.ok()) return loaded.status();
  place->vocabulary = std::make_shared<const ccmd::Vocabulary>(std::move(loaded).value());
  CCMD_LOG(INFO) << "vocabulary " << path << ": " << place->vocabulary->word_count() << " words";
  return ccmd::Status::Ok();
}

// Serves until SIGINT or SIGTERM (blocked in every thread by the caller, waited for here),
// ticking the runtime and rewriting the statistics as it goes.
void ServeUntilStopped(ccmd::ServerRuntime* server, const sigset_t& signals, const ServerArgs& a) {
  // Wake at least once a second for periodic work (statistics, dense snapshots).
  const double tick = std::min(1.0, a.stats_interval);
  double last_stats = ccmd::MonotonicSeconds();
  while (true) {
    timespec wait{};
    wait.tv_sec = static_cast<time_t>(tick);
    wait.tv_nsec = static_cast<long>((tick - std::floor(tick)) * 1e9);
    const int sig = sigtimedwait(&signals, nullptr, &wait);
    if (sig == SIGINT || sig == SIGTERM) {
      CCMD_LOG(INFO) << "stopping on " << (sig == SIGINT ? "SIGINT" : "SIGTERM");
      return;
    }
    server->Tick();
    if (ccmd::MonotonicSeconds() - last_stats >= a.stats_interval) {
      last_stats = ccmd::MonotonicSeconds();
      if (ccmd::Status s = WriteStats(server->TransportStatsJson(), a.stats_path); !s.ok()) {
        CCMD_LOG(WARNING) << "cannot write statistics: " << s.ToString();
      }
    }
  }
}

// From the first stop signal on, another one ends the server at once: the results are then
// not written, but every acknowledged message is in the journal in `journal_dir`. One already
// pending (two signals at once) counts too.
void ExitOnSecondSignal(const sigset_t& signals, const std::string& journal_dir) {
  const auto exit_now = [journal_dir](int sig) {
    std::fprintf(stderr,
                 "ccmd_server: stop signal while stopping: exiting before the results are "
                 "written; everything acknowledged is journaled: ccmd_server --resume %s takes the "
                 "run up again\n",
                 journal_dir.c_str());
    std::_Exit(128 + sig);
  };
  const timespec now{};
  if (const int sig = sigtimedwait(&signals, nullptr, &now); sig > 0) exit_now(sig);
  std::thread([signals, exit_now] {
    int sig = 0;
    if (sigwait(&signals, &sig) == 0) exit_now(sig);
  }).detach();
}

int Refuse(const ccmd::Status& status) {
  std::fprintf(stderr, "ccmd_server: %s\n", status.ToString().c_str());
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "CCMD server: accepts agents over TCP, journals and acknowledges their messages and\n"
      "hands them to the back-end. Without a key it listens on loopback only.\n"
      "Ctrl-C (SIGINT, SIGTERM) stops it and writes the results; a second Ctrl-C exits at once\n"
      "(status 128 + signal); --resume takes the run up again from the journal."};
  ServerArgs args;
  AddOptions(&app, &args);
  CLI11_PARSE(app, argc, argv);
  ccmd::ConfigureAllocatorForLongRuns();  // resident memory that follows the live data
  ccmd::ServerRuntimeOptions& runtime = args.runtime;
  if (ccmd::Status s = ApplyArgs(&args); !s.ok()) return Refuse(s);
  if (ccmd::Status s = LoadVocabulary(args.vocabulary, &runtime.backend.place); !s.ok())
    return Refuse(s);

  // Whoever started us may have closed our stdout after reading the port line: a write to it
  // must not kill the server (the network code never raises SIGPIPE itself).
  signal(SIGPIPE, SIG_IGN);
  // Block the stop signals in every thread; the main thread waits for them below.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  if (ccmd::Status s = runtime.Validate(); !s.ok()) return Refuse(s);
  ccmd::LogOptions("server", runtime);
  auto server = ccmd::ServerRuntime::Create(runtime);
  if (!server.ok()) return Refuse(server.status());
  if (ccmd::Status s = (*server)->Start(); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: %s\n", s.ToString().c_str());
    return 1;
  }
  if (const ccmd::ViewServer* view = (*server)->view())
    std::printf("map view: %s\n", view->url().c_str());
  const std::size_t colon = runtime.net.listen.rfind(':');
  std::printf("ccmd_server: listening on %s:%u\n", runtime.net.listen.substr(0, colon).c_str(),
              unsigned{(*server)->port()});
  std::printf("ccmd_server: results in %s\n", runtime.output_dir.c_str());
  std::fflush(stdout);

  ServeUntilStopped(server->get(), signals, args);
  std::printf(
      "ccmd_server: stopping: finishing the maps and writing the results (a second Ctrl-C exits "
      "at once)\n");
  std::fflush(stdout);
  ExitOnSecondSignal(signals, runtime.net.journal_dir);
  int exit_code = 0;
  if (ccmd::Status s = (*server)->Stop(); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: writing results: %s\n", s.ToString().c_str());
    exit_code = 1;
  }
  if (ccmd::Status s = WriteStats((*server)->TransportStatsJson(), args.stats_path); !s.ok()) {
    std::fprintf(stderr, "ccmd_server: cannot write statistics: %s\n", s.ToString().c_str());
    exit_code = 1;
  }
  std::printf("ccmd_server: results written to %s\n", runtime.output_dir.c_str());
  return exit_code;
}
