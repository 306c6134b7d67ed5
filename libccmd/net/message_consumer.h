#pragma once

// Where the server hands what the agents sent: the back-end implements MessageConsumer.
//
// Calls come from one thread (the server's delivery stage), in this order per agent:
// OnAgentKnown once per server run, then for each session OnAgentConnected, its messages,
// OnAgentDisconnected. Every data message is delivered exactly once per server run, in
// sequence order, and only after it is durably journaled (so the agent's copy may already
// be gone). With Server resume, the journal replay comes first: OnAgentKnown(from_journal)
// and the stored messages (replayed = true) of every agent, then OnReplayFinished, before
// any new connection is served; new messages continue the sequence without gaps or
// repeats. The calls may block (a slow consumer slows the agents down through bounded
// queues and TCP flow control; nothing is dropped).

#include <cstdint>
#include <string>
#include <vector>

#include "libccmd/net/session_messages.h"
#include "libccmd/util/ids.h"

namespace ccmd {

struct AgentDescription {
  AgentId id;
  std::string name;
  SessionCamera camera;
};

struct DeliveredMessage {
  AgentId agent;
  std::uint64_t seq = 0;              // per agent, 1-based, consecutive (see PROTOCOL.md on gaps)
  std::uint8_t type = 0;              // MessageType: 16 keyframe, 17 pose update
  std::vector<std::uint8_t> payload;  // the message (proto/messages.h Parse* input)
  bool replayed = false;              // read back from the journal at start
  double received_time = 0;           // MonotonicSeconds() at arrival; 0 when replayed
};

class MessageConsumer {
 public:
  virtual ~MessageConsumer() = default;
  virtual void OnAgentKnown(const AgentDescription& /*agent*/, bool /*from_journal*/) {}
  virtual void OnAgentConnected(AgentId /*agent*/, std::uint64_t /*last_stored_seq*/) {}
  virtual void OnAgentDisconnected(AgentId /*agent*/, const std::string& /*reason*/) {}
  virtual void OnMessage(DeliveredMessage message) = 0;
  virtual void OnReplayFinished(std::uint64_t /*messages*/) {}
};

}  // namespace ccmd
