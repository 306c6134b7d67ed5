// ccmd_view_bench: the live map view's figures (docs/benchmarks/view.md), in headless Chromium.
//
//   ccmd_view_bench latency [--dataset DIR --config YAML] [--agents K] [--rate realtime|max]
//       A ccmd_server with its view and K ccmd_agent processes on a split replay (default: the
//       demo's synthetic room, 600 frames, generated into a temporary folder); the page opened
//       before the agents start. Reports, from the page's own clocks: keyframe arrival at the
//       server -> its points drawn, and pose change -> drawn, against the targets (0.5 s,
//       0.2 s), with the back-end's share (arrival -> cloud in the dense store) measured in the
//       same run as the reference.
//   ccmd_view_bench fps [--points 3000000]
//       A view server in this process holding a synthetic map of that many view points; the
//       page draws frames with an orbiting camera, each waited for (a one-pixel read). Reports
//       frames per second with the level of detail and, as the reference in the same run, with
//       every point drawn.
// --json FILE writes the figures; --screenshot FILE.png keeps a picture of the page.

#include <signal.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>

#include "apps/app_common.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/timer.h"
#include "libccmd/view/view_server.h"
#include "tests/support/headless_browser.h"
#include "tests/support/server_with_view.h"

// After Eigen (through the headers above): see view_server.cc.
#include <httplib.h>

namespace {

using namespace ccmd;

int Fail(const std::string& what) {
  std::fprintf(stderr, "ccmd_view_bench: %s\n", what.c_str());
  return 1;
}

std::string ExecutableDir() {
  char path[4096] = {0};
  const ssize_t n = ::readlink("/proc/self/exe", path, sizeof(path) - 1);
  if (n <= 0) return ".";
  const std::string p(path, static_cast<std::size_t>(n));
  return p.substr(0, p.find_last_of('/'));
}

std::string LoadAverage() {
  std::ifstream in("/proc/loadavg");
  std::string one, five, fifteen;
  in >> one >> five >> fifteen;
  return one + " " + five + " " + fifteen;
}

std::string TempFolder() {
  char dir[] = "/tmp/ccmd_view_bench_XXXXXX";
  return ::mkdtemp(dir) ? dir : "";
}

struct Common {
  std::string json_path, screenshot_path;
  int width = 1280, height = 800;
};

Status KeepScreenshot(testing::HeadlessBrowser* browser, const std::string& path) {
  if (path.empty()) return Status::Ok();
  CCMD_RETURN_IF_ERROR(browser->Evaluate("ccmdView.whenRested()", 600).status());
  CCMD_ASSIGN_OR_RETURN(const std::string png, browser->Screenshot());
  return WriteFileAtomic(path, png);
}

StatusOr<Json> Page(testing::HeadlessBrowser* browser, const std::string& js,
                    double timeout_s = 600) {
  auto r = browser->Evaluate(js, timeout_s);
  if (!r.ok()) return Status(r.status().code(), r.status().message() + "\n" + browser->PageLog());
  return r;
}

// ---------------------------------------------------------------- latency

// A plain HTTP client on the event stream (the reference for the page's delivery figures):
// for every cloud and pose event, the time from its stamp to its arrival here.
class StreamProbe {
 public:
  StreamProbe(std::uint16_t port, std::uint64_t after) {
    thread_ = std::thread([this, port, after] {
      httplib::Client client("127.0.0.1", port);
      client.set_read_timeout(3600, 0);
      std::string buffer;
      client.Get(("/api/events?after=" + std::to_string(after)).c_str(),
                 [&](const char* data, std::size_t n) {
                   const double now_ms = WallSeconds() * 1e3;
                   buffer.append(data, n);
                   for (std::size_t end; (end = buffer.find("\n\n")) != std::string::npos;
                        buffer.erase(0, end + 2)) {
                     const std::size_t at = buffer.find("data: ");
                     if (at == std::string::npos || at > end) continue;
                     auto e = Json::Parse(buffer.substr(at + 6, end - at - 6));
                     if (!e.ok() || !e->Get("t") || !e->Get("type")) continue;
                     const std::string type = e->Get("type")->string();
                     if (type == "cloud") cloud_ms_.push_back(now_ms - e->Get("t")->number());
                     if (type == "poses") pose_ms_.push_back(now_ms - e->Get("t")->number());
                   }
                   return !stop_;
                 });
    });
  }
  // An early return (a failed agent): the stream is left at its next keep-alive comment.
  ~StreamProbe() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  // Call after the server stopped (its stream has ended).
  Json Finish() {
    thread_.join();
    auto summary = [](std::vector<double> v) {
      Json j;
      j["n"] = v.size();
      if (v.empty()) return j;
      std::sort(v.begin(), v.end());
      j["median"] = v[v.size() / 2];
      j["p95"] = v[std::min(v.size() - 1, static_cast<std::size_t>(0.95 * (v.size() - 1) + 0.5))];
      j["max"] = v.back();
      return j;
    };
    Json out;
    out["cloud"] = summary(cloud_ms_);
    out["pose"] = summary(pose_ms_);
    return out;
  }

