#pragma once

// The disk part of an agent's resend buffer. When the unacknowledged messages exceed the
// link's memory limit, newer ones go here, in order, and come back (oldest first) as
// acknowledgements free memory. Records are frames like the server's journal data records,
// in segment files of a folder the store owns: it locks the folder (one link per folder),
// clears segments a previous process left behind and removes its own files when done.
// Spilling bounds memory; it is not crash durability for the agent (a restarted agent has
// lost its map anyway).

#include <cstdint>
#include <deque>
#include <memory>
#include <string>
#include <vector>

#include "libccmd/net/socket.h"
#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

struct SpilledMessage {
  std::uint8_t type = 0;
  std::uint64_t seq = 0;
  std::vector<std::uint8_t> message;
};

class SpillStore {
 public:
  // max_bytes bounds the segment files on disk; segment_bytes is the size at which a new
  // segment file is started (a fully read segment is deleted).
  static StatusOr<std::unique_ptr<SpillStore>> Open(const std::string& dir, std::uint64_t max_bytes,
                                                    std::uint64_t segment_bytes = 16u << 20);
  ~SpillStore();
  SpillStore(const SpillStore&) = delete;
  SpillStore& operator=(const SpillStore&) = delete;

  // kOutOfRange when the disk limit would be exceeded.
  Status Push(std::uint8_t type, std::uint64_t seq, ByteSpan message);
  // Removes and returns the oldest message. Precondition: !empty(). A record that fails
  // its CRC on the way back is kCorrupt.
  StatusOr<SpilledMessage> Pop();

  bool empty() const { return index_.empty(); }
  std::size_t count() const { return index_.size(); }
  // Message bytes of the oldest record (to decide whether it fits in memory).
  std::size_t front_message_bytes() const { return index_.front().message_bytes; }
  std::uint64_t disk_bytes() const { return disk_bytes_; }
  const std::string& dir() const { return dir_; }

 private:
  struct Segment {
    std::uint64_t number = 0;
    std::string path;
    UniqueFd fd;
    std::uint64_t size = 0;
    std::size_t unread = 0;
  };
  struct Entry {
    std::uint64_t segment = 0;
    std::uint64_t offset = 0;
    std::size_t frame_bytes = 0;
    std::size_t message_bytes = 0;
  };

  SpillStore(std::string dir, UniqueFd lock, std::uint64_t max_bytes, std::uint64_t segment_bytes)
      : dir_(std::move(dir)),
        lock_(std::move(lock)),
        max_bytes_(max_bytes),
        segment_bytes_(segment_bytes) {}
  Status StartSegment();
  void DropSegment();

  std::string dir_;
  UniqueFd lock_;
  std::uint64_t max_bytes_;
  std::uint64_t segment_bytes_;
  std::deque<Segment> segments_;
  std::deque<Entry> index_;
  std::uint64_t next_segment_ = 0;
  std::uint64_t disk_bytes_ = 0;
  std::vector<std::uint8_t> buffer_;
};

}  // namespace ccmd
