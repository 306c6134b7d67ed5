// ccmd_replay: split-replay evaluation. Splits a sequence into K segments with 10% overlap,
// runs a ccmd_server and K ccmd_agent processes talking over real TCP on loopback (or, with
// --link, over a shaped link between network namespaces made for the run), shows progress,
// then evaluates what they produced: trajectories (ATE), dense map (reconstruction error),
// bandwidth, map latency, CPU. Writes results.json, report.md and plots in the output folder.

#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <thread>

#include "apps/app_common.h"
#include "libccmd/io/config.h"
#include "libccmd/io/split.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/netsim/netns_link.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/system/link_report.h"
#include "libccmd/system/replay_report.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/string_util.h"
#include "libccmd/util/subprocess.h"
#include "libccmd/util/timer.h"

namespace {

using namespace ccmd;

// Set by SIGINT/SIGTERM/SIGHUP during a --link run: the run stops its processes and removes
// its namespaces instead of leaving them behind.
std::atomic<bool> g_interrupted{false};
// Whether the terminal sent it (Ctrl-C, a closed terminal): it went to the whole foreground
// process group, the agents and the server included.
std::atomic<bool> g_interrupt_reached_children{false};
void OnSignal(int, siginfo_t* info, void*) {
  g_interrupt_reached_children = info->si_code == SI_KERNEL;
  g_interrupted = true;
}

// How long agents asked to stop at the time-out may take before they are ended.
constexpr double kStopGraceSeconds = 60;

int Fail(const std::string& what) {
  std::fprintf(stderr, "ccmd_replay: %s\n", what.c_str());
  return 1;
}

std::string ExecutableDir() {
  char path[4096] = {0};
  const ssize_t n = ::readlink("/proc/self/exe", path, sizeof(path) - 1);
  if (n <= 0) return ".";
  std::string p(path, static_cast<std::size_t>(n));
  return p.substr(0, p.find_last_of('/'));
}

std::string Tail(const std::string& path, int lines) {
  auto text = ReadFileToString(path, 1 << 26);
  if (!text.ok()) return "";
  const std::vector<std::string> all = Split(*text, '\n');
  std::string out;
  for (std::size_t i = all.size() > static_cast<std::size_t>(lines) ? all.size() - lines : 0;
       i < all.size(); ++i) {
    out += "    " + all[i] + "\n";
  }
  return out;
}

struct Tracked {
  Tracked(std::string name, Subprocess process, double started)
      : name(std::move(name)), process(std::move(process)), started(started) {}
  std::string name;
  Subprocess process;
  double started = 0, ended = -1;
  double last_cpu = 0, last_time = 0;
  ProcessResult result;
  std::vector<std::pair<double, double>> cpu_percent;
};

// --view: the server serves the live map view on loopback (docs/view.md).
struct ViewSetup {
  bool enabled = false;
  int port = 0;  // 0: a free port
};

std::vector<std::string> ViewServerArgs(const ViewSetup& view) {
  if (!view.enabled) return {};
  return {"--http", "127.0.0.1:" + std::to_string(view.port)};
}

// The server's "map view: URL" line, shown to the user as soon as the server prints it.
void ShowViewAddress(const std::string& line) {
  if (line.rfind("map view: ", 0) != 0) return;
  std::printf("%s  (open it in a browser to watch the map being built)\n", line.c_str());
  std::fflush(stdout);
}

// Everything a run needs, the same for every run of an ablation.
struct Setup {
  std::string dataset, camera_config, rate, bin_dir, command;
  int agents = 0;
  double timeout_s = 0;
  std::vector<std::string> agent_args, server_args;
  const TumSequence* sequence = nullptr;
  std::vector<FrameRange> segments;
  ReferenceOptions reference;
  std::optional<LinkSpec> link;  // none: loopback
  std::string link_text;         // as given
  ViewSetup view;
};

// Where a run's processes talk: loopback, or a shaped link between network namespaces that
// exist for this run only (the server in one, the agents in another). Over the link the
// server is not on loopback, so the run makes a random key for itself.
struct RunNetwork {
  std::unique_ptr<NetnsLink> link;
  std::string server_host = "127.0.0.1";
  std::vector<std::string> key_args;

