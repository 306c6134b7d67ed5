#pragma once

// The live map view's HTTP server (cpp-httplib): a read-only web page with three.js, the
// state of the maps, the keyframes' clouds and a stream of changes (Server-Sent Events).
// docs/view.md describes the page and every endpoint:
//   GET /                 the page (and /view.js, /view.css, /three.min.js, /OrbitControls.js)
//   GET /api/summary      maps, keyframes, dense points, per-agent statistics (JSON)
//   GET /api/state        every agent, keyframe (map, pose, cloud ready), loop; "seq" (JSON)
//   GET /api/events       the changes after ?after=SEQ (or Last-Event-ID), as SSE
//   GET /api/clouds?ids=A:K,A:K,...   clouds at viewing density (view_cloud.h), up to 64
//
// Security: nothing changes anything (GET and HEAD only; others get 405). With a token every
// request but the static scripts must carry it (?token=T or "Authorization: Bearer T"); it
// is compared in constant time. A host that is not loopback needs a token: one is made up
// (128 random bits) when none is given, and url() carries it. Without a token the server
// answers only requests whose Host is a loopback name, so that a web page elsewhere cannot
// read the map through a DNS name that resolves to 127.0.0.1.
//
// Threads: the listener and its worker pool (cpp-httplib's), and one statistics thread; all
// owned, joined by Stop(). An event stream holds a worker while it is open, so the pool has
// max_event_streams more workers than that.

#include <array>
#include <atomic>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/dense/dense_map.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"
#include "libccmd/view/view_cloud.h"
#include "libccmd/view/view_model.h"

namespace httplib {
class Server;
struct Request;
struct Response;
}  // namespace httplib

namespace ccmd {

struct ViewServerOptions {
  std::string listen = "127.0.0.1:0";  // HOST:PORT (port 0: any free port)
  std::string token;                   // "" : none on loopback, made up otherwise
  std::string web_dir;          // index.html, view.js, view.css, three.min.js, OrbitControls.js
  int max_event_streams = 8;    // browsers following at once
  int extra_workers = 8;        // for everything else
  double stats_period_s = 1.0;  // statistics pushed to the streams this often
  double keepalive_s = 5;       // an idle stream gets a comment this often (a closed
                                // browser's stream is noticed then, and freed)
  std::size_t max_clouds_per_request = 64;
  int max_inline_clouds = 16;  // per write of an event stream; later ones are fetched
  ViewCloudOptions cloud;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// What the page's panel shows; the program that runs the view fills it from its back-end and
// transport (ServerRuntime::ViewStats).
struct ViewAgentStats {
  AgentId id;
  std::string name;
  std::size_t keyframes = 0;  // held by the server
  std::uint64_t bytes = 0;    // keyframe and pose-update messages received
  double rate_kBps = 0;       // average over the agent's connected time
  bool connected = false;
  std::optional<MapId> map;
  double bucket_s = 1;  // traffic_kBps: one value per bucket, oldest first
  std::vector<double> traffic_kBps;
};

struct ViewMapStats {
  MapId id;
  std::size_t keyframes = 0;
  bool primary = false;  // the map whose frame is the world (where the dense map is)
  std::vector<AgentId> agents;
};

struct ViewStats {
  std::vector<ViewMapStats> maps;
  std::size_t keyframes = 0;  // held by the server, every map
  std::size_t points = 0;     // in the dense map (kept by its filter)
  std::vector<ViewAgentStats> agents;

  // The /api/summary object: maps (count), keyframes, points, agents [{id, name, keyframes,
  // bytes, rate_kBps, connected, map, bucket_s, traffic_kBps}], map_list [{id, keyframes,
  // primary, agents}].
  Json ToJson() const;
};

using ViewStatsSource = std::function<ViewStats()>;

class ViewServer {
 public:
  // Binds and starts serving. `model` and `dense` (null: no clouds) must outlive the server.
  static StatusOr<std::unique_ptr<ViewServer>> Start(const ViewServerOptions& options,
                                                     ViewModel* model, const DenseMap* dense,
                                                     ViewStatsSource stats);
  ~ViewServer();
  ViewServer(const ViewServer&) = delete;
  ViewServer& operator=(const ViewServer&) = delete;

  // Ends the streams and stops serving; idempotent.
  void Stop();

  std::uint16_t port() const { return port_; }
  const std::string& token() const { return token_; }
  // http://HOST:PORT/ with ?token=... when there is one; a wildcard bind (0.0.0.0, ::) is
  // written with the machine's host name.
  std::string url() const;

 private:
  struct StaticFile {
    std::string path, content_type, body;
  };
  ViewServer(const ViewServerOptions& options, ViewModel* model, const DenseMap* dense,
             ViewStatsSource stats);
  Status Bind();
  void Routes();
  void StatsLoop();
  // Answers a request the server must refuse (wrong method, token or host): true if refused.
  bool Refuse(const httplib::Request& request, httplib::Response* response) const;
  void ServeEvents(const httplib::Request& request, httplib::Response* response);
  // An event as the stream sends it: a "cloud" event carries the cloud's record (base64, in
  // "data") while `inline_budget` lasts, so the browser draws it without another request.
  std::string StreamEvent(std::uint64_t seq, const std::string& json, int* inline_budget) const;
  void ServeClouds(const httplib::Request& request, httplib::Response* response) const;

  const ViewServerOptions options_;
  ViewModel* const model_;
  const DenseMap* const dense_;
  const ViewStatsSource stats_;
  std::string host_, token_;
  std::array<unsigned char, 32> token_digest_{};
  bool loopback_ = true;
  std::uint16_t port_ = 0;
  std::vector<StaticFile> files_;
  std::unique_ptr<httplib::Server> http_;
  std::atomic<int> streams_{0};
  std::atomic<bool> listen_returned_{false};

  std::mutex stop_mutex_;
  std::condition_variable stop_cv_;
  bool stopping_ = false;  // guarded by stop_mutex_
  std::thread listen_thread_, stats_thread_;
};

}  // namespace ccmd
