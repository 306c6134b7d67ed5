#include "libccmd/view/view_server.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdio>

#include "libccmd/net/socket.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/string_util.h"
#include "libccmd/util/timer.h"

// Last: httplib.h brings <resolv.h>, whose _res macro breaks Eigen headers included after it.
#include <httplib.h>

namespace ccmd {

namespace {

std::array<unsigned char, 32> Sha256(const std::string& text) {
  std::array<unsigned char, 32> digest{};
  unsigned int size = 0;
  EVP_Digest(text.data(), text.size(), digest.data(), &size, EVP_sha256(), nullptr);
  return digest;
}

StatusOr<std::string> RandomToken() {
  unsigned char bytes[16];
  if (RAND_bytes(bytes, sizeof(bytes)) != 1)
    return Internal("no random bytes for the view's access token");
  std::string hex;
  for (unsigned char b : bytes) {
    char two[3];
    std::snprintf(two, sizeof(two), "%02x", b);
    hex += two;
  }
  return hex;
}

bool IsLoopbackAddress(const sockaddr* address) {
  if (address->sa_family == AF_INET) {
    const auto* in = reinterpret_cast<const sockaddr_in*>(address);
    return (ntohl(in->sin_addr.s_addr) >> 24) == 127;
  }
  if (address->sa_family == AF_INET6) {
    const auto* in6 = reinterpret_cast<const sockaddr_in6*>(address);
    return IN6_IS_ADDR_LOOPBACK(&in6->sin6_addr);
  }
  return false;
}

// True when every address the host resolves to is a loopback one.
StatusOr<bool> ResolvesToLoopback(const std::string& host) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* found = nullptr;
  const int rc = getaddrinfo(host.c_str(), nullptr, &hints, &found);
  if (rc != 0)
    return InvalidArgument("map view: cannot resolve '" + host + "': " + gai_strerror(rc));
  bool loopback = true;
  for (const addrinfo* p = found; p; p = p->ai_next)
    loopback = loopback && IsLoopbackAddress(p->ai_addr);
  freeaddrinfo(found);
  return loopback;
}

// The host part of a Host header ("127.0.0.1:8080", "[::1]:8080", "localhost").
std::string HostOfHeader(const std::string& header) {
  if (!header.empty() && header[0] == '[') return header.substr(0, header.find(']') + 1);
  return header.substr(0, header.find(':'));
}

bool IsLoopbackName(const std::string& host) {
  return host == "localhost" || host == "[::1]" || StartsWith(host, "127.");
}

std::string SseMessage(std::uint64_t seq, const std::string& json) {
  std::string m;
  if (seq > 0) m = "id: " + std::to_string(seq) + "\n";
  return m + "data: " + json + "\n\n";
}

void NoStore(httplib::Response* response) { response->set_header("Cache-Control", "no-store"); }

}  // namespace

Status ViewServerOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(ParseHostPort(listen).status());
  if (web_dir.empty()) return InvalidArgument("map view: no folder for its web page");
  if (max_event_streams < 1 || max_event_streams > 1024)
    return InvalidArgument("map view: streams must be 1..1024");
  if (extra_workers < 2 || extra_workers > 1024)
    return InvalidArgument("map view: extra workers must be 2..1024");
  if (!(stats_period_s > 0)) return InvalidArgument("map view: statistics period must be > 0");
  if (!(keepalive_s > 0)) return InvalidArgument("map view: keep-alive period must be > 0");
  if (max_clouds_per_request < 1)
    return InvalidArgument("map view: at least one cloud per request");
  for (char c : token) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_' && c != '.') {
      return InvalidArgument("map view: the token may hold letters, digits, '-', '_' and '.' only");
    }
  }
  return cloud.Validate();
}

void ViewServerOptions::Describe(OptionsWriter* out) const {
  out->Add("listen", listen);
  out->Add("token", token.empty() ? "none" : "set");
  out->Add("web_dir", web_dir);
  out->Add("max_event_streams", max_event_streams);
  out->Add("extra_workers", extra_workers);
  out->Add("stats_period_s", stats_period_s);
  out->Add("keepalive_s", keepalive_s);
  out->Add("max_clouds_per_request", max_clouds_per_request);
  out->Add("max_inline_clouds", max_inline_clouds);
  out->Nested("cloud", cloud);
}

