#include "libccmd/features/bow_database.h"

#include <algorithm>
#include <cmath>
#include <mutex>

#include "libccmd/util/logging.h"

namespace ccmd {

Status BowDatabase::Add(const GlobalKeyframeId& keyframe, MapId map, BowVector bow) {
  if (!bow.empty() && bow.entries().back().word >= kMaxWords) {
    return OutOfRange("word id " + std::to_string(bow.entries().back().word) +
                      " beyond the database limit");
  }
  bow.NormalizeL1();
  std::unique_lock lock(mutex_);
  if (auto it = slot_of_.find(keyframe); it != slot_of_.end()) EraseLocked(it->second);
  std::uint32_t slot;
  if (!free_slots_.empty()) {
    slot = free_slots_.back();
    free_slots_.pop_back();
  } else {
    slot = static_cast<std::uint32_t>(entries_.size());
    entries_.emplace_back();
  }
  if (!bow.empty() && bow.entries().back().word >= postings_.size()) {
    postings_.resize(bow.entries().back().word + 1);
  }
  for (const BowEntry& e : bow.entries()) {
    postings_[e.word].push_back({slot, static_cast<float>(e.weight)});
  }
  posting_count_ += bow.size();
  entries_[slot] = Entry{keyframe, map, std::move(bow), true};
  slot_of_[keyframe] = slot;
  return Status::Ok();
}

void BowDatabase::EraseLocked(std::uint32_t slot) {
  Entry& entry = entries_[slot];
  CCMD_CHECK(entry.used) << "erasing a free database slot";
  for (const BowEntry& e : entry.bow.entries()) {
    std::vector<Posting>& list = postings_[e.word];
    auto it =
        std::find_if(list.begin(), list.end(), [&](const Posting& p) { return p.slot == slot; });
    CCMD_CHECK(it != list.end()) << "inverted index lost keyframe posting";
    *it = list.back();
    list.pop_back();
  }
  posting_count_ -= entry.bow.size();
  slot_of_.erase(entry.keyframe);
  entry = Entry{};
  free_slots_.push_back(slot);
}

bool BowDatabase::Erase(const GlobalKeyframeId& keyframe) {
  std::unique_lock lock(mutex_);
  auto it = slot_of_.find(keyframe);
  if (it == slot_of_.end()) return false;
  EraseLocked(it->second);
  return true;
}

bool BowDatabase::SetMap(const GlobalKeyframeId& keyframe, MapId map) {
  std::unique_lock lock(mutex_);
  auto it = slot_of_.find(keyframe);
  if (it == slot_of_.end()) return false;
  entries_[it->second].map = map;
  return true;
}

int BowDatabase::MoveMap(MapId from, MapId to) {
  std::unique_lock lock(mutex_);
  int moved = 0;
  for (Entry& e : entries_) {
    if (e.used && e.map == from) {
      e.map = to;
      ++moved;
    }
  }
  return moved;
}

void BowDatabase::Clear() {
  std::unique_lock lock(mutex_);
  entries_.clear();
  free_slots_.clear();
  slot_of_.clear();
  postings_.clear();
  posting_count_ = 0;
}

std::vector<PlaceCandidate> BowDatabase::Query(const BowVector& bow,
                                               const PlaceQueryOptions& options) const {
  const double norm = bow.L1Norm();
  if (norm <= 0) return {};
  std::shared_lock lock(mutex_);
  std::vector<double> score(entries_.size(), 0.0);
  std::vector<int> common(entries_.size(), 0);
  std::vector<std::uint32_t> touched;
  for (const BowEntry& q : bow.entries()) {
    if (q.word >= postings_.size()) continue;
    const double weight = q.weight / norm;
    for (const Posting& p : postings_[q.word]) {
      if (common[p.slot]++ == 0) touched.push_back(p.slot);
      // Both vectors are L1-normalised and positive: the L1 score is the sum of the minima.
      score[p.slot] += std::min(weight, static_cast<double>(p.weight));
    }
  }

  auto contains = [](const auto& list, const auto& value) {
    return std::find(list.begin(), list.end(), value) != list.end();
  };
  std::vector<PlaceCandidate> candidates;
  int max_common = 0;
  for (std::uint32_t slot : touched) {
    const Entry& e = entries_[slot];
    if (common[slot] < options.min_common_words) continue;
    if (!options.exclude.empty() && options.exclude.count(e.keyframe)) continue;
    if (!options.agents.empty() && !contains(options.agents, e.keyframe.agent)) continue;
    if (!options.maps.empty() && !contains(options.maps, e.map)) continue;
    if (contains(options.exclude_maps, e.map)) continue;
    if (options.accept && !options.accept(e.keyframe, e.map)) continue;
    max_common = std::max(max_common, common[slot]);
    candidates.push_back({e.keyframe, e.map, std::min(score[slot], 1.0), common[slot]});
  }
  const double min_common = options.min_common_words_ratio * max_common;
  std::erase_if(candidates, [&](const PlaceCandidate& c) {
    return c.common_words < min_common || c.score < options.min_score;
  });
  auto better = [](const PlaceCandidate& a, const PlaceCandidate& b) {
    if (a.score != b.score) return a.score > b.score;
    return a.keyframe < b.keyframe;
  };
  if (options.max_results > 0 &&
      candidates.size() > static_cast<std::size_t>(options.max_results)) {
    std::partial_sort(candidates.begin(), candidates.begin() + options.max_results,
                      candidates.end(), better);
    candidates.resize(options.max_results);
  } else {
    std::sort(candidates.begin(), candidates.end(), better);
  }
  return candidates;
}

bool BowDatabase::Contains(const GlobalKeyframeId& keyframe) const {
  std::shared_lock lock(mutex_);
  return slot_of_.count(keyframe) > 0;
}

std::optional<BowVector> BowDatabase::Get(const GlobalKeyframeId& keyframe) const {
  std::shared_lock lock(mutex_);
  auto it = slot_of_.find(keyframe);
  if (it == slot_of_.end()) return std::nullopt;
  return entries_[it->second].bow;
}

std::optional<MapId> BowDatabase::MapOf(const GlobalKeyframeId& keyframe) const {
  std::shared_lock lock(mutex_);
  auto it = slot_of_.find(keyframe);
  if (it == slot_of_.end()) return std::nullopt;
  return entries_[it->second].map;
}

std::size_t BowDatabase::size() const {
  std::shared_lock lock(mutex_);
  return slot_of_.size();
}

std::size_t BowDatabase::PostingCount() const {
  std::shared_lock lock(mutex_);
  return posting_count_;
}

std::size_t BowDatabase::MemoryBytes() const {
  std::shared_lock lock(mutex_);
  // An unordered_map node: the value, a next pointer and the cached hash; plus its bucket.
  constexpr std::size_t kHashNode =
      sizeof(std::pair<GlobalKeyframeId, std::uint32_t>) + 3 * sizeof(void*);
  std::size_t bytes = entries_.capacity() * sizeof(Entry) +
                      free_slots_.capacity() * sizeof(std::uint32_t) + slot_of_.size() * kHashNode +
                      postings_.capacity() * sizeof(postings_[0]);
  for (const Entry& e : entries_) bytes += e.bow.entries().capacity() * sizeof(BowEntry);
  for (const auto& list : postings_) bytes += list.capacity() * sizeof(Posting);
  return bytes;
}

}  // namespace ccmd
