#include "libccmd/dense/voxel_grid.h"

#include <gtest/gtest.h>

#include <map>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

TEST(VoxelGridTest, KeysAreFloorOfCoordinatesOverSize) {
  const VoxelGrid grid(0.01);
  EXPECT_EQ(grid.Coordinates(grid.Key({0.0f, 0.0f, 0.0f})), Eigen::Vector3i(0, 0, 0));
  EXPECT_EQ(grid.Coordinates(grid.Key({0.0099f, 0.015f, 0.025f})), Eigen::Vector3i(0, 1, 2));
  EXPECT_EQ(grid.Coordinates(grid.Key({-0.001f, -0.0101f, -0.025f})), Eigen::Vector3i(-1, -2, -3));
  EXPECT_EQ(grid.Coordinates(grid.Key({123.456f, -7.0f, 0.5f})), Eigen::Vector3i(12345, -700, 50));
  EXPECT_NE(grid.Key({0.005f, 0.0f, 0.0f}), grid.Key({0.0f, 0.005f, 0.0f}) + 1);
  // Far beyond +-2^20 voxels: clamped, no overflow into the neighbouring axis.
  const Eigen::Vector3i far = grid.Coordinates(grid.Key({1e9f, -1e9f, 0.0f}));
  EXPECT_EQ(far, Eigen::Vector3i((1 << 20) - 1, -((1 << 20) - 1), 0));
}

TEST(VoxelTableTest, BehavesLikeAMapAcrossGrowthAndClears) {
  VoxelTable table;
  std::map<std::uint64_t, std::int32_t> reference;
  Rng rng(7);
  for (int round = 0; round < 3; ++round) {
    table.Clear(16);  // far fewer than inserted: must grow
    reference.clear();
    for (int i = 0; i < 20000; ++i) {
      const std::uint64_t key = rng.Next() % 5000 + round * 100000ull;
      bool inserted = false;
      std::int32_t& v = table.FindOrInsert(key, &inserted);
      EXPECT_EQ(inserted, reference.count(key) == 0);
      v += i;
      reference[key] += i;
    }
    ASSERT_EQ(table.size(), reference.size());
    for (const auto& [key, value] : reference) {
      const std::int32_t* found = table.Find(key);
      ASSERT_NE(found, nullptr);
      EXPECT_EQ(*found, value);
    }
    // Keys of the previous round are gone after Clear.
    if (round > 0) {
      EXPECT_EQ(table.Find((round - 1) * 100000ull + 1), nullptr);
    }
  }
}

TEST(VoxelFilterTest, KeepsTheLargestLabelPerVoxel) {
  PointCloud c;
  const auto add = [&](float x, float y, float z, std::uint32_t label, std::uint8_t red) {
    c.points.emplace_back(x, y, z);
    c.labels.push_back(label);
    c.colors.push_back({red, 0, 0});
  };
  // Voxel (0,0,0) at 1 cm: labels 5, 9, 7 -> the point labelled 9 survives.
  add(0.001f, 0.001f, 0.001f, 5, 1);
  add(0.009f, 0.002f, 0.0f, 9, 2);
  add(0.005f, 0.005f, 0.005f, 7, 3);
  add(-0.001f, 0.0f, 0.0f, 1, 4);  // voxel (-1,0,0), alone
  add(0.0101f, 0.0f, 0.0f, 2, 5);  // voxel (1,0,0)
  add(0.0199f, 0.0f, 0.0f, 2, 6);  // same voxel and label: the first one stays
  VoxelFilterLargestLabel(&c, 0.01);
  ASSERT_EQ(c.size(), 3u);
  ASSERT_TRUE(c.IsConsistent());
  // Survivors keep their order.
  EXPECT_EQ(c.labels, (std::vector<std::uint32_t>{9, 1, 2}));
  EXPECT_EQ(c.colors[0][0], 2);
  EXPECT_EQ(c.colors[2][0], 5);
  EXPECT_FLOAT_EQ(c.points[0].x(), 0.009f);
}

TEST(VoxelFilterTest, UnlabelledCloudKeepsTheFirstPointOfEachVoxel) {
  PointCloud c;
  // 0.05 .. 9.95 cm, never on a voxel boundary.
  for (int i = 0; i < 100; ++i) c.points.emplace_back(0.001f * i + 0.0005f, 0.0f, 0.0f);
  VoxelFilterLargestLabel(&c, 0.02);
  ASSERT_EQ(c.size(), 5u);
  for (int k = 0; k < 5; ++k) EXPECT_NEAR(c.points[k].x(), 0.02 * k + 0.0005, 1e-6);
}

}  // namespace
}  // namespace ccmd
