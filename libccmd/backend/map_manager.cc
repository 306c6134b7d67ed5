#include "libccmd/backend/map_manager.h"

#include "libccmd/util/logging.h"

namespace ccmd {

std::shared_ptr<MapManager::Entry> MapManager::EntryOf(MapId id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = maps_.find(id);
  return it == maps_.end() ? nullptr : it->second;
}

MapManager::Guard MapManager::CheckOutAgent(AgentId agent) {
  while (true) {
    std::shared_ptr<Entry> entry;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      auto it = agent_map_.find(agent);
      if (it == agent_map_.end()) {
        // An agent's own map is numbered like the agent (fused maps start at 1000).
        const MapId id(agent.value());
        auto fresh = std::make_shared<Entry>();
        fresh->map = std::make_unique<ServerMap>(id);
        maps_[id] = fresh;
        agent_map_[agent] = id;
        if (!primary_) primary_ = id;
        it = agent_map_.find(agent);
      }
      entry = maps_.at(it->second);
    }
    Guard guard(entry);
    if (guard) return guard;  // not fused away while we waited for its lock
  }
}

MapManager::Guard MapManager::CheckOut(MapId id) {
  std::shared_ptr<Entry> entry = EntryOf(id);
  if (!entry) return Guard();
  return Guard(entry);
}

std::pair<MapManager::Guard, MapManager::Guard> MapManager::CheckOutPair(MapId a, MapId b) {
  CCMD_CHECK(a != b) << "CheckOutPair needs two different maps";
  std::shared_ptr<Entry> ea = EntryOf(a), eb = EntryOf(b);
  if (!ea || !eb) return {Guard(), Guard()};
  if (a < b) {
    Guard ga(ea);
    Guard gb(eb);
    return {std::move(ga), std::move(gb)};
  }
  Guard gb(eb);
  Guard ga(ea);
  return {std::move(ga), std::move(gb)};
}

MapManager::Guard MapManager::Fuse(Guard* keep, Guard* other, const Pose& T_keep_other) {
  CCMD_CHECK(*keep && *other) << "fusing maps that are not checked out";
  auto fused = std::make_shared<Entry>();
  Guard result(fused);
  std::lock_guard<std::mutex> lock(mutex_);
  const MapId id(next_fused_id_++);
  fused->map = std::make_unique<ServerMap>(id);
  // The kept map goes first, so the fused map keeps its origin (and frame).
  fused->map->Absorb(keep->get(), Pose::Identity());
  fused->map->Absorb(other->get(), T_keep_other);
  const MapId keep_id = keep->get()->id(), other_id = other->get()->id();
  for (auto& [agent, map] : agent_map_) {
    if (map == keep_id || map == other_id) map = id;
  }
  if (primary_ && (*primary_ == keep_id || *primary_ == other_id)) primary_ = id;
  maps_[id] = fused;
  keep->entry_->retired = true;
  other->entry_->retired = true;
  maps_.erase(keep_id);
  maps_.erase(other_id);
  CCMD_LOG(INFO) << "maps " << keep_id.value() << " and " << other_id.value() << " fused into map "
                 << id.value();
  return result;
}

std::optional<MapId> MapManager::MapOfAgent(AgentId agent) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = agent_map_.find(agent);
  if (it == agent_map_.end()) return std::nullopt;
  return it->second;
}

std::optional<MapId> MapManager::primary() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return primary_;
}

std::vector<MapId> MapManager::Maps() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<MapId> ids;
  for (const auto& [id, entry] : maps_) ids.push_back(id);
  return ids;
}

std::vector<AgentId> MapManager::Agents() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<AgentId> ids;
  for (const auto& [agent, map] : agent_map_) ids.push_back(agent);
  return ids;
}

}  // namespace ccmd
