#include "libccmd/util/ids.h"

#include <gtest/gtest.h>

#include <type_traits>
#include <unordered_set>

namespace ccmd {
namespace {

TEST(IdsTest, DistinctTypesDoNotConvert) {
  static_assert(!std::is_convertible_v<AgentId, KeyframeId>);
  static_assert(!std::is_convertible_v<std::uint32_t, KeyframeId>);  // explicit only
  EXPECT_LT(KeyframeId(3), KeyframeId(4));
}

TEST(IdsTest, GlobalIdsOrderByAgentThenKeyframeAndHash) {
  const GlobalKeyframeId a{AgentId(1), KeyframeId(900)}, b{AgentId(2), KeyframeId(1)};
  EXPECT_LT(a, b);
  std::unordered_set<GlobalKeyframeId> set = {a, b, a};
  EXPECT_EQ(set.size(), 2u);
}

}  // namespace
}  // namespace ccmd
