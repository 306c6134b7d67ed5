#pragma once

// The server's stages behind the I/O thread (internal to libccmd/net; see server.h):
//
//   I/O thread --StageItem--> JournalStage (one thread) --DeliveryItem--> DeliveryStage
//        ^                         |                                    (one thread, calls
//        +------ StageFeedback ----+  (attach results, acks, freed bytes)  MessageConsumer)
//
// JournalStage owns the agent registry and the journals: it registers agents (name -> id,
// stable across reconnects and restarts because the journals record it), checks each
// connection's identity against the registration, appends data records, syncs once per
// batch (group commit) and only then reports the stored sequence numbers, which the I/O
// thread turns into acks. Queues are bounded; a slow consumer blocks the journal stage,
// whose full queue stops the I/O thread from reading sockets.
//
// Slots: a new name is registered only while fewer than max_agents agents are active
// (connected, or disconnected less than slot_timeout_s ago). A registration is provisional
// until its first data message: only then are its journal created and the consumer told;
// a provisional agent that leaves without sending anything is forgotten at once.

#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/journal.h"
#include "libccmd/net/message_consumer.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "libccmd/net/traffic_stats.h"
#include "libccmd/util/bounded_queue.h"

namespace ccmd {

struct DeliveryItem {
  enum class Kind { kAgentKnown, kConnected, kDisconnected, kMessage, kReplayFinished };
  Kind kind = Kind::kMessage;
  AgentDescription agent;  // kAgentKnown
  bool from_journal = false;
  AgentId id;                // kConnected, kDisconnected
  std::uint64_t value = 0;   // kConnected: last stored; kReplayFinished: messages
  std::string reason;        // kDisconnected
  DeliveredMessage message;  // kMessage
};

class DeliveryStage {
 public:
  DeliveryStage(MessageConsumer* consumer, std::size_t capacity, TrafficStats* stats);
  ~DeliveryStage() { Stop(); }
  void Start();
  void Push(DeliveryItem item);  // blocks while the queue is full
  // Waits until the consumer has returned from OnReplayFinished.
  void WaitReplayFinished();
  // Delivers what is queued, then joins the thread.
  void Stop();

 private:
  void Run();

  MessageConsumer* consumer_;
  TrafficStats* stats_;
  BoundedQueue<DeliveryItem> queue_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable replay_done_cv_;
  bool replay_done_ = false;
};

struct StageItem {
  enum class Kind { kAttach, kData, kDetach };
  Kind kind = Kind::kData;
  std::uint64_t conn = 0;       // the I/O thread's connection token
  HelloMessage hello;           // kAttach
  IdentityVerifier verifier{};  // kAttach: of the identity the connection presented
  AgentId agent;                // kData, kDetach
  std::uint64_t seq = 0;        // kData
  std::uint8_t type = 0;
  std::vector<std::uint8_t> message;
  double received_time = 0;  // MonotonicSeconds() at the I/O thread (every kind)
  std::string reason;        // kDetach
};

struct AttachResult {
  std::uint64_t conn = 0;
  Status status;  // not ok: refuse the agent with `reason`
  ByeReason reason = ByeReason::kNormal;
  AgentId agent;
  std::uint64_t last_stored = 0;
};

struct StageFeedback {
  std::vector<AttachResult> attached;
  std::map<AgentId, std::uint64_t> stored;         // durable sequence numbers reached
  std::map<AgentId, std::uint64_t> freed_bytes;    // message bytes the stage is done with
  std::vector<std::pair<AgentId, Status>> failed;  // journal write failures
  std::vector<AgentId> forgotten;  // provisional registrations dropped (left without data)
  bool empty() const {
    return attached.empty() && stored.empty() && freed_bytes.empty() && failed.empty() &&
           forgotten.empty();
  }
};

struct JournalStageOptions {
  std::string dir;
  bool fsync = true;
  int max_agents = 16;          // active at once (see above)
  double slot_timeout_s = 300;  // a disconnected agent keeps its slot this long
  std::size_t queue_capacity = 256;
  std::size_t max_batch = 64;
  std::uint32_t max_payload_bytes = kDefaultMaxPayloadBytes;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class JournalStage {
 public:
  JournalStage(JournalStageOptions options, DeliveryStage* delivery, WakeFd* wake,
               TrafficStats* stats);
  ~JournalStage() { Stop(); }

  // For a fresh start: the folder must hold no journals (kInvalidArgument otherwise, so an
  // earlier run's data is never mixed in by accident).
  Status CheckNoJournals();
  // For --resume: replays every journal in the folder into the delivery stage (which must
  // be running), cutting torn tails, and rebuilds the registry. Returns the message count.
  StatusOr<std::uint64_t> Resume();

  void Start();
  // Single producer (the I/O thread): moves the item in if there is room, else leaves it
  // untouched and returns false.
  bool TryPush(StageItem& item);
  void Push(StageItem&& item) { queue_.Push(std::move(item)); }
  // Moves the feedback gathered since the last call into *out (I/O thread).
  void TakeFeedback(StageFeedback* out);
  // Processes what is queued, syncs, joins.
  void Stop();

 private:
  struct Agent {
    JournalAgentInfo info;
    std::unique_ptr<JournalWriter> writer;  // null while provisional
    std::uint64_t written_seq = 0;          // appended
    std::uint64_t durable_seq = 0;          // appended and synced
    bool announced = false;                 // OnAgentKnown sent in this run
    int connections = 0;                    // attached connections (a replacement overlaps)
    double last_detach = 0;                 // when the last one ended (slot time-out)
  };
  struct Batch {
    std::vector<DeliveryItem> deliveries;
    std::vector<AttachResult> attached;
    std::map<AgentId, bool> touched;
    std::map<AgentId, std::uint64_t> freed;
    std::vector<AgentId> forgotten;
  };

  void Run();
  void ProcessBatch(std::vector<StageItem>* items);
  void Attach(const StageItem& item, Batch* batch);
  // The registered agent `hello` names, after its identity and camera are checked; null
  // with *refusal set when refused.
  Agent* CheckRegistered(const StageItem& item, AttachResult* refusal);
  Agent* RegisterProvisionally(const StageItem& item, AttachResult* refusal);
  Status CheckResumePoint(const HelloMessage& hello, bool registered, Agent* agent);
  void Detach(const StageItem& item, Batch* batch);
  void Data(StageItem* item, Batch* batch);
  // Creates a provisional agent's journal at its first data message and announces it.
  Status Persist(Agent* agent, Batch* batch);
  int ActiveAgents(double now) const;
  void Fail(AgentId id, const Status& status, Batch* batch, StageFeedback* feedback);
  Status Announce(Agent* agent, bool from_journal, std::vector<DeliveryItem>* out);

  JournalStageOptions options_;
  DeliveryStage* delivery_;
  WakeFd* wake_;
  TrafficStats* stats_;
  BoundedQueue<StageItem> queue_;
  std::thread thread_;

  // Journal thread only (and Resume before Start).
  std::map<AgentId, Agent> agents_;
  std::map<std::string, AgentId> by_name_;
  std::uint32_t next_id_ = 1;  // ids are never reused within a run

  std::mutex feedback_mutex_;
  StageFeedback feedback_;
};

}  // namespace ccmd
