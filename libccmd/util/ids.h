#pragma once

// Typed identifiers. Across module boundaries ids are never bare integers: an AgentId cannot
// be passed where a KeyframeId is expected. A keyframe is globally identified by
// (agent, keyframe id): GlobalKeyframeId.

#include <cstdint>
#include <functional>
#include <ostream>

namespace ccmd {

template <typename Tag, typename Rep>
class TypedId {
 public:
  using ValueType = Rep;
  constexpr TypedId() = default;
  constexpr explicit TypedId(Rep value) : value_(value) {}
  constexpr Rep value() const { return value_; }
  constexpr auto operator<=>(const TypedId&) const = default;

 private:
  Rep value_ = 0;
};

template <typename Tag, typename Rep>
std::ostream& operator<<(std::ostream& os, TypedId<Tag, Rep> id) {
  return os << +id.value();
}

using AgentId = TypedId<struct AgentIdTag, std::uint16_t>;
using KeyframeId = TypedId<struct KeyframeIdTag, std::uint32_t>;  // unique within an agent
using MapPointId = TypedId<struct MapPointIdTag, std::uint32_t>;  // unique within an agent
using MapId = TypedId<struct MapIdTag, std::uint32_t>;            // server-side maps

struct GlobalKeyframeId {
  AgentId agent;
  KeyframeId keyframe;
  constexpr auto operator<=>(const GlobalKeyframeId&) const = default;
};

struct GlobalMapPointId {
  AgentId agent;
  MapPointId point;
  constexpr auto operator<=>(const GlobalMapPointId&) const = default;
};

}  // namespace ccmd

template <typename Tag, typename Rep>
struct std::hash<ccmd::TypedId<Tag, Rep>> {
  std::size_t operator()(ccmd::TypedId<Tag, Rep> id) const noexcept {
    return std::hash<Rep>()(id.value());
  }
};

template <>
struct std::hash<ccmd::GlobalKeyframeId> {
  std::size_t operator()(const ccmd::GlobalKeyframeId& id) const noexcept {
    return (static_cast<std::size_t>(id.agent.value()) << 32) ^ id.keyframe.value();
  }
};

template <>
struct std::hash<ccmd::GlobalMapPointId> {
  std::size_t operator()(const ccmd::GlobalMapPointId& id) const noexcept {
    return (static_cast<std::size_t>(id.agent.value()) << 32) ^ id.point.value();
  }
};