 private:
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::vector<double> cloud_ms_, pose_ms_;  // the probe's thread only, until Finish
};

struct LatencyOptions {
  std::string dataset, config, keep;
  int agents = 3, frames = 600;
  std::string rate = "realtime";
};

// Waits until the server stops changing and the page has drawn all of it.
Status Settle(testing::HeadlessBrowser* browser, std::uint16_t view_port) {
  httplib::Client client("127.0.0.1", view_port);
  client.set_read_timeout(60, 0);
  const double deadline = MonotonicSeconds() + 900;
  while (MonotonicSeconds() < deadline) {
    auto a = client.Get("/api/state");
    if (!a || a->status != 200) return Unavailable("the view stopped answering");
    CCMD_ASSIGN_OR_RETURN(const Json state, Json::Parse(a->body));
    const long seq = static_cast<long>(state.Get("seq")->number());
    CCMD_ASSIGN_OR_RETURN(const Json shown,
                          Page(browser, "ccmdView.whenSettled(" + std::to_string(seq) + ")"));
    auto b = client.Get("/api/state");
    if (!b || b->status != 200) return Unavailable("the view stopped answering");
    CCMD_ASSIGN_OR_RETURN(const Json again, Json::Parse(b->body));
    if (static_cast<long>(again.Get("seq")->number()) == seq &&
        static_cast<long>(shown.number()) == seq) {
      return Status::Ok();
    }
  }
  return Timeout("the server never stopped changing");
}

void PrintLatencyRow(const char* what, const Json* s, double target_ms) {
  if (!s || !s->Get("n") || s->Get("n")->number() == 0) {
    std::printf("| %s | 0 | - | - | - | %s |\n", what,
                target_ms > 0 ? std::to_string(target_ms).c_str() : "-");
    return;
  }
  const auto num = [&](const char* k) {
    return s->Get(k) && s->Get(k)->is_number() ? s->Get(k)->number() : -1.0;
  };
  std::printf("| %s | %.0f | %.0f | %.0f | %.0f |", what, num("n"), num("median"), num("p95"),
              num("max"));
  if (target_ms > 0) {
    std::printf(" %.0f | %.2f |\n", target_ms, num("median") / target_ms);
  } else {
    std::printf(" - | - |\n");
  }
}

int RunLatency(const LatencyOptions& o, const Common& common) {
  const std::string work = TempFolder();
  if (work.empty()) return Fail("cannot make a temporary folder");
  std::string dataset = o.dataset;
  if (dataset.empty()) {
    std::printf("generating the demo's synthetic room (%d frames, 640x480) in %s\n", o.frames,
                work.c_str());
    std::fflush(stdout);
    SyntheticSequenceOptions synth;
    synth.frames = o.frames;
    dataset = JoinPath(work, "sequence");
    if (auto s = WriteSyntheticSequence(dataset, synth); !s.ok())
      return Fail(s.status().ToString());
  }
  const std::string bin = ExecutableDir();
  auto server = testing::StartServerWithView(JoinPath(bin, "ccmd_server"), work);
  if (!server.ok()) return Fail(server.status().ToString());
  testing::BrowserOptions browser_options;
  browser_options.width = common.width;
  browser_options.height = common.height;
  browser_options.log_path = JoinPath(work, "chromium.log");
  auto browser = testing::HeadlessBrowser::Launch(browser_options);
  if (!browser.ok()) return Fail(browser.status().ToString());
  if (auto s = (*browser)->Open(server->url); !s.ok()) return Fail(s.ToString());
  if (auto s = Page(browser->get(), "ccmdView.whenConnection('live')"); !s.ok())
    return Fail(s.status().ToString());
  const std::string load_before = LoadAverage();
  StreamProbe probe(server->view_port, 0);
  const Stopwatch watch;
  std::vector<Subprocess> agents;
  for (int i = 1; i <= o.agents; ++i) {
    std::vector<std::string> argv = {JoinPath(bin, "ccmd_agent"),
                                     "--source",
                                     "tum:" + dataset,
                                     "--segment",
                                     std::to_string(i) + "/" + std::to_string(o.agents),
                                     "--server",
                                     "127.0.0.1:" + std::to_string(server->port),
                                     "--name",
                                     "agent" + std::to_string(i),
                                     "--rate",
                                     o.rate,
                                     "--spill-dir",
                                     JoinPath(work, "spill" + std::to_string(i))};
    if (!o.config.empty()) {
      argv.push_back("--config");
      argv.push_back(o.config);
    }
    auto agent = Subprocess::Start(argv, JoinPath(work, "agent" + std::to_string(i) + ".out"),
                                   JoinPath(work, "agent" + std::to_string(i) + ".log"));
    if (!agent.ok()) return Fail(agent.status().ToString());
    agents.push_back(std::move(agent).value());
  }
  std::printf("%d agents replaying %s (%s pace); the page follows\n", o.agents, dataset.c_str(),
              o.rate.c_str());
  std::fflush(stdout);
  for (Subprocess& a : agents) {
    if (a.Wait().exit_code != 0) return Fail("an agent failed; logs in " + work);
  }
  const double replay_s = watch.ElapsedSeconds();
  if (auto s = Settle(browser->get(), server->view_port); !s.ok()) return Fail(s.ToString());
  const std::string load_after = LoadAverage();
  auto latency = Page(browser->get(), "ccmdView.latency()");
  auto state = Page(browser->get(), "ccmdView.state()");
  if (!latency.ok() || !state.ok()) return Fail("cannot read the page's figures");
  if (auto s = KeepScreenshot(browser->get(), common.screenshot_path); !s.ok())
    return Fail(s.ToString());
  server->process.Signal(SIGINT).IgnoreError();
  server->process.Wait();
  const Json plain = probe.Finish();

  const Json& l = *latency;
  std::printf(
      "\nreplay %.1f s, %zu keyframes, %.0f view points; load average %s (before) / %s (after)\n\n",
      replay_s, state->Get("keyframes")->size(), state->Get("totalPoints")->number(),
      load_before.c_str(), load_after.c_str());
  std::printf(
      "| latency (ms) | n | median | p95 | max | target | median / target "
      "|\n|---|---|---|---|---|---|---|\n");
  PrintLatencyRow("keyframe arrival -> points drawn", l.Get("keyframe"), 500);
  PrintLatencyRow("of which back-end (arrival -> cloud in the dense store; reference)",
                  l.Get("backend"), 0);
  PrintLatencyRow("of which view (cloud stored -> drawn)", l.Get("cloud"), 0);
  PrintLatencyRow("of which event delivery (cloud stored -> page told)", l.Get("delivery"), 0);
  PrintLatencyRow("event delivery to a plain HTTP client (reference)", plain.Get("cloud"), 0);
  PrintLatencyRow("of which cloud request (page told -> points uploaded)", l.Get("fetch"), 0);
  PrintLatencyRow("of which next frame (uploaded -> drawn)", l.Get("frame"), 0);
  PrintLatencyRow("cloud request handled in the server", l.Get("server"), 0);
  PrintLatencyRow("pose update -> drawn (all)", l.Get("pose"), 200);
  PrintLatencyRow("pose update -> plain HTTP client (reference)", plain.Get("pose"), 0);
  if (const Json* by = l.Get("pose_by_source")) {
    for (const auto& [src, s] : by->object())
      PrintLatencyRow(("pose update -> drawn (" + src + ")").c_str(), &s, 200);
  }
  if (!common.json_path.empty()) {
    Json out;
    out["mode"] = "latency";
    out["dataset"] = dataset;
    out["agents"] = o.agents;
    out["rate"] = o.rate;
    out["replay_seconds"] = replay_s;
    out["load_average_before"] = load_before;
    out["load_average_after"] = load_after;
    out["latency_ms"] = l;
    out["plain_client_ms"] = plain;
    if (auto s = WriteJsonFile(out, common.json_path); !s.ok()) return Fail(s.ToString());
  }
  std::error_code ec;
  if (!o.keep.empty()) {
    std::filesystem::rename(work, o.keep, ec);
    if (ec) return Fail("cannot move the run to " + o.keep + ": " + ec.message());
    std::printf("\nthe run (server results, logs) is in %s\n", o.keep.c_str());
    return 0;
  }
  std::filesystem::remove_all(work, ec);
  return 0;
}

// ---------------------------------------------------------------- fps

// A room of wall patches: keyframes on a circle looking outwards, each cloud a 100 x 100 grid
// 2.1 cm apart (one point per 2 cm viewing voxel, so every point reaches the browser).
CameraCloud WallPatch(int keyframe) {
  CameraCloud cloud;
  const float depth = 1.5f + 0.5f * static_cast<float>(keyframe % 3);
  for (int i = 0; i < 100; ++i) {
    for (int j = 0; j < 100; ++j) {
      cloud.points.emplace_back(0.021f * (i - 50), 0.021f * (j - 50),
                                depth + 0.002f * static_cast<float>(i % 7));
      const bool stripe = ((i / 8) + (j / 8) + keyframe) % 2 == 0;
      cloud.colors.push_back({static_cast<std::uint8_t>(60 + (keyframe * 37) % 160),
                              static_cast<std::uint8_t>(stripe ? 170 : 90),
                              static_cast<std::uint8_t>(100 + (i + j) % 100)});
    }
  }
  return cloud;
}

Pose PatchPose(int keyframe, int count) {
  const double yaw = 2 * M_PI * keyframe / count * 3.0;  // three turns, at three heights
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T.translation() =
      Eigen::Vector3d(0.5 * std::cos(yaw), -1.0 * (keyframe * 3 / count), 0.5 * std::sin(yaw));
  return T;
}

int RunFps(std::size_t points, int frames, const Common& common) {
  const int keyframes = static_cast<int>((points + 9999) / 10000);
  auto dense = DenseMap::Create();
  if (!dense.ok()) return Fail(dense.status().ToString());
  ViewModel model;
  model.OnAgent(AgentId(1), "bench");
  std::printf("building a map of %d keyframes x 10000 view points\n", keyframes);
  std::fflush(stdout);
  for (int k = 0; k < keyframes; ++k) {
    const GlobalKeyframeId id{AgentId(1), KeyframeId(static_cast<std::uint32_t>(k))};
    if (auto s = (*dense)->AddKeyframeCloud(id, PatchPose(k, keyframes), WallPatch(k)); !s.ok())
      return Fail(s.ToString());
    model.OnKeyframe(id, MapId(1), PatchPose(k, keyframes), MonotonicSeconds(), true);
    model.OnDenseKeyframe(id, MapId(1), PatchPose(k, keyframes));
  }
  ViewServerOptions options;
  options.web_dir = app::WebDir();
  const DenseMap* map = dense->get();
  auto server = ViewServer::Start(options, &model, map, [&] {
    ViewStats s;
    s.keyframes = static_cast<std::size_t>(keyframes);
    s.points = map->Stats().kept_points;
    s.maps.push_back({MapId(1), s.keyframes, true, {AgentId(1)}});
    ViewAgentStats a;
    a.id = AgentId(1);
    a.name = "bench";
    a.keyframes = s.keyframes;
    a.map = MapId(1);
    s.agents.push_back(a);
    return s;
  });
  if (!server.ok()) return Fail(server.status().ToString());
  testing::BrowserOptions browser_options;
  browser_options.width = common.width;
  browser_options.height = common.height;
  auto browser = testing::HeadlessBrowser::Launch(browser_options);
  if (!browser.ok()) return Fail(browser.status().ToString());
  if (auto s = (*browser)->Open((*server)->url()); !s.ok()) return Fail(s.ToString());
  const Stopwatch load;
  auto settled =
      Page(browser->get(), "ccmdView.whenSettled(" + std::to_string(model.last_seq()) + ")", 1800);
  if (!settled.ok()) return Fail(settled.status().ToString());
  const double load_s = load.ElapsedSeconds();
  const std::string load_avg = LoadAverage();
  auto lod = Page(browser->get(),
                  "ccmdView.benchmark({frames: " + std::to_string(frames) + ", warmup: 30})", 1800);
  auto full = Page(browser->get(), "ccmdView.benchmark({frames: 3, warmup: 1, lod: false})", 1800);
  if (!lod.ok() || !full.ok())
    return Fail("benchmark failed: " + (lod.ok() ? full.status() : lod.status()).ToString());
  if (auto s = KeepScreenshot(browser->get(), common.screenshot_path); !s.ok())
    return Fail(s.ToString());
  const auto num = [](const Json& j, const char* k) {
    return j.Get(k) && j.Get(k)->is_number() ? j.Get(k)->number() : 0.0;
  };
  std::printf("\n%.0f view points loaded and drawn in %.1f s; canvas %dx%d; load average %s\n\n",
              num(*lod, "total_points"), load_s, common.width - 380, common.height,
              load_avg.c_str());
  std::printf(
      "| drawing | points per frame | frames/s | mean ms | p95 ms | ratio to every point "
      "|\n|---|---|---|---|---|---|\n");
  std::printf("| level of detail (moving camera) | %.0f | %.1f | %.1f | %.1f | %.1f |\n",
              num(*lod, "drawn_points"), num(*lod, "fps"), num(*lod, "mean_ms"),
              num(*lod, "p95_ms"), num(*lod, "fps") / std::max(1e-9, num(*full, "fps")));
  std::printf("| every point (reference) | %.0f | %.2f | %.0f | %.0f | 1 |\n",
              num(*full, "drawn_points"), num(*full, "fps"), num(*full, "mean_ms"),
              num(*full, "p95_ms"));
  std::printf("\nat rest, the rest of the points are added in %.0f frames (%.0f ms)\n",
              num(*lod, "refine_frames"), num(*lod, "refine_ms"));
  if (!common.json_path.empty()) {
    Json out;
    out["mode"] = "fps";
    out["view_points"] = num(*lod, "total_points");
    out["load_seconds"] = load_s;
    out["load_average"] = load_avg;
    out["level_of_detail"] = *lod;
    out["every_point"] = *full;
    if (auto s = WriteJsonFile(out, common.json_path); !s.ok()) return Fail(s.ToString());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Live map view benchmarks in headless Chromium (docs/benchmarks/view.md)."};
  app.require_subcommand(1);
  Common common;
  app.add_option("--json", common.json_path, "Write the figures as JSON");
  app.add_option("--screenshot", common.screenshot_path, "Keep a PNG of the page at the end");
  app.add_option("--width", common.width, "Browser window width (the 3D view is 380 px narrower)")
      ->capture_default_str();
  app.add_option("--height", common.height, "Browser window height")->capture_default_str();
  LatencyOptions latency;
  auto* lat = app.add_subcommand(
      "latency", "Keyframe and pose-update latency to the browser during a split replay");
  lat->add_option("--dataset", latency.dataset,
                  "TUM-layout sequence (default: the demo's synthetic room)");
  lat->add_option("--config", latency.config, "Camera config for --dataset");
  lat->add_option("--agents", latency.agents, "Agents")
      ->check(CLI::Range(1, 16))
      ->capture_default_str();
  lat->add_option("--frames", latency.frames, "Frames of the synthetic room")
      ->capture_default_str();
  lat->add_option("--keep", latency.keep,
                  "Keep the run (the server's results/, logs) in this new folder");
  lat->add_option("--rate", latency.rate, "realtime or max")
      ->check(CLI::IsMember({"realtime", "max"}))
      ->capture_default_str();
  std::size_t points = 3000000;
  int frames = 60;
  auto* fps =
      app.add_subcommand("fps", "Frames per second of a large map in the software renderer");
  fps->add_option("--points", points, "View points in the map")
      ->check(CLI::Range(10000, 50000000))
      ->capture_default_str();
  fps->add_option("--frames", frames, "Measured frames (after 30 to settle the level of detail)")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  if (*lat) return RunLatency(latency, common);
  return RunFps(points, frames, common);
}