Json ViewStats::ToJson() const {
  Json j;
  j["maps"] = maps.size();
  j["keyframes"] = keyframes;
  j["points"] = points;
  Json list = Json::MakeArray();
  for (const ViewAgentStats& a : agents) {
    Json x;
    x["id"] = static_cast<int>(a.id.value());
    x["name"] = a.name;
    x["keyframes"] = a.keyframes;
    x["bytes"] = a.bytes;
    x["rate_kBps"] = a.rate_kBps;
    x["connected"] = a.connected;
    x["map"] = a.map ? Json(a.map->value()) : Json();
    x["bucket_s"] = a.bucket_s;
    Json traffic = Json::MakeArray();
    for (double v : a.traffic_kBps) traffic.Push(v);
    x["traffic_kBps"] = std::move(traffic);
    list.Push(std::move(x));
  }
  j["agents"] = std::move(list);
  Json map_list = Json::MakeArray();
  for (const ViewMapStats& m : maps) {
    Json x;
    x["id"] = m.id.value();
    x["keyframes"] = m.keyframes;
    x["primary"] = m.primary;
    Json agent_ids = Json::MakeArray();
    for (AgentId a : m.agents) agent_ids.Push(static_cast<int>(a.value()));
    x["agents"] = std::move(agent_ids);
    map_list.Push(std::move(x));
  }
  j["map_list"] = std::move(map_list);
  return j;
}

ViewServer::ViewServer(const ViewServerOptions& options, ViewModel* model, const DenseMap* dense,
                       ViewStatsSource stats)
    : options_(options), model_(model), dense_(dense), stats_(std::move(stats)) {}

StatusOr<std::unique_ptr<ViewServer>> ViewServer::Start(const ViewServerOptions& options,
                                                        ViewModel* model, const DenseMap* dense,
                                                        ViewStatsSource stats) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (model == nullptr || !stats)
    return InvalidArgument("map view: needs a model and a statistics source");
  std::unique_ptr<ViewServer> server(new ViewServer(options, model, dense, std::move(stats)));
  const std::vector<std::array<std::string, 3>> files = {
      {"/", "index.html", "text/html; charset=utf-8"},
      {"/view.js", "view.js", "text/javascript; charset=utf-8"},
      {"/view.css", "view.css", "text/css; charset=utf-8"},
      {"/three.min.js", "three.min.js", "text/javascript; charset=utf-8"},
      {"/OrbitControls.js", "OrbitControls.js", "text/javascript; charset=utf-8"}};
  for (const auto& [path, name, type] : files) {
    auto body = ReadFileToString(JoinPath(options.web_dir, name), 16u << 20);
    if (!body.ok()) {
      return NotFound("map view: " + JoinPath(options.web_dir, name) +
                      " is missing (three.js comes from Debian's libjs-three: run scripts/setup.sh "
                      "and rebuild)");
    }
    server->files_.push_back({path, type, std::move(body).value()});
  }
  CCMD_RETURN_IF_ERROR(server->Bind());
  server->Routes();
  server->listen_thread_ = std::thread([s = server.get()] {
    s->http_->listen_after_bind();
    s->listen_returned_ = true;
  });
  // httplib's stop() only works once the listener runs: Stop() must not come earlier. The
  // listener marks itself running as its first step, so this wait is short.
  while (!server->http_->is_running() && !server->listen_returned_) std::this_thread::yield();
  server->stats_thread_ = std::thread([s = server.get()] { s->StatsLoop(); });
  return server;
}

Status ViewServer::Bind() {
  CCMD_ASSIGN_OR_RETURN(const HostPort address, ParseHostPort(options_.listen));
  host_ = address.host;
  CCMD_ASSIGN_OR_RETURN(loopback_, ResolvesToLoopback(host_));
  token_ = options_.token;
  if (token_.empty() && !loopback_) {
    CCMD_ASSIGN_OR_RETURN(token_, RandomToken());
  }
  token_digest_ = Sha256(token_);

  http_ = std::make_unique<httplib::Server>();
  const int workers = options_.max_event_streams + options_.extra_workers;
  http_->new_task_queue = [workers] {
    return new httplib::ThreadPool(static_cast<std::size_t>(workers));
  };
  http_->set_keep_alive_timeout(2);
  http_->set_tcp_nodelay(true);  // events are small writes: no waiting for earlier ones' ACKs  //
                                 // Stop waits for idle connections this long at most
  http_->set_payload_max_length(1 << 16);  // nothing is uploaded
  int port = address.port;
  if (port == 0) {
    port = http_->bind_to_any_port(host_);
  } else if (!http_->bind_to_port(host_, port)) {
    port = -1;
  }
  if (port <= 0)
    return Unavailable("map view: cannot listen on " + options_.listen + " (address in use?)");
  port_ = static_cast<std::uint16_t>(port);
  return Status::Ok();
}

