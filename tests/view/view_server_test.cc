// The live view's HTTP endpoints on a known map: the state, summary and clouds are exactly
// what the server was fed, a pose update reaches an open event stream, a stream too far
// behind is told to reload, and the server refuses writes, foreign hosts and wrong tokens.

#include <gtest/gtest.h>

#include <future>
#include <set>
#include <thread>

#include "libccmd/util/file_util.h"
#include "libccmd/view/view_server.h"
#include "tests/support/headless_browser.h"
#include "tests/support/test_support.h"

// After Eigen (through the headers above): httplib.h brings <resolv.h>, whose _res macro
// breaks Eigen's headers when they come later.
#include <httplib.h>

namespace ccmd {
namespace {

GlobalKeyframeId Id(int agent, int keyframe) {
  return {AgentId(static_cast<std::uint16_t>(agent)),
          KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

Pose PoseOf(int agent, int keyframe) {
  Pose T = Pose::Identity();
  T.linear() =
      Eigen::AngleAxisd(0.1 * keyframe + 0.5 * agent, Eigen::Vector3d(0.2, 1, 0.1).normalized())
          .toRotationMatrix();
  T.translation() = Eigen::Vector3d(0.3 * keyframe, -0.1 * agent, 0.05 * keyframe);
  return T;
}

// A plane 1.2-2 m in front of the camera on a 1 cm grid (off the voxel boundaries).
CameraCloud PlaneCloud(int agent, int keyframe) {
  CameraCloud cloud;
  const float z = 1.2f + 0.2f * static_cast<float>(keyframe);
  for (int i = 0; i < 60; ++i) {
    for (int j = 0; j < 40; ++j) {
      cloud.points.emplace_back(-0.295f + 0.01f * i, -0.195f + 0.01f * j, z + 0.001f * i);
      cloud.colors.push_back({static_cast<std::uint8_t>(40 * agent), static_cast<std::uint8_t>(i),
                              static_cast<std::uint8_t>(j)});
    }
  }
  return cloud;
}

const std::vector<std::pair<int, int>> kKeyframes = {{1, 0}, {1, 1}, {1, 2}, {2, 0}, {2, 1}};

class ViewServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    for (const char* name :
         {"index.html", "view.js", "view.css", "three.min.js", "OrbitControls.js"}) {
      ASSERT_TRUE(WriteFileAtomic(web_.File(name), std::string("content of ") + name).ok());
    }
    auto dense = DenseMap::Create();
    ASSERT_TRUE(dense.ok());
    dense_ = std::move(dense).value();
    model_ = std::make_unique<ViewModel>(model_options_);
    model_->OnAgent(AgentId(1), "alpha");
    model_->OnAgent(AgentId(2), "beta");
    for (const auto& [a, k] : kKeyframes) {
      ASSERT_TRUE(dense_->SetAgentMap(AgentId(static_cast<std::uint16_t>(a)), MapId(1)).ok());
      ASSERT_TRUE(dense_->AddKeyframeCloud(Id(a, k), PoseOf(a, k), PlaneCloud(a, k)).ok());
      model_->OnKeyframe(Id(a, k), MapId(1), PoseOf(a, k), 1.0, true);
      model_->OnDenseKeyframe(Id(a, k), MapId(1), PoseOf(a, k));
    }
  }

  ViewStats Stats() const {
    ViewStats s;
    s.keyframes = kKeyframes.size();
    s.points = dense_->Stats().kept_points;
    s.maps.push_back({MapId(1), kKeyframes.size(), true, {AgentId(1), AgentId(2)}});
    ViewAgentStats alpha;
    alpha.id = AgentId(1);
    alpha.name = "alpha";
    alpha.keyframes = 3;
    alpha.bytes = 123456;
    alpha.map = MapId(1);
    alpha.traffic_kBps = {1.5, 2.5};
    ViewAgentStats beta = alpha;
    beta.id = AgentId(2);
    beta.name = "beta";
    beta.keyframes = 2;
    beta.bytes = 789;
    s.agents = {alpha, beta};
    return s;
  }

  std::unique_ptr<ViewServer> Start(const std::string& listen = "127.0.0.1:0",
                                    const std::string& token = "") {
    ViewServerOptions options;
    options.listen = listen;
    options.token = token;
    options.web_dir = web_.path();
    options.max_event_streams = max_streams_;
    auto server =
        ViewServer::Start(options, model_.get(), dense_.get(), [this] { return Stats(); });
    EXPECT_TRUE(server.ok()) << server.status().ToString();
    return server.ok() ? std::move(server).value() : nullptr;
  }

  static Json GetJson(httplib::Client* client, const std::string& path) {
    auto r = client->Get(path.c_str());
    EXPECT_TRUE(r && r->status == 200) << path << ": " << (r ? r->status : -1);
    if (!r || r->status != 200) return Json();
    auto j = Json::Parse(r->body);
    EXPECT_TRUE(j.ok());
    return j.ok() ? *j : Json();
  }

  testing::TempDir web_;
  ViewModelOptions model_options_;
  int max_streams_ = 8;
  std::unique_ptr<DenseMap> dense_;
  std::unique_ptr<ViewModel> model_;
};

TEST_F(ViewServerTest, StateSummaryAndCloudsAreExactlyTheMapItWasFed) {
  auto server = Start();
  ASSERT_TRUE(server);
  EXPECT_EQ(server->url(), "http://127.0.0.1:" + std::to_string(server->port()) + "/");
  httplib::Client client("127.0.0.1", server->port());

  const Json state = GetJson(&client, "/api/state");
  ASSERT_EQ(state.Get("keyframes")->size(), kKeyframes.size());
  std::set<std::pair<int, int>> ids;
  for (const Json& kf : state.Get("keyframes")->array()) {
    const int a = static_cast<int>(kf.Get("a")->number()),
              k = static_cast<int>(kf.Get("k")->number());
    ids.insert({a, k});
    EXPECT_TRUE(kf.Get("cloud")->boolean());
    EXPECT_EQ(kf.Get("m")->number(), 1);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 4; ++c)
        EXPECT_NEAR(kf.Get("T")->at(4 * r + c).number(), PoseOf(a, k).matrix()(r, c), 1e-9);
    }
  }
  const std::set<std::pair<int, int>> fed(kKeyframes.begin(), kKeyframes.end());
  EXPECT_EQ(ids, fed);
  EXPECT_EQ(state.Get("seq")->number(), model_->last_seq());

