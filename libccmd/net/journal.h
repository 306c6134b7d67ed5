#pragma once

// The server's per-agent journal: an append-only file of frames in the wire format
// (proto/frame.h: magic, version, type, length, payload CRC32C, header CRC32C), so every
// record is checked on replay.
//
//   record 0            type 1 (journal info): the agent's id, name and camera, the frame
//                       payload limit the journal is written with, the agent's identity
//                       verifier (agent_identity.h)
//   records 1..n        type 16/17 (data): payload = u64 sequence number | message, exactly
//                       the payload of the data frame that arrived (never a tag)
//                       type 2 (update, anywhere after the info): a raised payload limit or
//                       an identity verifier adopted later (journals of protocol version 1)
//
// Durability: JournalWriter::Append() write()s whole records; Sync() calls fdatasync().
// The server syncs once per batch of records, before it acknowledges any of them, so an
// acknowledged message survives a crash of the process and of the machine (a group commit:
// agents sending at the same time share one fdatasync per journal).
//
// Replay (ScanJournalFile) reads the records in order, each checked against the payload
// limit the journal was written with (not the server's current one). A crash can leave the
// last record incomplete or, on some file systems, ending in never-written (zero) blocks:
// a tail shown to be incomplete that way is reported and cut off (JournalWriter::
// OpenForAppend truncates it), never fatal. Anything else that fails its checks is damage:
// an error naming the file and offset that says whether intact records follow, and never
// advises a cut that would drop a record passing its CRC. The operator decides.

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

constexpr std::uint8_t kJournalInfoRecord = 1;
constexpr std::uint8_t kJournalUpdateRecord = 2;
// Info and update records are small; a larger one is damage.
constexpr std::uint32_t kMaxJournalInfoBytes = 4096;
// The largest payload limit a journal may record (the server's --max-frame-bytes range).
constexpr std::uint32_t kMaxJournalPayloadBytes = 1u << 30;

struct JournalAgentInfo {
  AgentId id;
  std::string name;
  SessionCamera camera;
  // The frame payload limit the records were written under; 0 in journals of protocol
  // version 1, which did not record it (they are read with kMaxJournalPayloadBytes).
  std::uint32_t max_payload_bytes = kDefaultMaxPayloadBytes;
  IdentityVerifier verifier{};  // all zero: none recorded (protocol version 1)
};

// Version 2 layout. `version` is the record's frame version: version 1 info records end
// after the camera (and its distortion trailer), with no limit and no verifier.
std::vector<std::uint8_t> SerializeJournalInfo(const JournalAgentInfo& info);
StatusOr<JournalAgentInfo> ParseJournalInfo(ByteSpan payload,
                                            std::uint8_t version = kProtocolVersion);

// An update record: the limit and verifier in force from there on (a zero verifier keeps
// the previous one).
struct JournalUpdate {
  std::uint32_t max_payload_bytes = 0;
  IdentityVerifier verifier{};
};
std::vector<std::uint8_t> SerializeJournalUpdate(const JournalUpdate& update);
StatusOr<JournalUpdate> ParseJournalUpdate(ByteSpan payload);

// "agent_00003.journal": the file of agent id 3 in a journal folder.
std::string JournalFileName(AgentId id);
// True for names of that form (the agent id is stored in *id).
bool ParseJournalFileName(const std::string& name, AgentId* id);

class JournalWriter {
 public:
  // Creates a new journal (kInvalidArgument if the file exists), writes the info record and
  // makes the file and its folder entry durable before returning.
  static StatusOr<std::unique_ptr<JournalWriter>> Create(const std::string& path,
                                                         const JournalAgentInfo& info);
  // Opens a replayed journal for appending after its last good record (`valid_bytes`);
  // anything after it (a torn record) is cut off and the cut made durable.
  static StatusOr<std::unique_ptr<JournalWriter>> OpenForAppend(const std::string& path,
                                                                std::uint64_t valid_bytes);

  // Appends one data record (written, not yet durable).
  Status Append(std::uint8_t type, std::uint64_t seq, ByteSpan message);
  // Appends an update record and makes it durable.
  Status AppendUpdate(const JournalUpdate& update);
  // Makes everything appended so far durable (fdatasync).
  Status Sync();
  // After a failed Append or Sync: cuts the file back to what the last Sync made durable.
  Status RollBack();

  std::uint64_t size() const { return size_; }
  std::uint64_t synced_size() const { return synced_size_; }
  const std::string& path() const { return path_; }

 private:
  JournalWriter(std::string path, UniqueFd fd, std::uint64_t size)
      : path_(std::move(path)), fd_(std::move(fd)), size_(size), synced_size_(size) {}

  std::string path_;
  UniqueFd fd_;
  std::uint64_t size_ = 0;
  std::uint64_t synced_size_ = 0;
  std::vector<std::uint8_t> buffer_;
};

struct JournalRecord {
  std::uint8_t type = 0;
  std::uint64_t seq = 0;
  ByteSpan message;          // valid during the callback only
  std::uint64_t offset = 0;  // of the record in the file
};

struct JournalScan {
  bool has_info = false;      // false: the file ends inside its first record (crash at creation)
  JournalAgentInfo info;      // with every update record applied
  std::uint64_t records = 0;  // data records
  std::uint64_t first_seq = 0;
  std::uint64_t last_seq = 0;
  std::uint64_t gaps = 0;         // forward jumps in the sequence numbers (see Server, resume)
  std::uint64_t valid_bytes = 0;  // the file up to the end of the last good record
  std::uint64_t torn_bytes = 0;   // bytes after that: a torn tail, to be cut off
  std::string torn_reason;
};

struct JournalScanOptions {
  // An upper bound on top of the journal's own limit (fuzzing uses a small one).
  std::uint32_t max_payload_bytes = kMaxJournalPayloadBytes;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Called during a scan: on_info once with the info record, then on_record for each data
// record in order (either may be empty). An error from a callback stops the scan and is
// returned.
struct JournalVisitor {
  std::function<Status(const JournalAgentInfo&)> on_info;
  std::function<Status(const JournalRecord&)> on_record;
};

StatusOr<JournalScan> ScanJournalFile(const std::string& path, const JournalVisitor& visitor = {},
                                      const JournalScanOptions& options = {});
// The same over bytes in memory (tests, fuzzing).
StatusOr<JournalScan> ScanJournalBytes(ByteSpan bytes, const JournalVisitor& visitor = {},
                                       const JournalScanOptions& options = {});

// Makes a folder entry (a created or renamed file) durable.
Status SyncDirectory(const std::string& dir);

}  // namespace ccmd