std::string ViewServer::url() const {
  std::string host = host_;
  if (host == "0.0.0.0" || host == "::") {
    char name[256] = {0};
    host = gethostname(name, sizeof(name) - 1) == 0 && name[0] ? name : "localhost";
  }
  if (host.find(':') != std::string::npos) host = "[" + host + "]";
  std::string u = "http://" + host + ":" + std::to_string(port_) + "/";
  if (!token_.empty()) u += "?token=" + token_;
  return u;
}

bool ViewServer::Refuse(const httplib::Request& request, httplib::Response* response) const {
  if (request.method != "GET" && request.method != "HEAD") {
    response->status = 405;
    response->set_header("Allow", "GET, HEAD");
    response->set_content("the map view is read-only\n", "text/plain");
    return true;
  }
  const bool script = request.path == "/view.js" || request.path == "/view.css" ||
                      request.path == "/three.min.js" || request.path == "/OrbitControls.js";
  if (token_.empty()) {
    if (!IsLoopbackName(HostOfHeader(request.get_header_value("Host")))) {
      response->status = 403;
      response->set_content(
          "the map view answers loopback names only (start it with a token for others)\n",
          "text/plain");
      return true;
    }
    return false;
  }
  if (script) return false;  // the page's code holds no data
  std::string given = request.get_param_value("token");
  const std::string authorization = request.get_header_value("Authorization");
  if (given.empty() && StartsWith(authorization, "Bearer ")) given = authorization.substr(7);
  const std::array<unsigned char, 32> digest = Sha256(given);
  if (given.empty() || CRYPTO_memcmp(digest.data(), token_digest_.data(), digest.size()) != 0) {
    response->status = 403;
    response->set_content(given.empty() ? "access token missing: open the URL the server printed\n"
                                        : "wrong access token: open the URL the server printed\n",
                          "text/plain");
    return true;
  }
  return false;
}

void ViewServer::Routes() {
  http_->set_pre_routing_handler(
      [this](const httplib::Request& request, httplib::Response& response) {
        return Refuse(request, &response) ? httplib::Server::HandlerResponse::Handled
                                          : httplib::Server::HandlerResponse::Unhandled;
      });
  for (const StaticFile& file : files_) {
    http_->Get(file.path, [&file](const httplib::Request&, httplib::Response& response) {
      response.set_content(file.body, file.content_type);
    });
  }
  http_->Get("/index.html", [this](const httplib::Request&, httplib::Response& response) {
    response.set_content(files_.front().body, files_.front().content_type);
  });
  http_->Get("/api/summary", [this](const httplib::Request&, httplib::Response& response) {
    NoStore(&response);
    response.set_content(stats_().ToJson().Dump(-1), "application/json");
  });
  http_->Get("/api/state", [this](const httplib::Request&, httplib::Response& response) {
    NoStore(&response);
    response.set_content(model_->StateJson().Dump(-1), "application/json");
  });
  http_->Get("/api/events", [this](const httplib::Request& request, httplib::Response& response) {
    ServeEvents(request, &response);
  });
  http_->Get("/api/clouds", [this](const httplib::Request& request, httplib::Response& response) {
    ServeClouds(request, &response);
  });
}

void ViewServer::ServeEvents(const httplib::Request& request, httplib::Response* response) {
  std::string after_text = request.get_header_value("Last-Event-ID");
  if (after_text.empty()) after_text = request.get_param_value("after");
  const auto after = ParseInt(after_text.empty() ? "0" : after_text);
  if (!after.ok() || *after < 0) {
    response->status = 400;
    response->set_content("after: expected an event number\n", "text/plain");
    return;
  }
  if (streams_.fetch_add(1) >= options_.max_event_streams) {
    streams_.fetch_sub(1);
    response->status = 503;
    response->set_content("too many browsers follow this server's map\n", "text/plain");
    return;
  }
  NoStore(response);
  struct Cursor {
    std::uint64_t after = 0, stats_version = 0;
  };
  auto cursor = std::make_shared<Cursor>();
  cursor->after = static_cast<std::uint64_t>(*after);
  response->set_chunked_content_provider(
      "text/event-stream",
      [this, cursor](std::size_t, httplib::DataSink& sink) {
        const EventBatch batch =
            model_->WaitEvents(cursor->after, cursor->stats_version, options_.keepalive_s);
        std::string text;
        switch (batch.kind) {
          case EventBatch::Kind::kClosed:
            sink.done();
            return true;
          case EventBatch::Kind::kReset:
            // The browser reloads the state; its EventSource reconnects with the new number.
            text = SseMessage(0, R"({"type":"reset"})");
            sink.write(text.data(), text.size());
            sink.done();
            return true;
          case EventBatch::Kind::kTimeout:
            text = ": keep-alive\n\n";
            break;
          case EventBatch::Kind::kEvents: {
            int inline_budget = options_.max_inline_clouds;
            for (const auto& [seq, json] : batch.events) {
              text += StreamEvent(seq, json, &inline_budget);
              cursor->after = seq;
            }
            if (!batch.stats.empty())
              text += SseMessage(0, R"({"type":"stats","stats":)" + batch.stats + "}");
            cursor->stats_version = batch.stats_version;
            break;
          }
        }
        return sink.write(text.data(), text.size());
      },
      [this](bool) {
        std::lock_guard<std::mutex> lock(stop_mutex_);
        streams_.fetch_sub(1);
        stop_cv_.notify_all();
      });
}