  const Json summary = GetJson(&client, "/api/summary");
  EXPECT_EQ(summary.Get("maps")->number(), 1);
  EXPECT_EQ(summary.Get("keyframes")->number(), 5);
  EXPECT_EQ(summary.Get("points")->number(), dense_->Stats().kept_points);
  ASSERT_EQ(summary.Get("agents")->size(), 2u);
  EXPECT_EQ(summary.Get("agents")->at(0).Get("name")->string(), "alpha");
  EXPECT_EQ(summary.Get("agents")->at(0).Get("keyframes")->number(), 3);
  EXPECT_EQ(summary.Get("agents")->at(0).Get("bytes")->number(), 123456);
  EXPECT_EQ(summary.Get("agents")->at(1).Get("keyframes")->number(), 2);
  EXPECT_TRUE(summary.Get("map_list")->at(0).Get("primary")->boolean());

  // Every cloud point is a point the keyframe was added with (to the millimetre), coloured as
  // it was; one point per viewing voxel.
  auto r = client.Get("/api/clouds?ids=1:0,1:1,1:2,2:0,2:1,7:7");
  ASSERT_TRUE(r && r->status == 200);
  auto clouds = ParseViewClouds(r->body);
  ASSERT_TRUE(clouds.ok()) << clouds.status().ToString();
  ASSERT_EQ(clouds->size(), 6u);
  for (std::size_t i = 0; i < kKeyframes.size(); ++i) {
    const ViewCloud& c = (*clouds)[i];
    EXPECT_EQ(c.id, Id(kKeyframes[i].first, kKeyframes[i].second));
    ASSERT_TRUE(c.found);
    const CameraCloud original = PlaneCloud(kKeyframes[i].first, kKeyframes[i].second);
    std::map<std::array<int, 3>, std::array<std::uint8_t, 3>> by_mm;
    std::set<std::array<long, 3>> voxels;
    for (std::size_t j = 0; j < original.size(); ++j) {
      const Eigen::Vector3f& p = original.points[j];
      by_mm[{static_cast<int>(std::lround(p.x() * 1e3)), static_cast<int>(std::lround(p.y() * 1e3)),
             static_cast<int>(std::lround(p.z() * 1e3))}] = original.colors[j];
      const Eigen::Vector3d v = (p.cast<double>() * (1.0 / 0.02)).array().floor();
      voxels.insert({std::lround(v.x()), std::lround(v.y()), std::lround(v.z())});
    }
    EXPECT_EQ(c.points_mm.size(), voxels.size());
    for (std::size_t j = 0; j < c.points_mm.size(); ++j) {
      const auto it = by_mm.find({c.points_mm[j][0], c.points_mm[j][1], c.points_mm[j][2]});
      ASSERT_NE(it, by_mm.end());
      EXPECT_EQ(it->second, c.colors[j]);
    }
  }
  EXPECT_FALSE(clouds->back().found);

