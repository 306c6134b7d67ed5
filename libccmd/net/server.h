#pragma once

// The transport's server side: accepts agents over TCP, authenticates them, journals what
// they send, acknowledges it, and hands it to a MessageConsumer (message_consumer.h).
//
//   ServerOptions options;
//   options.listen = "0.0.0.0:7420";
//   options.journal_dir = "run/journal";
//   options.psk = key;                    // required unless listening on loopback
//   CountingConsumer consumer;            // implements MessageConsumer
//   Server server(options, &consumer);
//   CCMD_RETURN_IF_ERROR(server.Start()); // binds, replays journals (resume), starts threads
//   ...
//   server.Stop();                        // Bye to agents, everything stored is delivered
//
// Threads (each owned and joined by Stop): the I/O thread multiplexes the listener and all
// connections with poll() and does the handshakes; the journal stage appends and syncs;
// the delivery stage calls the consumer (journal_stage.h). Untrusted input never stops the
// server: a malformed, oversized, truncated, unknown or unexpected frame, a frame failing
// its tag, a wrong key or identity, a silent or dribbling peer closes that one connection,
// with a Bye saying why and a log line (refusals before a session: summarised per source).

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>

#include "libccmd/net/message_consumer.h"
#include "libccmd/net/traffic_stats.h"
#include "libccmd/util/json.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ServerOptions {
  std::string listen = "127.0.0.1:7420";  // HOST:PORT; port 0 = any free port
  std::string journal_dir;                // required: one journal per agent
  bool resume = false;                    // replay journal_dir's journals before serving
  std::string psk;  // pre-shared key; empty = no authentication, allowed on loopback only
  // Agents active at once (connected, or disconnected less than slot_timeout_s ago); a new
  // name is refused ("server full") while all are; registered agents are always served.
  int max_agents = 16;
  double slot_timeout_s = 300.0;
  int max_handshakes = 32;  // connections not yet through the handshake
  std::uint32_t max_payload_bytes = kDefaultMaxPayloadBytes;  // per frame
  double handshake_timeout_s = 5.0;                           // accept to welcome
  double idle_timeout_s = 30.0;          // a session without a complete frame this long is closed
  double frame_timeout_s = 20.0;         // a frame must be complete this long after its header
  double heartbeat_interval_s = 5.0;     // the server sends a heartbeat after this much silence
  double refusal_log_interval_s = 10.0;  // refused connections: one summary per source
  std::size_t per_agent_memory_bytes = 64u << 20;  // received, not yet journaled
  std::size_t max_output_bytes = 8u << 20;         // unsent bytes to an agent not reading
  bool fsync =
      true;  // fdatasync journals before acknowledging (off: survives process crashes only)
  std::size_t journal_queue = 256;
  std::size_t delivery_queue = 256;
  TrafficOptions traffic;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;  // the key is shown as set or not, never its bytes
};

class ServerIo;

class Server {
 public:
  Server(ServerOptions options, MessageConsumer* consumer);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // Binds the listener, replays the journals when resuming (the consumer sees all of it
  // before Start returns), then serves. Fails on bad options, a busy port, a non-loopback
  // address without a key, journals left in journal_dir without resume, corrupt journals.
  Status Start();
  // Stops accepting, says Bye to every agent, stores and delivers what was received,
  // joins every thread. Idempotent.
  void Stop();

  std::uint16_t port() const { return port_; }
  const TrafficStats& stats() const { return *stats_; }
  Json StatsJson() const;

 private:
  ServerOptions options_;
  MessageConsumer* consumer_;
  std::unique_ptr<TrafficStats> stats_;
  std::unique_ptr<ServerIo> io_;
  int journal_lock_ = -1;  // flock on journal_dir/LOCK: one server per journal folder
  std::uint16_t port_ = 0;
  bool started_ = false;
};

}  // namespace ccmd