std::string ViewServer::StreamEvent(std::uint64_t seq, const std::string& json,
                                    int* inline_budget) const {
  if (*inline_budget <= 0 || dense_ == nullptr ||
      json.find(R"("type":"cloud")") == std::string::npos) {
    return SseMessage(seq, json);
  }
  auto event = Json::Parse(json);
  if (!event.ok() || !event->Get("a") || !event->Get("k")) return SseMessage(seq, json);
  const GlobalKeyframeId id{AgentId(static_cast<std::uint16_t>(event->Get("a")->number())),
                            KeyframeId(static_cast<std::uint32_t>(event->Get("k")->number()))};
  auto cloud = dense_->KeyframeCloud(id);
  if (!cloud.ok()) return SseMessage(seq, json);
  std::string record;
  AppendViewCloud(id, &*cloud, options_.cloud, &record);
  (*event)["data"] = EncodeBase64(record);
  --*inline_budget;
  return SseMessage(seq, event->Dump(-1));
}

void ViewServer::ServeClouds(const httplib::Request& request, httplib::Response* response) const {
  const std::vector<std::string> ids = Split(request.get_param_value("ids"), ',');
  if (ids.empty() || ids.size() > options_.max_clouds_per_request) {
    response->status = 400;
    response->set_content("ids: expected 1 to " + std::to_string(options_.max_clouds_per_request) +
                              " AGENT:KEYFRAME pairs\n",
                          "text/plain");
    return;
  }
  const Stopwatch watch;
  std::string body;
  for (const std::string& text : ids) {
    const std::vector<std::string> parts = Split(text, ':');
    const auto agent =
        parts.size() == 2 ? ParseInt(parts[0]) : StatusOr<long long>(InvalidArgument(""));
    const auto keyframe =
        parts.size() == 2 ? ParseInt(parts[1]) : StatusOr<long long>(InvalidArgument(""));
    if (!agent.ok() || !keyframe.ok() || *agent < 0 || *agent > 65535 || *keyframe < 0 ||
        *keyframe > 0xffffffffll) {
      response->status = 400;
      response->set_content("ids: '" + text + "' is not AGENT:KEYFRAME\n", "text/plain");
      return;
    }
    const GlobalKeyframeId id{AgentId(static_cast<std::uint16_t>(*agent)),
                              KeyframeId(static_cast<std::uint32_t>(*keyframe))};
    StatusOr<CameraCloud> cloud =
        dense_ ? dense_->KeyframeCloud(id) : StatusOr<CameraCloud>(NotFound(""));
    AppendViewCloud(id, cloud.ok() ? &*cloud : nullptr, options_.cloud, &body);
  }
  NoStore(response);
  // The time the server took (Server-Timing, visible in the browser's developer tools).
  response->set_header("Server-Timing", "clouds;dur=" + std::to_string(watch.ElapsedMillis()));
  response->set_content(std::move(body), "application/octet-stream");
}

void ViewServer::StatsLoop() {
  std::unique_lock<std::mutex> lock(stop_mutex_);
  while (!stopping_) {
    lock.unlock();
    model_->PublishStats(stats_().ToJson());
    lock.lock();
    stop_cv_.wait_for(lock, std::chrono::duration<double>(options_.stats_period_s),
                      [&] { return stopping_; });
  }
}

void ViewServer::Stop() {
  {
    std::lock_guard<std::mutex> lock(stop_mutex_);
    if (stopping_) return;
    stopping_ = true;
  }
  stop_cv_.notify_all();
  model_->Close();  // ends the event streams
  {
    // Let them finish their last write, so browsers see the stream end rather than a broken
    // connection; a browser that does not read is not waited for long.
    std::unique_lock<std::mutex> lock(stop_mutex_);
    stop_cv_.wait_for(lock, std::chrono::seconds(2), [&] { return streams_.load() == 0; });
  }
  if (http_) http_->stop();
  if (listen_thread_.joinable()) listen_thread_.join();
  if (stats_thread_.joinable()) stats_thread_.join();
}

ViewServer::~ViewServer() { Stop(); }

}  // namespace ccmd
