#pragma once

// The whole server in one object: the transport (libccmd/net) delivers every agent's messages
// to the back-end (libccmd/backend); results (dense map, trajectories, statistics) are written
// to an output folder, periodically and at the end. ccmd_server is a thin shell around it.

#include <atomic>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "libccmd/backend/backend.h"
#include "libccmd/dense/snapshot.h"
#include "libccmd/net/message_consumer.h"
#include "libccmd/net/server.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"
#include "libccmd/view/view_server.h"

namespace ccmd {

struct ServerRuntimeOptions {
  ServerOptions net;
  BackendOptions backend;
  std::string output_dir;           // results; created if missing
  double stats_period_s = 5.0;      // server_stats.json rewritten this often
  double snapshot_period_s = 30.0;  // dense map snapshot (<= 0: only at the end)
  double memory_period_s = 30.0;    // memory by part in server_stats.json (it reads every map)
  std::optional<ViewServerOptions> view;  // set: serve the live map view (docs/view.md)

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class ServerRuntime : public MessageConsumer {
 public:
  static StatusOr<std::unique_ptr<ServerRuntime>> Create(const ServerRuntimeOptions& options);
  ~ServerRuntime() override;

  // Starts the back-end, then the transport (which replays journals first when resuming).
  Status Start();
  std::uint16_t port() const { return server_ ? server_->port() : 0; }
  // Periodic work for the caller's loop: statistics file and dense snapshots when due.
  void Tick();
  // Stops the transport (everything received is delivered), lets the back-end finish, writes
  // the results and stops the back-end. Idempotent.
  Status Stop();

  Backend* backend() { return backend_.get(); }
  // The live map view, when the options ask for one (after Start).
  const ViewServer* view() const { return view_.get(); }
  // What the view's panel shows, from the back-end and the transport (any thread).
  ViewStats CollectViewStats();
  Json StatsJson();
  Json TransportStatsJson() const { return server_ ? server_->StatsJson() : Json(); }
  // Results written by Stop (and WriteResults): map.ply, trajectory_fused.txt,
  // trajectory_<agent name>.txt, keyframe_arrivals.csv, server_stats.json.
  Status WriteResults();
  // keyframe_arrivals.csv: when each keyframe reached the back-end and the dense map.
  Status WriteKeyframeArrivals(const std::map<AgentId, std::string>& names);

  // MessageConsumer
  void OnAgentKnown(const AgentDescription& agent, bool from_journal) override;
  void OnAgentDisconnected(AgentId agent, const std::string& reason) override;
  void OnMessage(DeliveredMessage message) override;
  void OnReplayFinished(std::uint64_t messages) override;

 private:
  explicit ServerRuntime(const ServerRuntimeOptions& options) : options_(options) {}
  Status StartView();

  ServerRuntimeOptions options_;
  std::unique_ptr<ViewModel> view_model_;  // the back-end's observer: outlives it
  std::unique_ptr<Backend> backend_;
  std::unique_ptr<ViewServer> view_;
  std::unique_ptr<Server> server_;
  std::unique_ptr<DenseSnapshotWriter> snapshots_;
  std::mutex names_mutex_;
  std::map<AgentId, std::string> names_;
  // Counted on the delivery thread, read by StatsJson on the caller's thread.
  std::atomic<std::uint64_t> malformed_messages_{0};
  double last_stats_ = -1e9;
  double last_memory_ = -1e9;
  Json memory_;  // the last memory by part
  bool stopped_ = false;
};

}  // namespace ccmd