  // Bad requests get a clear refusal.
  for (const char* bad :
       {"/api/clouds", "/api/clouds?ids=1-0", "/api/clouds?ids=1:x", "/api/events?after=-3"}) {
    auto b = client.Get(bad);
    ASSERT_TRUE(b);
    EXPECT_EQ(b->status, 400) << bad;
  }
  std::string many;
  for (int k = 0; k < 65; ++k) many += (k ? "," : "") + std::string("1:") + std::to_string(k);
  EXPECT_EQ(client.Get(("/api/clouds?ids=" + many).c_str())->status, 400);
  // The page and its scripts, as they are on disk.
  EXPECT_EQ(client.Get("/")->body, "content of index.html");
  EXPECT_EQ(client.Get("/three.min.js")->body, "content of three.min.js");
  EXPECT_EQ(client.Get("/nothing")->status, 404);
}

// Reads an event stream until `until` is in it (or the stream ends); returns what came.
std::string ReadStream(std::uint16_t port, const std::string& path, const std::string& until,
                       const httplib::Headers& headers = {}) {
  httplib::Client client("127.0.0.1", port);
  client.set_read_timeout(120, 0);
  std::string text;
  client.Get(path.c_str(), headers, [&](const char* data, std::size_t n) {
    text.append(data, n);
    return text.find(until) == std::string::npos;
  });
  return text;
}

TEST_F(ViewServerTest, APoseUpdateReachesAnOpenEventStream) {
  auto server = Start();
  ASSERT_TRUE(server);
  const std::uint64_t seq = model_->last_seq();
  auto stream = std::async(std::launch::async, [&] {
    return ReadStream(server->port(), "/api/events?after=" + std::to_string(seq),
                      "\"type\":\"poses\"");
  });
  Pose moved = PoseOf(1, 1);
  moved.translation() += Eigen::Vector3d(0.5, -0.25, 0.125);
  model_->OnPoses(PoseSource::kLoop, MapId(1), {{Id(1, 1), moved}}, 5.0);
  const std::string text = stream.get();
  const std::size_t at = text.find("id: " + std::to_string(seq + 1) + "\ndata: ");
  ASSERT_NE(at, std::string::npos) << text;
  const std::size_t data = text.find("data: ", at) + 6;
  auto event = Json::Parse(text.substr(data, text.find('\n', data) - data));
  ASSERT_TRUE(event.ok()) << text;
  EXPECT_EQ(event->Get("src")->string(), "loop");
  const Json& kf = event->Get("kfs")->at(0);
  EXPECT_EQ(kf.at(0).number(), 1);
  EXPECT_EQ(kf.at(1).number(), 1);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c)
      EXPECT_NEAR(kf.at(2 + 4 * r + c).number(), moved.matrix()(r, c), 1e-9);
  }
  // A browser that reconnects names the last event it saw (Last-Event-ID) and gets the rest.
  const std::string resumed = ReadStream(server->port(), "/api/events", "\"type\":\"poses\"",
                                         {{"Last-Event-ID", std::to_string(seq)}});
  EXPECT_NE(resumed.find("id: " + std::to_string(seq + 1)), std::string::npos) << resumed;
  // And the new pose is in the state.
  httplib::Client client("127.0.0.1", server->port());
  const Json state = GetJson(&client, "/api/state");
  for (const Json& k : state.Get("keyframes")->array()) {
    if (k.Get("a")->number() == 1 && k.Get("k")->number() == 1) {
      EXPECT_NEAR(k.Get("T")->at(3).number(), moved.translation().x(), 1e-9);
    }
  }
}

TEST_F(ViewServerTest, CloudEventsCarryTheCloudSoTheBrowserNeedNotAsk) {
  auto server = Start();
  ASSERT_TRUE(server);
  const std::string text = ReadStream(server->port(), "/api/events?after=0", "\"type\":\"cloud\"");
  const std::size_t at = text.find("\"type\":\"cloud\"");
  ASSERT_NE(at, std::string::npos) << text;
  const std::size_t start = text.rfind("data: ", at) + 6;
  auto event = Json::Parse(text.substr(start, text.find('\n', start) - start));
  ASSERT_TRUE(event.ok());
  ASSERT_TRUE(event->Get("data")) << "no cloud inlined";
  auto bytes = testing::DecodeBase64(event->Get("data")->string());
  ASSERT_TRUE(bytes.ok());
  const std::string id = std::to_string(static_cast<int>(event->Get("a")->number())) + ":" +
                         std::to_string(static_cast<int>(event->Get("k")->number()));
  httplib::Client client("127.0.0.1", server->port());
  auto asked = client.Get(("/api/clouds?ids=" + id).c_str());
  ASSERT_TRUE(asked && asked->status == 200);
  EXPECT_EQ(*bytes, asked->body);  // the same record either way
}

