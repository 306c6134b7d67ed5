#pragma once

// Owns the server maps. Every agent starts its own map; the first agent's map is the primary
// map (its frame is the world frame of the results). A map is worked on by one thread at a
// time: CheckOut returns a Guard that holds the map's lock until it goes out of scope. When
// a loop links two maps they are fused into a new map that replaces both.

#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <vector>

#include "libccmd/backend/server_map.h"

namespace ccmd {

class MapManager {
 private:
  struct Entry {
    std::mutex mutex;
    std::unique_ptr<ServerMap> map;
    bool retired = false;  // fused into another map; guards taken later see no map
  };

 public:
  // Exclusive access to one map while it lives. Empty when the map no longer exists.
  class Guard {
   public:
    Guard() = default;
    ServerMap* get() const { return entry_ && !entry_->retired ? entry_->map.get() : nullptr; }
    ServerMap* operator->() const { return get(); }
    ServerMap& operator*() const { return *get(); }
    explicit operator bool() const { return get() != nullptr; }

   private:
    friend class MapManager;
    Guard(std::shared_ptr<Entry> entry) : entry_(std::move(entry)), lock_(entry_->mutex) {}
    std::shared_ptr<Entry> entry_;
    std::unique_lock<std::mutex> lock_;
  };

  // The map `agent` currently belongs to, creating the agent's own map the first time.
  Guard CheckOutAgent(AgentId agent);
  Guard CheckOut(MapId id);
  // Two different maps, locked in id order (no deadlock between threads doing the same).
  std::pair<Guard, Guard> CheckOutPair(MapId a, MapId b);

  // Fuses the two checked-out maps into a new map in `keep`'s frame: `other`'s keyframes and
  // points are premultiplied by T_keep_other. Returns a guard on the new map; the old guards
  // become empty.
  Guard Fuse(Guard* keep, Guard* other, const Pose& T_keep_other);

  std::optional<MapId> MapOfAgent(AgentId agent) const;
  std::optional<MapId> primary() const;
  std::vector<MapId> Maps() const;
  std::vector<AgentId> Agents() const;

 private:
  std::shared_ptr<Entry> EntryOf(MapId id) const;

  mutable std::mutex mutex_;  // guards the tables below, never held while a map is locked
  std::map<MapId, std::shared_ptr<Entry>> maps_;
  std::map<AgentId, MapId> agent_map_;
  std::optional<MapId> primary_;
  std::uint32_t next_fused_id_ = 1000;
};

}  // namespace ccmd
