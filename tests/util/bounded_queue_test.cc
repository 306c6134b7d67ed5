#include "libccmd/util/bounded_queue.h"

#include <gtest/gtest.h>

#include <thread>
#include <vector>

namespace ccmd {
namespace {

TEST(BoundedQueueTest, TryPushRespectsCapacity) {
  BoundedQueue<int> q(2);
  EXPECT_TRUE(q.TryPush(1));
  EXPECT_TRUE(q.TryPush(2));
  EXPECT_FALSE(q.TryPush(3));
  EXPECT_EQ(*q.TryPop(), 1);
  EXPECT_TRUE(q.TryPush(3));
  EXPECT_EQ(q.size(), 2u);
}

TEST(BoundedQueueTest, CloseDrainsThenEnds) {
  BoundedQueue<int> q(4);
  q.Push(7);
  q.Close();
  EXPECT_FALSE(q.Push(8));
  EXPECT_EQ(*q.Pop(), 7);
  EXPECT_FALSE(q.Pop().has_value());
}

TEST(BoundedQueueTest, ProducersAndConsumersDeliverEverythingOnce) {
  BoundedQueue<int> q(3);  // small capacity forces producers to block
  constexpr int kProducers = 4, kItems = 2000;
  std::vector<int> seen(kProducers * kItems, 0);
  std::vector<std::thread> producers;
  for (int p = 0; p < kProducers; ++p) {
    producers.emplace_back([&, p] {
      for (int i = 0; i < kItems; ++i) ASSERT_TRUE(q.Push(p * kItems + i));
    });
  }
  std::thread consumer([&] {
    while (auto v = q.Pop()) ++seen[*v];
  });
  for (auto& t : producers) t.join();
  q.Close();
  consumer.join();
  for (int count : seen) ASSERT_EQ(count, 1);
}

}  // namespace
}  // namespace ccmd