TEST_F(ViewServerTest, AStreamTooFarBehindIsToldToReload) {
  model_options_.max_events = 16;
  SetUp();  // again, with the small log
  for (int k = 10; k < 40; ++k) model_->OnKeyframe(Id(1, k), MapId(1), PoseOf(1, k), 1.0, true);
  auto server = Start();
  ASSERT_TRUE(server);
  // The stream ends after the reset, so this returns without a match.
  const std::string text = ReadStream(server->port(), "/api/events?after=1", "never");
  EXPECT_NE(text.find(R"({"type":"reset"})"), std::string::npos) << text;
}

TEST_F(ViewServerTest, StopEndsStreamsAndLimitsTheirNumber) {
  max_streams_ = 1;
  auto server = Start();
  ASSERT_TRUE(server);
  std::promise<void> opened;
  auto first = std::async(std::launch::async, [&] {
    httplib::Client client("127.0.0.1", server->port());
    client.set_read_timeout(120, 0);
    bool told = false;
    return client.Get("/api/events?after=0", [&](const char*, std::size_t) {
      if (!told) opened.set_value();
      told = true;
      return true;
    });
  });
  opened.get_future().wait();  // the stream sent its first events: it holds its place
  httplib::Client client("127.0.0.1", server->port());
  auto second = client.Get("/api/events?after=0");
  ASSERT_TRUE(second);
  EXPECT_EQ(second->status, 503);
  server->Stop();  // ends the open stream
  auto ended = first.get();
  EXPECT_TRUE(ended);
}

TEST_F(ViewServerTest, RefusesWritesForeignHostsAndMissingScripts) {
  auto server = Start();
  ASSERT_TRUE(server);
  httplib::Client client("127.0.0.1", server->port());
  EXPECT_EQ(client.Post("/api/state", "x", "text/plain")->status, 405);
  EXPECT_EQ(client.Delete("/api/state")->status, 405);
  EXPECT_EQ(client.Put("/", "x", "text/plain")->status, 405);
  // A page elsewhere that names a host resolving to 127.0.0.1 (DNS rebinding) gets nothing.
  auto foreign = client.Get("/api/state", {{"Host", "evil.example:80"}});
  ASSERT_TRUE(foreign);
  EXPECT_EQ(foreign->status, 403);
  EXPECT_EQ(client.Get("/api/state", {{"Host", "localhost:1"}})->status, 200);

  ViewServerOptions options;
  options.web_dir = web_.File("nowhere");
  auto missing = ViewServer::Start(options, model_.get(), dense_.get(), [this] { return Stats(); });
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.status().message().find("libjs-three"), std::string::npos)
      << missing.status().ToString();
  options.web_dir = web_.path();
  options.token = "no spaces please";
  EXPECT_FALSE(options.Validate().ok());
  options.token = "";
  options.listen = "127.0.0.1";
  EXPECT_FALSE(options.Validate().ok());
}

TEST_F(ViewServerTest, ANonLoopbackAddressNeedsTheToken) {
  auto server = Start("0.0.0.0:0");
  ASSERT_TRUE(server);
  const std::string token = server->token();
  EXPECT_EQ(token.size(), 32u);  // 128 random bits, made up as none was given
  EXPECT_NE(server->url().find("?token=" + token), std::string::npos) << server->url();
  httplib::Client client("127.0.0.1", server->port());
  EXPECT_EQ(client.Get("/api/summary")->status, 403);
  EXPECT_EQ(client.Get("/api/summary?token=wrong")->status, 403);
  // The token with its last character changed (to one it is not).
  const std::string near = token.substr(0, 31) + (token.back() == '0' ? "1" : "0");
  EXPECT_EQ(client.Get(("/api/summary?token=" + near).c_str())->status, 403);
  EXPECT_EQ(client.Get(("/api/summary?token=" + token).c_str())->status, 200);
  EXPECT_EQ(client.Get("/api/summary", {{"Authorization", "Bearer " + token}})->status, 200);
  EXPECT_EQ(client.Get("/api/clouds?ids=1:0")->status, 403);
  EXPECT_EQ(client.Get("/api/events")->status, 403);
  EXPECT_EQ(client.Get("/")->status, 403);
  EXPECT_EQ(client.Get(("/?token=" + token).c_str())->status, 200);
  EXPECT_EQ(client.Get("/three.min.js")->status, 200);  // code, no data
  server->Stop();

  // A given token is required on loopback too.
  server = Start("127.0.0.1:0", "s3cret-token");
  ASSERT_TRUE(server);
  httplib::Client local("127.0.0.1", server->port());
  EXPECT_EQ(local.Get("/api/state")->status, 403);
  EXPECT_EQ(local.Get("/api/state?token=s3cret-token")->status, 200);
}

}  // namespace
}  // namespace ccmd
