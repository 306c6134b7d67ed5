#pragma once

// Voxel keys and the open-addressing table the dense map filters with.
//
// A voxel is floor(p / size) per axis; the three indices are packed into one 64-bit key,
// 21 bits each (offset by 2^20), so the grid spans +-2^20 voxels per axis (+-10 km at 1 cm).
// Points beyond that are clamped to the outermost voxel: they still get a key, but share it.
//
// VoxelTable maps keys to 32-bit values. It is cleared in O(1) (a generation stamp per slot),
// because the store clears it for every keyframe it adds and a clear must not cost a pass
// over memory sized for the largest use.

#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "libccmd/io/ply.h"

namespace ccmd {

class VoxelGrid {
 public:
  explicit VoxelGrid(double voxel_size) : inverse_size_(static_cast<float>(1.0 / voxel_size)) {}

  std::uint64_t Key(const Eigen::Vector3f& p) const {
    return (static_cast<std::uint64_t>(Index(p.x())) << 42) |
           (static_cast<std::uint64_t>(Index(p.y())) << 21) |
           static_cast<std::uint64_t>(Index(p.z()));
  }

  // The voxel's integer coordinates, for tests and tools.
  Eigen::Vector3i Coordinates(std::uint64_t key) const {
    const auto axis = [](std::uint64_t bits) { return static_cast<int>(bits & kMask) - kOffset; };
    return {axis(key >> 42), axis(key >> 21), axis(key)};
  }

 private:
  static constexpr int kOffset = 1 << 20;
  static constexpr std::uint64_t kMask = (1u << 21) - 1;
  static constexpr float kLimit = static_cast<float>(kOffset - 1);

  // floor(v / size) + offset, clamped to [0, 2^21 - 1]. Written without std::floor: the
  // cast truncates towards zero, so negative non-integers step down by one.
  std::uint32_t Index(float v) const {
    float scaled = v * inverse_size_;
    if (!(scaled > -kLimit)) scaled = -kLimit;  // also catches NaN
    if (scaled > kLimit) scaled = kLimit;
    int i = static_cast<int>(scaled);
    if (scaled < static_cast<float>(i)) --i;
    return static_cast<std::uint32_t>(i + kOffset);
  }

  float inverse_size_;
};

class VoxelTable {
 public:
  // Empties the table and makes room for `expected` keys (it still grows if more arrive).
  void Clear(std::size_t expected);

  // The value stored for `key`, inserting it (value 0) if absent; `inserted` says which.
  // The reference is valid until the next insertion.
  std::int32_t& FindOrInsert(std::uint64_t key, bool* inserted);

  // The value for `key`, or nullptr.
  const std::int32_t* Find(std::uint64_t key) const;

  std::size_t size() const { return size_; }
  std::size_t MemoryBytes() const { return slots_.capacity() * sizeof(Slot); }

 private:
  struct Slot {
    std::uint64_t key;
    std::int32_t value;
    std::uint32_t stamp;  // the slot is occupied iff stamp == stamp_
  };

  std::size_t SlotOf(std::uint64_t key) const {
    return static_cast<std::size_t>((key * 0x9E3779B97F4A7C15ull) >> shift_);
  }
  void Allocate(std::size_t capacity);
  void Grow();

  std::vector<Slot> slots_;
  std::size_t size_ = 0;
  std::size_t mask_ = 0;
  int shift_ = 64;
  std::uint32_t stamp_ = 1;
};

// Keeps one point per voxel of `voxel_size` metres: the one with the largest label (the first
// of them if several share it). Without labels, the first point of each voxel. Survivors keep
// their order. Every attribute of the cloud is filtered alike.
void VoxelFilterLargestLabel(PointCloud* cloud, double voxel_size);

}  // namespace ccmd