  static StatusOr<RunNetwork> Open(const Setup& setup, const std::string& out) {
    RunNetwork n;
    if (!setup.link) return n;
    CCMD_ASSIGN_OR_RETURN(n.link, NetnsLink::Create(*setup.link));
    n.server_host = n.link->address(NetnsLink::Side::kServer);
    std::ifstream urandom("/dev/urandom", std::ios::binary);
    char random[32];
    if (!urandom.read(random, sizeof(random)))
      return IoError("cannot read /dev/urandom for the run's key");
    std::string key;
    for (const char c : random) {
      key += "0123456789abcdef"[(static_cast<unsigned char>(c) >> 4) & 15];
      key += "0123456789abcdef"[static_cast<unsigned char>(c) & 15];
    }
    const std::string path = JoinPath(out, "logs/link.key");
    CCMD_RETURN_IF_ERROR(WriteFileAtomic(path, key + "\n"));
    ::chmod(path.c_str(), 0600);
    n.key_args = {"--psk-file", path};
    return n;
  }
  std::vector<std::string> In(NetnsLink::Side side, std::vector<std::string> argv) const {
    argv.insert(argv.end(), key_args.begin(), key_args.end());
    return link ? link->Command(side, argv) : argv;
  }
};

// One split replay into `out`: server and agents, progress, evaluation. `failures` counts the
// processes that failed (the run is still evaluated, from what they left).
StatusOr<Json> RunOnce(const Setup& setup, const std::string& out,
                       const std::vector<std::string>& extra_agent_args, int* failures) {
  for (const char* sub : {"agents", "logs", "plots"}) {
    const Status s = MakeDirectories(JoinPath(out, sub));
    if (!s.ok()) return s;
  }
  if (FileExists(JoinPath(out, "journal"))) {
    return InvalidArgument(out + " already holds a run (journal/): choose a new --out folder");
  }
  WriteFileAtomic(JoinPath(out, "command.txt"), setup.command + "\n").IgnoreError();
  if (!setup.camera_config.empty()) {
    auto text = ReadFileToString(setup.camera_config);
    if (text.ok()) WriteFileAtomic(JoinPath(out, "config.yaml"), *text).IgnoreError();
  }

  if (g_interrupted) return Cancelled("interrupted");
  CCMD_ASSIGN_OR_RETURN(const RunNetwork network, RunNetwork::Open(setup, out));
  if (network.link) {
    std::printf("link %s: namespaces %s, %s, %s\n", setup.link_text.c_str(),
                network.link->namespace_name(NetnsLink::Side::kAgents).c_str(),
                network.link->namespace_name(NetnsLink::Side::kLink).c_str(),
                network.link->namespace_name(NetnsLink::Side::kServer).c_str());
    std::fflush(stdout);
  }
  // Server on a free port; it prints the port once it serves.
  const Stopwatch wall;
  std::vector<std::string> server_argv = {JoinPath(setup.bin_dir, "ccmd_server"),
                                          "--listen",
                                          network.server_host + ":0",
                                          "--journal",
                                          JoinPath(out, "journal"),
                                          "--out",
                                          out,
                                          "--stats-interval",
                                          "1"};
  server_argv.insert(server_argv.end(), setup.server_args.begin(), setup.server_args.end());
  for (const std::string& arg : ViewServerArgs(setup.view)) server_argv.push_back(arg);
  auto server_process = Subprocess::Start(network.In(NetnsLink::Side::kServer, server_argv), "",
                                          JoinPath(out, "logs/server.log"), /*pipe_stdout=*/true);
  if (!server_process.ok())
    return Unavailable("cannot start ccmd_server: " + server_process.status().ToString());
  Tracked server{"server", std::move(server_process).value(), 0};
  std::string port;
  while (port.empty()) {
    auto line = server.process.ReadLine(120);
    if (!line.ok()) {
      return Unavailable("ccmd_server did not start (" + line.status().ToString() +
                         "); its log:\n" + Tail(JoinPath(out, "logs/server.log"), 20));
    }
    ShowViewAddress(*line);
    const auto at = line->find("listening on ");
    if (at != std::string::npos) port = line->substr(line->find_last_of(':') + 1);
  }
  server.process.DrainStdoutTo(JoinPath(out, "logs/server.out"));
  const std::string address = network.server_host + ":" + port;

  std::vector<Tracked> agent_processes;
  for (int i = 1; i <= setup.agents; ++i) {
    const std::string name = "agent" + std::to_string(i);
    std::vector<std::string> a = {JoinPath(setup.bin_dir, "ccmd_agent"),
                                  "--source",
                                  "tum:" + setup.dataset,
                                  "--segment",
                                  std::to_string(i) + "/" + std::to_string(setup.agents),
                                  "--server",
                                  address,
                                  "--name",
                                  name,
                                  "--stats",
                                  JoinPath(out, "agents/" + name + "_stats.json"),
                                  "--trajectory",
                                  JoinPath(out, "agents/" + name + "_frames.txt"),
                                  "--progress",
                                  JoinPath(out, "agents/" + name + "_progress.json"),
                                  "--rate",
                                  setup.rate,
                                  "--spill-dir",
                                  JoinPath(out, "agents/" + name + "_spill")};
    if (!setup.camera_config.empty()) {
      a.push_back("--config");
      a.push_back(setup.camera_config);
    }
    a.insert(a.end(), setup.agent_args.begin(), setup.agent_args.end());
    a.insert(a.end(), extra_agent_args.begin(), extra_agent_args.end());
    auto p = Subprocess::Start(network.In(NetnsLink::Side::kAgents, a),
                               JoinPath(out, "logs/" + name + ".out"),
                               JoinPath(out, "logs/" + name + ".log"));
    if (!p.ok()) return Unavailable("cannot start ccmd_agent: " + p.status().ToString());
    agent_processes.emplace_back(name, std::move(p).value(), wall.ElapsedSeconds());
  }

  // Progress, once a second, until every agent is done.
  const bool tty = ::isatty(1);
  int& failed = *failures;
  std::vector<std::array<double, 3>> server_memory;  // ReplayRunInfo::server_memory
  auto sample_cpu = [&](Tracked* t) {
    const double now = wall.ElapsedSeconds();
    const double cpu = t->process.CpuSecondsSoFar();
    if (now > t->last_time)
      t->cpu_percent.emplace_back(now, 100 * (cpu - t->last_cpu) / (now - t->last_time));
    t->last_cpu = cpu;
    t->last_time = now;
  };
  bool timed_out = false, forced = false;
  while (true) {
    int running = 0;
    for (Tracked& a : agent_processes) {
      if (a.ended >= 0) continue;
      sample_cpu(&a);
      if (a.process.Poll(&a.result)) {
        a.ended = wall.ElapsedSeconds();
        if (a.result.exit_code != 0) {
          ++failed;
          std::fprintf(stderr, "\n%s failed (exit %d, signal %d); its log ends:\n%s",
                       a.name.c_str(), a.result.exit_code, a.result.signal,
                       Tail(JoinPath(out, "logs/" + a.name + ".log"), 15).c_str());
        }
      } else {
        ++running;
      }
    }
    sample_cpu(&server);
    std::string line;
    for (const Tracked& a : agent_processes) {
      auto p = ReadJsonFile(JoinPath(out, "agents/" + a.name + "_progress.json"));
      char part[160];
      if (p.ok()) {
        const Json* link = p->Get("link");
        std::snprintf(
            part, sizeof(part), "%s %d/%d fr %d kf %.0f kB | ", a.name.c_str(),
            static_cast<int>(p->Get("frames") ? p->Get("frames")->number() : 0),
            static_cast<int>(p->Get("total_frames") ? p->Get("total_frames")->number() : 0),
            static_cast<int>(
                link && link->Get("keyframes_sent") ? link->Get("keyframes_sent")->number() : 0),
            link && link->Get("keyframe_bytes") ? link->Get("keyframe_bytes")->number() / 1e3
                                                : 0.0);
      } else {
        std::snprintf(part, sizeof(part), "%s starting | ", a.name.c_str());
      }
      line += a.ended >= 0 ? a.name + " done | " : part;
    }
    auto s = ReadJsonFile(JoinPath(out, "server_stats.json"));
    if (s.ok() && s->Get("backend")) {
      const Json* b = s->Get("backend");
      char part[160];
      std::snprintf(part, sizeof(part), "server: %d keyframes, loops %d, fusions %d, maps %d",
                    static_cast<int>(b->Get("keyframes") ? b->Get("keyframes")->number() : 0),
                    static_cast<int>(b->Get("loops") ? b->Get("loops")->number() : 0),
                    static_cast<int>(b->Get("fusions") ? b->Get("fusions")->number() : 0),
                    static_cast<int>(b->Get("maps") ? b->Get("maps")->number() : 0));
      line += part;
      const Json* process = s->Get("process");
      if (process && process->Get("rss_mb") && b->Get("keyframes")) {
        server_memory.push_back({wall.ElapsedSeconds(), b->Get("keyframes")->number(),
                                 process->Get("rss_mb")->number()});
      }
    }
    if (tty) {
      std::printf("\r%-150s", line.c_str());
    } else {
      std::printf("%.0f s  %s\n", wall.ElapsedSeconds(), line.c_str());
    }
    std::fflush(stdout);
    if (running == 0) break;
    if (g_interrupted) {
      std::fprintf(stderr,
                   "\nccmd_replay: interrupted; stopping the processes and removing the link\n");
      // A Ctrl-C at the terminal reached them already; a second signal would end them at once.
      if (!g_interrupt_reached_children) {
        for (Tracked& a : agent_processes) a.process.Signal(SIGINT).IgnoreError();
        server.process.Signal(SIGINT).IgnoreError();
      }
      return Cancelled("interrupted");
    }
    // At the time-out the agents are asked to stop cleanly; those still running a grace
    // period later get the second signal, which ends an agent at once.
    const double over = wall.ElapsedSeconds() - setup.timeout_s;
    if (over > 0 && !timed_out) {
      timed_out = true;
      ++failed;
      std::fprintf(stderr, "\nccmd_replay: time-out after %.0f s, stopping the agents\n",
                   setup.timeout_s);
      for (Tracked& a : agent_processes) a.process.Signal(SIGINT).IgnoreError();
    } else if (over > kStopGraceSeconds && !forced) {
      forced = true;
      std::fprintf(stderr,
                   "\nccmd_replay: agents still running %.0f s after the time-out, ending them\n",
                   kStopGraceSeconds);
      for (Tracked& a : agent_processes) {
        if (a.ended < 0) a.process.Signal(SIGINT).IgnoreError();
      }
    }
    // A refresh period for the display and the CPU samples, not synchronisation: the loop
    // ends on the children's exit status.
    std::this_thread::sleep_for(std::chrono::seconds(1));
  }
  if (tty) std::printf("\n");

  // The server writes its results when told to stop.
  std::printf(
      "agents done after %.1f s; stopping the server (it finishes optimisation and writes the "
      "map)\n",
      wall.ElapsedSeconds());
  std::fflush(stdout);
  server.process.Signal(SIGINT).IgnoreError();
  server.result = server.process.Wait();
  server.ended = wall.ElapsedSeconds();
  if (server.result.exit_code != 0) {
    ++failed;
    std::fprintf(stderr, "ccmd_server failed (exit %d, signal %d); its log ends:\n%s",
                 server.result.exit_code, server.result.signal,
                 Tail(JoinPath(out, "logs/server.log"), 20).c_str());
  }

  ReplayRunInfo info;
  info.dataset_dir = setup.dataset;
  info.command = setup.command;
  info.config = setup.camera_config;
  info.agents = setup.agents;
  info.rate = setup.rate;
  info.wall_seconds = wall.ElapsedSeconds();
  info.segments = setup.segments;
  if (network.link) {
    info.link = setup.link_text;
    info.link_stats = network.link->ToJson();
    const Status closed = network.link->Close();
    if (!closed.ok())
      std::fprintf(stderr, "ccmd_replay: removing the link: %s\n", closed.ToString().c_str());
  }
  info.server_memory = std::move(server_memory);
  for (Tracked* t : [&] {
         std::vector<Tracked*> all;
         for (Tracked& a : agent_processes) all.push_back(&a);
         all.push_back(&server);
         return all;
       }()) {
    ReplayProcess p;
    p.name = t->name;
    p.cpu_seconds = t->result.cpu_seconds;
    p.wall_seconds = t->ended - t->started;
    p.max_rss_mb = t->result.max_rss_mb;
    p.exit_code = t->result.exit_code;
    p.cpu_percent = t->cpu_percent;
    info.processes.push_back(p);
  }
  std::printf("evaluating...\n");
  std::fflush(stdout);
  LogOptions("reference", setup.reference);
  return EvaluateReplay(out, *setup.sequence, info, setup.reference);
}

// --budgets: the same replay once per budget, every agent under it, in DIR/budget/<B>kBps;
// the main run is the unbudgeted reference.
Status RunBudgetSweep(const Setup& setup, const std::string& out,
                      const std::vector<double>& budgets, const Json& main_results, int* failed) {
  std::vector<BudgetRow> rows;
  BudgetRow reference;
  reference.run_dir = ".";
  reference.results = main_results;
  rows.push_back(reference);
  int index = 0;
  for (const double budget : budgets) {
    char name[64];
    std::snprintf(name, sizeof(name), "budget/%gkBps", budget);
    std::printf("\nbudget run %d of %zu: %g kB/s per agent\n", ++index, budgets.size(), budget);
    std::fflush(stdout);
    char value[32];
    std::snprintf(value, sizeof(value), "%g", budget);
    auto run = RunOnce(setup, JoinPath(out, name), {"--bandwidth-budget", value}, failed);
    if (!run.ok()) return run.status().WithContext(std::string("budget run ") + name);
    BudgetRow row;
    row.budget_kBps = budget;
    row.run_dir = name;
    row.results = *run;
    rows.push_back(row);
  }
  return AppendBudgetSweep(out, rows);
}

// --knob-costs: one run per RGB-D setting, each changed alone from the agents' defaults (the
// main run), in DIR/knobs/; the measurement behind the order of the budget's ladder.
Status RunKnobCosts(const Setup& setup, const std::string& out, const Json& main_results,
                    int* failed) {
  const std::vector<std::pair<std::string, std::vector<std::string>>> variants = {
      {"JPEG quality 50", {"--jpeg-quality", "50"}},
      {"JPEG quality 35", {"--jpeg-quality", "35"}},
      {"depth bound 1 %", {"--depth-bound", "100"}},
      {"depth bound 2 %", {"--depth-bound", "200"}},
      {"r = 1/4", {"--rgbd-downsample", "4"}},
      {"S_min x0.7", {"--rgbd-threshold-scale", "0.7"}},
      {"S_min x0.5", {"--rgbd-threshold-scale", "0.5"}},
      {"JPEG quality 90, depth bound 0.25 %", {"--jpeg-quality", "90", "--depth-bound", "25"}},
      {"S_min x1.5", {"--rgbd-threshold-scale", "1.5"}},
      {"r = 1", {"--rgbd-downsample", "1"}},
      {"every keyframe", {"--rgbd-every-keyframe"}}};
  std::vector<KnobRow> rows = {{"agent defaults", ".", main_results}};
  int index = 0;
  for (const auto& [knob, args] : variants) {
    const std::string dir = "knobs/" + std::to_string(++index);
    std::printf("\nknob run %d of %zu: %s\n", index, variants.size(), knob.c_str());
    std::fflush(stdout);
    auto run = RunOnce(setup, JoinPath(out, dir), args, failed);
    if (!run.ok()) return run.status().WithContext("knob run " + knob);
    rows.push_back({knob, dir, *run});
  }
  return AppendKnobCosts(out, rows);
}

// Everything the command line sets.
struct ReplayArgs {
  std::string dataset, out, config, rate = "max", reference, bin_dir;
  int agents = 3;
  double timeout_s = 3600;
  bool ablation = false, knob_costs = false;
  std::string link_text, budgets_text;
  std::vector<std::string> agent_args, server_args;
  ViewSetup view;
};

void AddOptions(CLI::App* app, ReplayArgs* a) {
  app->add_option("--dataset", a->dataset,
                  "TUM-layout folder (TUM RGB-D, ICL-NUIM, 7-Scenes converted, ccmd_synth)")
      ->required();
  app->add_option("--agents", a->agents, "Number of agents K (segments)")
      ->check(CLI::Range(1, 32))
      ->capture_default_str();
  app->add_option("--out", a->out, "Results folder (created)")->required();
  app->add_option("--config", a->config,
                  "Camera/tracking config (default: the dataset's camera.yaml or a guess)");
  app->add_option("--rate", a->rate, "realtime (the dataset's timestamps) or max")
      ->check(CLI::IsMember({"realtime", "max"}))
      ->capture_default_str();
  app->add_option(
      "--reference", a->reference,
      "Reference surface (PLY, points or mesh) for reconstruction error; default: the dataset's "
      "surface.ply, else a cloud built from ground-truth poses and depth");
  app->add_option("--agent-arg", a->agent_args, "Extra argument for every ccmd_agent (repeatable)");
  app->add_option("--server-arg", a->server_args, "Extra argument for ccmd_server (repeatable)");
  app->add_option("--bin-dir", a->bin_dir,
                  "Folder of ccmd_server and ccmd_agent (default: next to this program)");
  app->add_option("--timeout", a->timeout_s,
                  "Ask the agents of a run (each run of --ablation) to stop after this many "
                  "seconds; those still running a minute later are ended")
      ->capture_default_str();
  CLI::Option* view_flag =
      app->add_flag("--view", a->view.enabled,
                    "Serve the live map view while the run goes on (its address is printed)");
  app->add_option("--view-port", a->view.port, "Port of the map view on 127.0.0.1 (0: a free one)")
      ->check(CLI::Range(0, 65535))
      ->needs(view_flag)
      ->capture_default_str();
  app->add_flag(
      "--ablation", a->ablation,
      "Also run r = 1, 0.5, 0.25 with and without the RGB-D keyframe selection (six runs in all, "
      "in DIR/ablation/) and add the RGB-D bytes and map points table to the report");
  app->add_option("--link", a->link_text,
                  "Run over a shaped link instead of loopback, e.g. "
                  "rate=2.4mbit,delay=50ms,jitter=10ms,loss=0.02 "
                  "(keys: rate, delay, jitter, loss, queue, seed; docs/benchmarks/link.md). The "
                  "server and the agents "
                  "run in network namespaces made for the run and removed after it. Needs root");
  app->add_option("--budgets", a->budgets_text,
                  "Also run with every agent under each of these bandwidth budgets (kB/s, "
                  "comma-separated, e.g. "
                  "25,50,100,200; runs in DIR/budget/) and add the reconstruction-against-budget "
                  "table and plot");
  app->add_flag(
      "--knob-costs", a->knob_costs,
      "Also run with each RGB-D setting (JPEG quality, depth bound, r, S_min, every keyframe) "
      "changed alone "
      "(eleven runs in DIR/knobs/) and add what each saves and costs the map to the report");
}

// The first of `prefixes` an --agent-arg starts with ("" if none): an option a run series
// sets itself.
std::string SetBySeries(const std::vector<std::string>& agent_args,
                        const std::vector<std::string>& prefixes) {
  for (const std::string& arg : agent_args) {
    for (const std::string& prefix : prefixes) {
      if (arg.rfind(prefix, 0) == 0) return prefix;
    }
  }
  return "";
}

// The options that need more than CLI11's checks: the shaped link (parsed, and available on
// this machine), the budgets, and --agent-arg against what the run series set. The error's
// message is the user's explanation.
Status CheckArgs(const ReplayArgs& a, std::optional<LinkSpec>* link, std::vector<double>* budgets) {
  if (!a.link_text.empty()) {
    auto parsed = ParseLinkSpec(a.link_text);
    if (!parsed.ok()) return InvalidArgument("--link: " + parsed.status().message());
    // The view serves on the server's loopback, which inside its namespace no browser reaches.
    if (a.view.enabled) {
      return InvalidArgument(
          "--view cannot be combined with --link: the server runs in its own network namespace");
    }
    const Status available = CheckNetnsLinkAvailable();
    if (!available.ok()) return InvalidArgument("--link: " + available.message());
    *link = *parsed;
  }
  if (a.knob_costs) {
    const std::string knob = SetBySeries(
        a.agent_args, {"--jpeg-quality", "--depth-bound", "--rgbd-downsample",
                       "--rgbd-threshold-scale", "--rgbd-every-keyframe", "--bandwidth-budget"});
    if (!knob.empty())
      return InvalidArgument("--knob-costs sets " + knob + " itself; leave it out of --agent-arg");
  }
  if (!a.budgets_text.empty()) {
    for (const std::string& part : Split(a.budgets_text, ',')) {
      auto b = ParseDouble(Trim(part));
      if (!b.ok() || !(*b >= 1))
        return InvalidArgument("--budgets: '" + part + "' is not a budget in kB/s (>= 1)");
      budgets->push_back(*b);
    }
    if (!SetBySeries(a.agent_args, {"--bandwidth-budget"}).empty())
      return InvalidArgument(
          "--budgets sets --bandwidth-budget itself; leave it out of --agent-arg");
  }
  if (a.ablation) {
    for (const std::string& arg : a.agent_args) {
      if (arg.rfind("--rgbd-downsample", 0) == 0 || arg == "--rgbd-every-keyframe")
        return InvalidArgument("--ablation sets " + arg + " itself; leave it out of --agent-arg");
    }
  }
  return Status::Ok();
}

// The dataset (frame count, camera, ground truth) and its split, and the config the agents
// get as --config: camera, tracking and sensor options from one file.
Status OpenDataset(const ReplayArgs& a, std::optional<TumSequence>* sequence, Setup* setup) {
  std::optional<PinholeCamera> camera;
  SourceOptions source_options;
  source_options.camera_config = a.config;
  source_options.configs_dir = app::ConfigDir();
  setup->camera_config = DatasetConfigPath(a.dataset, source_options);
  if (!setup->camera_config.empty()) {
    CCMD_ASSIGN_OR_RETURN(camera, LoadCameraConfig(setup->camera_config));
  }
  // With the Depth block and the ground truth's camera.
  CCMD_RETURN_IF_ERROR(ReadReferenceCamera(setup->camera_config, &setup->reference));
  setup->reference.reference_ply = a.reference;
  CCMD_ASSIGN_OR_RETURN(*sequence, TumSequence::Open(a.dataset, camera));
  CCMD_ASSIGN_OR_RETURN(setup->segments,
                        SplitWithOverlap(static_cast<int>((*sequence)->size()), a.agents));
  setup->sequence = &**sequence;
  return Status::Ok();
}

// --ablation: the main run is r = 0.5 with the selection (the agent's defaults); five more
// runs cover the rest of the grid, each in its own folder, and the table joins the report.
Status RunAblation(const Setup& setup, const std::string& out, const Json& main_results,
                   int* failed) {
  std::vector<AblationRow> rows;
  int variant_index = 0;
  for (const int downsample : {1, 2, 4}) {
    for (const bool selection : {true, false}) {
      AblationRow row;
      row.downsample = downsample;
      row.selection = selection;
      if (downsample == 2 && selection) {
        row.run_dir = ".";
        row.results = main_results;
        rows.push_back(row);
        continue;
      }
      row.run_dir =
          "ablation/r" + std::to_string(downsample) + (selection ? "_selected" : "_every_keyframe");
      std::printf("\nablation run %d of 5: r = 1/%d, %s\n", ++variant_index, downsample,
                  selection ? "RGB-D selection on" : "RGB-D with every keyframe");
      std::fflush(stdout);
      std::vector<std::string> extra = {"--rgbd-downsample", std::to_string(downsample)};
      if (!selection) extra.push_back("--rgbd-every-keyframe");
      auto variant = RunOnce(setup, JoinPath(out, row.run_dir), extra, failed);
      if (!variant.ok()) return variant.status().WithContext("ablation " + row.run_dir);
      row.results = *variant;
      rows.push_back(row);
    }
  }
  return AppendAblation(out, rows);
}

void PrintSummary(const Json& r, const std::string& out) {
  auto num = [&](const char* key) { return r.Get(key) ? r.Get(key)->number() : -1.0; };
  std::printf(
      "\nmaps after fusion: %.0f   fused ATE RMSE: %.4f m   reconstruction mean %.4f m, Hausdorff "
      "%.4f m\n",
      num("maps_after_fusion"), num("ate_rmse_m"), num("recon_mean_m"), num("recon_hausdorff_m"));
  if (r.Get("all_maps_fused") && !r.Get("all_maps_fused")->boolean()) {
    std::string members;
    if (const Json* names = r.Get("primary_map_agents")) {
      for (const Json& n : names->array()) members += (members.empty() ? "" : ", ") + n.string();
    }
    std::printf(
        "not every map fused: the figures above are the primary map's (%s); see report.md for the "
        "others\n",
        members.empty() ? "no agent" : members.c_str());
  }
  std::printf("per agent: %.1f kB/s, %.1f kB per keyframe, %.2f keyframes/s\n", num("atps_kBps"),
              num("akfs_kB"), num("akfr_hz"));
  std::printf("link: %s   map latency p50 %.2f s, p95 %.2f s   every keyframe once: %s\n",
              r.Get("link") ? r.Get("link")->string().c_str() : "loopback",
              num("map_latency_p50_s"), num("map_latency_p95_s"),
              r.Get("keyframes_delivered_once") && r.Get("keyframes_delivered_once")->boolean()
                  ? "yes"
                  : "NO");
  std::printf("report: %s\nmap:    %s\n", JoinPath(out, "report.md").c_str(),
              JoinPath(out, "map.ply").c_str());
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Split-replay evaluation: a ccmd_server and K ccmd_agent processes over TCP on loopback (or "
      "a\n"
      "shaped link with --link), each agent replaying one segment (10% overlap) of a TUM-layout\n"
      "sequence; then ATE, reconstruction error, bandwidth, map latency and CPU in DIR/report.md "
      "and\n"
      "DIR/results.json."};
  ReplayArgs a;
  AddOptions(&app, &a);
  CLI11_PARSE(app, argc, argv);
  std::optional<LinkSpec> link;
  std::vector<double> budgets;
  if (const Status s = CheckArgs(a, &link, &budgets); !s.ok()) return Fail(s.message());
  if (link) {
    // Stop cleanly on a signal: processes stopped, namespaces removed.
    struct sigaction action {};
    action.sa_sigaction = OnSignal;
    action.sa_flags = SA_SIGINFO;
    sigemptyset(&action.sa_mask);
    for (const int sig : {SIGINT, SIGTERM, SIGHUP}) sigaction(sig, &action, nullptr);
  }
  std::string command;
  for (int i = 0; i < argc; ++i) command += (i ? " " : "") + std::string(argv[i]);

  Setup setup;
  std::optional<TumSequence> sequence;
  if (const Status s = OpenDataset(a, &sequence, &setup); !s.ok()) return Fail(s.ToString());
  setup.dataset = a.dataset;
  setup.rate = a.rate;
  setup.bin_dir = a.bin_dir.empty() ? ExecutableDir() : a.bin_dir;
  setup.command = command;
  setup.agents = a.agents;
  setup.timeout_s = a.timeout_s;
  setup.agent_args = a.agent_args;
  setup.server_args = a.server_args;
  setup.link = link;
  setup.link_text = a.link_text;
  setup.view = a.view;
  std::printf("replaying %s: %zu frames, %d agents\n", a.dataset.c_str(), sequence->size(),
              a.agents);
  for (int i = 0; i < a.agents; ++i) {
    std::printf("  agent%d: frames %d-%d\n", i + 1, setup.segments[i].first,
                setup.segments[i].last);
  }
  std::fflush(stdout);
  int failed = 0;
  auto results = RunOnce(setup, a.out, {}, &failed);
  if (!results.ok()) return Fail(results.status().ToString());
  // Each series adds its table to the main run's report and results.json.
  const auto series = [&](const Status& ran) -> Status {
    CCMD_RETURN_IF_ERROR(ran);
    CCMD_ASSIGN_OR_RETURN(results, ReadJsonFile(JoinPath(a.out, "results.json")));
    return Status::Ok();
  };
  if (a.ablation) {
    if (const Status s = series(RunAblation(setup, a.out, *results, &failed)); !s.ok())
      return Fail(s.ToString());
  }
  if (a.knob_costs) {
    if (const Status s = series(RunKnobCosts(setup, a.out, *results, &failed)); !s.ok())
      return Fail(s.ToString());
  }
  if (!budgets.empty()) {
    if (const Status s = series(RunBudgetSweep(setup, a.out, budgets, *results, &failed)); !s.ok())
      return Fail(s.ToString());
  }
  PrintSummary(*results, a.out);
  return failed ? 1 : 0;
}
