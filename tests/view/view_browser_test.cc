// The map view in a real browser: headless Chromium opens the page of a ccmd_server while two
// ccmd_agent processes replay the halves of a synthetic sequence. From the page's own state
// (window.ccmdView) the test checks that every keyframe the server holds is there with the
// server's pose, that every cloud is drawn, that keyframes that moved are drawn where the
// server says, that the agents' panel shows the server's counts, and that the page says so
// when the server is gone. A long mission fed to the view in the test's process checks that
// the page frees the clouds the server releases. Every wait is on the page's or the server's
// state.
//
// CCMD_VIEW_SCREENSHOT=path.png keeps the screenshot (docs/view.md uses one).

#include <gtest/gtest.h>

#include <signal.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <deque>
#include <map>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <utility>

#include "libccmd/io/trajectory.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/timer.h"
#include "libccmd/view/view_cloud.h"
#include "libccmd/view/view_model.h"
#include "libccmd/view/view_server.h"
#include "tests/support/headless_browser.h"
#include "tests/support/server_with_view.h"
#include "tests/support/test_support.h"

// After Eigen (through the headers above): see view_server.cc.
#include <httplib.h>

namespace ccmd {
namespace {

Json Get(std::uint16_t port, const std::string& path) {
  httplib::Client client("127.0.0.1", port);
  client.set_read_timeout(60, 0);
  auto r = client.Get(path.c_str());
  EXPECT_TRUE(r && r->status == 200) << path;
  if (!r || r->status != 200) return Json();
  auto j = Json::Parse(r->body);
  EXPECT_TRUE(j.ok()) << path;
  return j.ok() ? *j : Json();
}

std::string Key(const Json& kf) {
  return std::to_string(static_cast<int>(kf.Get("a")->number())) + ":" +
         std::to_string(static_cast<long>(kf.Get("k")->number()));
}

// The page as the build copies it for ccmd_server: $CCMD_WEB_DIR, else share/ccmd/web beside
// the programs' bin/ folder.
std::string WebDir() {
  if (const char* env = std::getenv("CCMD_WEB_DIR")) return env;
  return testing::ProgramPath("../share/ccmd/web");
}

// Place p of kPlaces around a room: a camera 0.5 m from the centre looking out at the wall,
// which fills its view as 50 x 40 points 3 cm apart, 1.5 m ahead (one per cube of the view's
// 2 cm thinning: the page gets all 2000).
constexpr int kPlaces = 40;

Pose PlacePose(int p) {
  const double yaw = 2 * M_PI * p / kPlaces;
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(-yaw, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(0.5 * std::sin(yaw), 0, 0.5 * std::cos(yaw));
  return T;
}

CameraCloud PlaceCloud(int p) {
  CameraCloud cloud;
  for (int i = 0; i < 50; ++i) {
    for (int j = 0; j < 40; ++j) {
      cloud.points.emplace_back(-0.735f + 0.03f * i, -0.585f + 0.03f * j,
                                1.5f + 0.002f * static_cast<float>((i + j + p) % 5));
      cloud.colors.push_back({static_cast<std::uint8_t>(6 * p), static_cast<std::uint8_t>(5 * i),
                              static_cast<std::uint8_t>(6 * j)});
    }
  }
  return cloud;
}

// A ccmd_server with its view in a folder of the test's, and headless Chromium on its page.
class ViewBrowserTest : public ::testing::Test {
 protected:
  // Starts both (call ASSERT_NO_FATAL_FAILURE on it).
  void Open(const std::vector<std::string>& server_args) {
    auto server =
        testing::StartServerWithView(testing::ProgramPath("ccmd_server"), dir_.path(), server_args);
    ASSERT_TRUE(server.ok()) << server.status().ToString();
    server_.emplace(std::move(server).value());
    ASSERT_NO_FATAL_FAILURE(OpenPage(server_->url));
  }

  // Headless Chromium on the page at `url`.
  void OpenPage(const std::string& url) {
    browser_options_.log_path = dir_.File("chromium.log");
    auto browser = testing::HeadlessBrowser::Launch(browser_options_);
    ASSERT_TRUE(browser.ok()) << browser.status().ToString();
    browser_ = std::move(browser).value();
    ASSERT_TRUE(browser_->Open(url).ok()) << browser_->PageLog();
  }

  Json Script(const std::string& js, double timeout_s = 120) {
    auto r = browser_->Evaluate(js, timeout_s);
    EXPECT_TRUE(r.ok()) << js << ": " << r.status().ToString() << "\n" << browser_->PageLog();
    return r.ok() ? *r : Json();
  }

  Subprocess StartAgent(const std::string& name, const std::vector<std::string>& extra) {
    std::vector<std::string> args = {testing::ProgramPath("ccmd_agent"), "--source",
                                     "tum:" + dir_.File("seq"), "--server",
                                     "127.0.0.1:" + std::to_string(server_->port), "--name", name,
                                     // Its own spill folder (and identity file): the default
                                     // one in /tmp is shared with any other agent of that name
                                     // on the machine, such as another test's.
                                     "--spill-dir", dir_.File("spill-" + name)};
    args.insert(args.end(), extra.begin(), extra.end());
    auto agent = Subprocess::Start(args, dir_.File(name + ".out"), dir_.File(name + ".log"));
    EXPECT_TRUE(agent.ok()) << agent.status().ToString();
    return std::move(agent).value();
  }

  // Once the server stops changing, the page holds the same state: the server's event number
  // is the same before and after the page has applied it and drawn every cloud. Returns the
  // server's state and the page's at that number.
  std::pair<Json, Json> Settled() {
    Json state, shown;
    const double deadline = MonotonicSeconds() + 240;
    while (true) {
      state = Get(server_->view_port, "/api/state");
      const long seq = static_cast<long>(state.Get("seq")->number());
      shown = Script(
          "ccmdView.whenSettled(" + std::to_string(seq) + ").then(() => ccmdView.state())", 240);
      if (static_cast<long>(Get(server_->view_port, "/api/state").Get("seq")->number()) == seq &&
          static_cast<long>(shown.Get("seq")->number()) == seq) {
        return {state, shown};
      }
      EXPECT_LT(MonotonicSeconds(), deadline) << "the server never stopped changing";
      if (MonotonicSeconds() > deadline) return {state, shown};
    }
  }

  testing::TempDir dir_;
  std::optional<testing::ServerWithView> server_;
  testing::BrowserOptions browser_options_;
  std::unique_ptr<testing::HeadlessBrowser> browser_;
};

TEST_F(ViewBrowserTest, ThePageDrawsWhatTheServerHoldsDuringASplitReplay) {
  SyntheticSequenceOptions synth;
  synth.frames = 200;
  synth.width = 320;
  synth.height = 240;
  synth.threads = 2;
  ASSERT_TRUE(WriteSyntheticSequence(dir_.File("seq"), synth).ok());

  // Every point kept: the page keeps a keyframe's cloud as it first loaded it, and does not yet
  // reload it when the dense store compacts the keyframe (its points then differ).
  ASSERT_NO_FATAL_FAILURE(Open({"--dense-every-point"}));
  // Before any agent: connected, and it says there is no map yet.
  const Json waiting = Script("ccmdView.whenConnection('live').then(() => ccmdView.state())");
  ASSERT_TRUE(waiting.Get("status"));
  EXPECT_NE(waiting.Get("status")->string().find("No map yet"), std::string::npos)
      << waiting.Dump();

  std::vector<Subprocess> agents;
  for (int i = 1; i <= 2; ++i) {
    agents.push_back(StartAgent(
        "agent" + std::to_string(i),
        {"--segment", std::to_string(i) + "/2", "--rgbd-every-keyframe"}));  // more clouds to check
  }
  for (Subprocess& a : agents) EXPECT_EQ(a.Wait().exit_code, 0);
  const double deadline = MonotonicSeconds() + 240;
  const auto [state, shown] = Settled();
  const std::uint16_t view = server_->view_port;

  // Every keyframe of the server, where the server has it, every cloud drawn.
  std::map<std::string, const Json*> on_page;
  for (const Json& kf : shown.Get("keyframes")->array()) on_page[Key(kf)] = &kf;
  ASSERT_EQ(on_page.size(), state.Get("keyframes")->size());
  ASSERT_GT(on_page.size(), 10u);
  int clouds = 0;
  std::vector<const Json*> moved;
  for (const Json& kf : state.Get("keyframes")->array()) {
    ASSERT_EQ(on_page.count(Key(kf)), 1u) << Key(kf);
    const Json& p = *on_page[Key(kf)];
    EXPECT_EQ(p.Get("m")->number(), kf.Get("m")->number()) << Key(kf);
    for (int i = 0; i < 12; ++i)
      EXPECT_NEAR(p.Get("T")->at(i).number(), kf.Get("T")->at(i).number(), 1e-9);
    if (kf.Get("cloud")->boolean()) {
      ++clouds;
      EXPECT_TRUE(p.Get("drawn")->boolean()) << Key(kf);
      if (kf.Get("moves")->number() > 0) moved.push_back(&kf);
    }
  }
  EXPECT_GE(clouds, 8);
  EXPECT_EQ(shown.Get("cloudErrors")->number(), 0);

  // Keyframes that moved after they were drawn first are drawn where their pose says: their
  // points go through the pose the page holds for them on the GPU (which is the server's, as
  // checked above at one event number; the page's pose is read again here, with the point,
  // because the server may still move keyframes after that event, as a global BA finishing
  // does). A pose update the GPU missed would move the point by the update, centimetres after
  // a loop.
  ASSERT_FALSE(moved.empty())
      << "no keyframe with a cloud moved: nothing shows that updates reach the page";
  for (std::size_t i = 0; i < moved.size() && i < 8; ++i) {
    const Json& kf = *moved[i];
    httplib::Client client("127.0.0.1", view);
    auto r = client.Get(("/api/clouds?ids=" + Key(kf)).c_str());
    ASSERT_TRUE(r && r->status == 200);
    auto cloud = ParseViewClouds(r->body);
    ASSERT_TRUE(cloud.ok() && cloud->size() == 1 && !cloud->front().points_mm.empty());
    for (std::size_t j : {std::size_t{0}, cloud->front().points_mm.size() - 1}) {
      const Json point =
          Script("ccmdView.drawnPoint(" + std::to_string(static_cast<int>(kf.Get("a")->number())) +
                 ", " + std::to_string(static_cast<long>(kf.Get("k")->number())) + ", " +
                 std::to_string(j) + ")");
      ASSERT_TRUE(point.Has("held") && point.Has("world") && point.Has("T")) << Key(kf);
      const Json& held = *point.Get("held");
      Eigen::Matrix<double, 3, 4> T;
      for (int e = 0; e < 12; ++e) T(e / 4, e % 4) = point.Get("T")->at(e).number();
      const Eigen::Vector3d expected =
          T * Eigen::Vector4d(held.at(0).number() * 1e-3, held.at(1).number() * 1e-3,
                              held.at(2).number() * 1e-3, 1);
      for (int a = 0; a < 3; ++a) {
        EXPECT_NEAR(point.Get("world")->at(a).number(), expected(a), 1e-6) << Key(kf);
        // The page's point is the server's (--dense-every-point: no compaction changes it).
        EXPECT_NEAR(held.at(a).number(), cloud->front().points_mm[j][a], 0.5) << Key(kf);
      }
    }
  }

  // The agents' panel shows the server's counts (statistics come once a second).
  const Json summary = Get(view, "/api/summary");
  EXPECT_EQ(summary.Get("keyframes")->number(), static_cast<double>(on_page.size()));
  std::map<std::string, double> counts;
  for (const Json& a : summary.Get("agents")->array())
    counts[a.Get("name")->string()] = a.Get("keyframes")->number();
  ASSERT_EQ(counts.size(), 2u);
  Json panel_state = shown;
  while (true) {
    std::map<std::string, double> panel;
    for (const Json& row : panel_state.Get("panel")->array()) {
      panel[row.Get("name")->string()] = row.Get("keyframes")->number();
    }
    if (panel == counts) break;
    ASSERT_LT(MonotonicSeconds(), deadline) << "the panel never showed the server's counts";
    panel_state =
        Script("ccmdView.whenStats(" +
               std::to_string(static_cast<long>(panel_state.Get("statsVersion")->number())) +
               ").then(() => ccmdView.state())");
  }

  // A picture of it: the 3D view (left of the panel) is not empty.
  Script("ccmdView.whenRested()");
  auto png = browser_->Screenshot();
  ASSERT_TRUE(png.ok());
  const cv::Mat image =
      cv::imdecode(std::vector<uchar>(png->begin(), png->end()), cv::IMREAD_COLOR);
  ASSERT_EQ(image.cols, browser_options_.width);
  int drawn_pixels = 0;
  for (int v = 0; v < image.rows; ++v) {
    for (int u = 0; u < image.cols - 380; ++u) {
      const cv::Vec3b c = image.at<cv::Vec3b>(v, u);
      drawn_pixels += std::abs(c[0] - 29) + std::abs(c[1] - 24) + std::abs(c[2] - 21) > 30;
    }
  }
  EXPECT_GT(drawn_pixels, image.rows * (image.cols - 380) / 20);
  if (const char* keep = std::getenv("CCMD_VIEW_SCREENSHOT")) {
    EXPECT_TRUE(WriteFileAtomic(keep, *png).ok());
  }

  // The server stops: it writes what the page showed, and the page says it is gone.
  ASSERT_TRUE(server_->process.Signal(SIGINT).ok());
  EXPECT_EQ(server_->process.Wait().exit_code, 0);
  for (const auto& [name, n] : counts) {
    auto trajectory = ReadTumTrajectory(dir_.File("results/trajectory_" + name + ".txt"));
    ASSERT_TRUE(trajectory.ok());
    EXPECT_EQ(static_cast<double>(trajectory->size()), n) << name;
  }
  const Json gone = Script("ccmdView.whenConnection('gone').then(() => ccmdView.state())");
  EXPECT_NE(gone.Get("status")->string().find("Server gone"), std::string::npos)
      << gone.Get("status")->string();
  EXPECT_EQ(gone.Get("keyframes")->size(), on_page.size());  // the last map stays on screen
}

// One agent circling a room twice against a server that culls keyframes soon after they
// arrive: the second lap's keyframes are culled, and the page holds what the server's state
// holds (a culled keyframe only while its cloud is in the dense store, marked culled), draws
// every cloud the state has and none it released.
TEST_F(ViewBrowserTest, ThePageLetsCulledKeyframesGoAsTheServerDoes) {
  SyntheticSequenceOptions synth;
  synth.frames = 400;
  synth.width = 320;
  synth.height = 240;
  synth.path.loop_period_s = 8;  // 240 frames a lap
  synth.threads = 2;
  ASSERT_TRUE(WriteSyntheticSequence(dir_.File("seq"), synth).ok());
  ASSERT_NO_FATAL_FAILURE(Open({"--culling-keep-recent", "20"}));
  Script("ccmdView.whenConnection('live')");
  EXPECT_EQ(StartAgent("agent1", {}).Wait().exit_code, 0);
  const auto [state, shown] = Settled();
  std::map<std::string, const Json*> on_page;
  for (const Json& kf : shown.Get("keyframes")->array()) on_page[Key(kf)] = &kf;
  ASSERT_EQ(on_page.size(), state.Get("keyframes")->size());
  int culled_with_cloud = 0;
  for (const Json& kf : state.Get("keyframes")->array()) {
    ASSERT_EQ(on_page.count(Key(kf)), 1u) << Key(kf);
    const Json& p = *on_page[Key(kf)];
    const bool culled = kf.Has("culled") && kf.Get("culled")->boolean();
    EXPECT_EQ(p.Get("culled")->boolean(), culled) << Key(kf);
    EXPECT_EQ(p.Get("drawn")->boolean(), kf.Get("cloud")->boolean()) << Key(kf);
    culled_with_cloud += culled;
  }
  // The server culled keyframes: those without a cloud (a third or so send RGB-D) left the
  // page, those with one stay, off the path, until their cloud is released.
  const Json summary = Get(server_->view_port, "/api/summary");
  const double held = summary.Get("keyframes")->number();
  ASSERT_TRUE(server_->process.Signal(SIGINT).ok());
  EXPECT_EQ(server_->process.Wait().exit_code, 0);
  auto text = ReadFileToString(dir_.File("results/server_stats.json"));
  ASSERT_TRUE(text.ok());
  auto stats = Json::Parse(*text);
  ASSERT_TRUE(stats.ok());
  const double culled = stats->Get("backend")->Get("keyframes_culled")->number();
  EXPECT_GE(culled, 10);
  EXPECT_GT(culled_with_cloud, 0);
  EXPECT_LT(culled_with_cloud, culled);
  EXPECT_EQ(static_cast<double>(on_page.size()), held - culled + culled_with_cloud);
  auto trajectory = ReadTumTrajectory(dir_.File("results/trajectory_agent1.txt"));
  ASSERT_TRUE(trajectory.ok());
  EXPECT_EQ(static_cast<double>(trajectory->size()), held);  // the trajectory keeps them all
}

// A long mission, fed to the view as the back-end tells it (ccmd_server on the synthetic room
// releases no cloud in a run of a few laps: every keyframe of a place seen again still stores
// hundreds of new voxels, docs/benchmarks/dense.md). One agent maps a room with kPlaces
// keyframes, then circles it again: each later keyframe is a place seen again, culled, and its
// cloud released once 4 newer ones follow (the dense store's filter window). 600 keyframes pass
// through the page, more than two chunks' slots, and it loads every cloud before it is
// released. The page's buffers hold at most twice the points it draws at any time, in one
// chunk; a cloud announced again is not loaded twice; a cloud that leaves the dense map and
// comes back is loaded again without keeping the old copy; the room's keyframes are drawn with
// the server's points through all of it; and once every cloud is released, nothing is left.
// (Without the page's compaction the buffers keep every point loaded: 1.2 million here.)
TEST_F(ViewBrowserTest, ThePageFreesTheCloudsTheServerReleases) {
  constexpr int kKeyframes = 600, kBatch = 20, kWindow = 4;
  const AgentId agent(1);
  const MapId map(1);
  DenseMapOptions dense_options;
  dense_options.compact_keyframes = false;  // releases come from the test only
  auto created = DenseMap::Create(dense_options);
  ASSERT_TRUE(created.ok());
  std::unique_ptr<DenseMap> dense = std::move(created).value();
  ASSERT_TRUE(dense->SetAgentMap(agent, map).ok());
  ViewModel model;
  model.OnAgent(agent, "agent1");
  ViewServerOptions options;
  options.web_dir = WebDir();
  auto started = ViewServer::Start(options, &model, dense.get(), [&] {
    ViewStats s;
    s.keyframes = model.Keyframes().size();
    s.maps.push_back({map, s.keyframes, true, {agent}});
    ViewAgentStats a;
    a.id = agent;
    a.name = "agent1";
    a.keyframes = s.keyframes;
    a.map = map;
    s.agents.push_back(a);
    return s;
  });
  ASSERT_TRUE(started.ok()) << started.status().ToString();
  std::unique_ptr<ViewServer> server = std::move(started).value();
  ASSERT_NO_FATAL_FAILURE(OpenPage(server->url()));
  Script("ccmdView.whenConnection('live')");

  // Only the test changes the model: once the page has applied its last event, loaded every
  // cloud and drawn a frame, it holds the model's state.
  const auto settled = [&] {
    return Script("ccmdView.whenSettled(" + std::to_string(model.last_seq()) +
                  ").then(() => ccmdView.state())");
  };
  const auto id_of = [&](int k) { return GlobalKeyframeId{agent, KeyframeId(k)}; };
  const auto add = [&](int k) {
    const Pose T = PlacePose(k % kPlaces);
    ASSERT_TRUE(dense->AddKeyframeCloud(id_of(k), T, PlaceCloud(k % kPlaces)).ok());
    model.OnKeyframe(id_of(k), map, T, MonotonicSeconds(), true);
    model.OnDenseKeyframe(id_of(k), map, T);
  };
  const auto release = [&](const std::vector<GlobalKeyframeId>& ids) {
    for (const GlobalKeyframeId& id : ids) ASSERT_TRUE(dense->RemoveKeyframe(id).ok());
    model.OnDenseReleased(ids);
  };
  const auto number = [](const Json& state, const char* name) { return state.Get(name)->number(); };

  std::deque<GlobalKeyframeId> revisits;  // places seen again whose cloud is held, oldest first
  double loaded_points = 0;
  for (int k = 0; k < kKeyframes; ++k) {
    ASSERT_NO_FATAL_FAILURE(add(k));
    if (k >= kPlaces) revisits.push_back(id_of(k));
    if ((k + 1) % kBatch != 0) continue;
    // Every cloud so far drawn; then the revisits with kWindow newer ones are culled and
    // their clouds released.
    const Json loaded = settled();
    ASSERT_EQ(loaded.Get("keyframes")->size(),
              static_cast<std::size_t>(std::min(k + 1, kPlaces)) + revisits.size());
    std::vector<GlobalKeyframeId> released;
    while (revisits.size() > kWindow) {
      released.push_back(revisits.front());
      revisits.pop_front();
      model.OnCulled(map, released.back());
    }
    ASSERT_NO_FATAL_FAILURE(release(released));
    const Json shown = settled();
    const double drawn = number(shown, "totalPoints"), held = number(shown, "bufferedPoints");
    loaded_points = number(shown, "loadedPoints");
    EXPECT_EQ(drawn, 2000.0 * static_cast<double>(shown.Get("keyframes")->size())) << k;
    EXPECT_GE(held, drawn) << k;
    EXPECT_LE(held, 2 * drawn) << "after keyframe " << k << ": the buffers keep released clouds ("
                               << number(shown, "loadedPoints") << " points loaded)";
    EXPECT_EQ(number(shown, "chunks"), 1) << k;  // the keyframes drawn fit one chunk's slots
  }
  EXPECT_EQ(loaded_points, 2000.0 * kKeyframes);  // every cloud went through the buffers
  EXPECT_EQ(number(settled(), "cloudErrors"), 0);

  // A second cloud event for a cloud the page holds loads nothing.
  const Json before = settled();
  model.OnDenseKeyframe(id_of(0), map, PlacePose(0));
  const Json again = settled();
  EXPECT_EQ(number(again, "loadedPoints"), number(before, "loadedPoints"));
  EXPECT_EQ(number(again, "bufferedPoints"), number(before, "bufferedPoints"));
  // A keyframe whose cloud leaves the dense map and comes back (a restarted segment's, unplaced
  // then placed by a loop): the page loads it once more, into a new slot, and the old copy,
  // hidden, goes with the chunk's next compaction.
  model.OnPlacement(map, {id_of(1)}, false);
  ASSERT_TRUE(dense->RemoveKeyframe(id_of(1)).ok());
  EXPECT_EQ(number(settled(), "totalPoints"), number(again, "totalPoints") - 2000);
  model.OnPlacement(map, {id_of(1)}, true);
  ASSERT_TRUE(dense->AddKeyframeCloud(id_of(1), PlacePose(1), PlaceCloud(1)).ok());
  model.OnDenseKeyframe(id_of(1), map, PlacePose(1));
  const Json back = settled();
  EXPECT_EQ(number(back, "totalPoints"), number(again, "totalPoints"));
  EXPECT_EQ(number(back, "loadedPoints"), number(again, "loadedPoints") + 2000);
  EXPECT_LE(number(back, "bufferedPoints"), 2 * number(back, "totalPoints"));

  // The room's keyframes are drawn as at first, through every compaction: their first and last
  // points are the server's, drawn through their pose.
  httplib::Client client("127.0.0.1", server->port());
  for (int p = 0; p < kPlaces; ++p) {
    auto r = client.Get(("/api/clouds?ids=1:" + std::to_string(p)).c_str());
    ASSERT_TRUE(r && r->status == 200);
    auto cloud = ParseViewClouds(r->body);
    ASSERT_TRUE(cloud.ok() && cloud->size() == 1 && cloud->front().points_mm.size() == 2000);
    for (std::size_t j : {std::size_t{0}, std::size_t{1999}}) {
      const Json point =
          Script("ccmdView.drawnPoint(1, " + std::to_string(p) + ", " + std::to_string(j) + ")");
      ASSERT_TRUE(point.Has("held") && point.Has("world")) << p;
      const Eigen::Vector4d held(point.Get("held")->at(0).number() * 1e-3,
                                 point.Get("held")->at(1).number() * 1e-3,
                                 point.Get("held")->at(2).number() * 1e-3, 1);
      const Eigen::Vector3d expected = PlacePose(p).matrix().topRows<3>() * held;
      for (int a = 0; a < 3; ++a) {
        EXPECT_EQ(point.Get("held")->at(a).number(), cloud->front().points_mm[j][a]) << p;
        EXPECT_NEAR(point.Get("world")->at(a).number(), expected(a), 1e-6) << p;
      }
    }
  }

  // Every cloud released (the last revisits culled): the room's keyframes stay without one,
  // and the buffers are empty.
  std::vector<GlobalKeyframeId> all(revisits.begin(), revisits.end());
  for (const GlobalKeyframeId& id : all) model.OnCulled(map, id);
  for (int p = 0; p < kPlaces; ++p) all.push_back(id_of(p));
  ASSERT_NO_FATAL_FAILURE(release(all));
  const Json empty = settled();
  EXPECT_EQ(empty.Get("keyframes")->size(), static_cast<std::size_t>(kPlaces));
  EXPECT_EQ(number(empty, "totalPoints"), 0);
  EXPECT_EQ(number(empty, "bufferedPoints"), 0);
  EXPECT_EQ(number(empty, "chunks"), 0);
  server->Stop();
}

}  // namespace
}  // namespace ccmd
