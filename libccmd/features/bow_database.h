#pragma once

// The keyframe database for place recognition: an inverted index from each word to the
// keyframes whose bag-of-words vector holds it, so a query visits only keyframes that share
// a word with it and scores them with the L1 score (bow_vector.h). Keyframes are identified
// globally by (agent, keyframe) and carry the map they currently belong to, so the server
// can look for loops inside one map or between maps.
//
// Thread safety: every method may be called from any thread at any time. Add, Erase, SetMap,
// MoveMap and Clear take the database exclusively; Query, Get, Contains and size share it, so
// several queries run in parallel and a keyframe added by one thread is visible to every
// query that starts after Add returned. The `accept` filter of a query runs under the shared
// lock and must not call back into a modifying method of the same database.
//
// All vectors in one database must come from one vocabulary; after a vocabulary is retrained
// the database is cleared and every keyframe added again with its new vector.

#include <cstdint>
#include <functional>
#include <optional>
#include <shared_mutex>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "libccmd/features/bow_vector.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct PlaceCandidate {
  GlobalKeyframeId keyframe;
  MapId map;
  double score = 0;      // L1 score against the query, in [0, 1]
  int common_words = 0;  // words shared with the query
};

struct PlaceQueryOptions {
  int max_results = 10;    // best candidates by score; <= 0: all
  double min_score = 0.0;  // candidates scoring lower are dropped
  // Keep only candidates sharing at least this fraction of the words shared by the best
  // sharing candidate (ORB-SLAM's pre-filter against keyframes with few words in common).
  double min_common_words_ratio = 0.0;
  int min_common_words = 1;
  // Filters, all optional: keyframes never returned; only these agents / maps (empty: any);
  // never these maps; a predicate on (keyframe, map) that must return true.
  std::unordered_set<GlobalKeyframeId> exclude;
  std::vector<AgentId> agents;
  std::vector<MapId> maps;
  std::vector<MapId> exclude_maps;
  std::function<bool(const GlobalKeyframeId&, MapId)> accept;
};

class BowDatabase {
 public:
  // Word ids at or above this are refused (a bound on the index size, far above any
  // vocabulary of the supported shape).
  static constexpr WordId kMaxWords = 1u << 25;

  BowDatabase() = default;
  BowDatabase(const BowDatabase&) = delete;
  BowDatabase& operator=(const BowDatabase&) = delete;

  // Adds a keyframe, or replaces its vector and map if it is already present. The vector is
  // L1-normalised on the way in. OutOfRange for word ids >= kMaxWords (nothing is changed).
  Status Add(const GlobalKeyframeId& keyframe, MapId map, BowVector bow);
  // Removes a keyframe; false if it was not present.
  bool Erase(const GlobalKeyframeId& keyframe);
  // Moves one keyframe to another map; false if it is not present.
  bool SetMap(const GlobalKeyframeId& keyframe, MapId map);
  // Moves every keyframe of map `from` to map `to` (map fusion); returns how many moved.
  int MoveMap(MapId from, MapId to);
  void Clear();

  // The best candidates for `bow`, highest score first (ties: lower agent, then keyframe id).
  std::vector<PlaceCandidate> Query(const BowVector& bow,
                                    const PlaceQueryOptions& options = {}) const;

  bool Contains(const GlobalKeyframeId& keyframe) const;
  std::optional<BowVector> Get(const GlobalKeyframeId& keyframe) const;
  std::optional<MapId> MapOf(const GlobalKeyframeId& keyframe) const;
  std::size_t size() const;
  // Postings in the inverted index (one per keyframe per word it holds); for statistics
  // and consistency tests.
  std::size_t PostingCount() const;
  // Bytes the database holds: entries, their vectors, the inverted index.
  std::size_t MemoryBytes() const;

 private:
  struct Posting {
    std::uint32_t slot;
    float weight;
  };
  struct Entry {
    GlobalKeyframeId keyframe;
    MapId map;
    BowVector bow;
    bool used = false;
  };

  void EraseLocked(std::uint32_t slot);

  mutable std::shared_mutex mutex_;
  std::vector<Entry> entries_;  // by slot
  std::vector<std::uint32_t> free_slots_;
  std::unordered_map<GlobalKeyframeId, std::uint32_t> slot_of_;
  std::vector<std::vector<Posting>> postings_;  // by word
  std::size_t posting_count_ = 0;
};

}  // namespace ccmd
