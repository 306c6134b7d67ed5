#pragma once

// Voxels and the lookup structures the dense map filters with.
//
// A voxel is floor(p / size) per axis, offset by 2^20 so that indices are unsigned 21-bit
// values: the grid spans +-2^20 voxels per axis (+-10 km at 1 cm). Points beyond that are
// clamped to the outermost voxel: they still get a voxel, but share it. A voxel's key packs
// the three indices into 63 bits.
//
// VoxelTable maps 64-bit keys to 32-bit values (open addressing, cleared in O(1) by a
// generation stamp, because the store clears it for every keyframe it adds).
//
// VoxelBricks<T> gives every voxel a value of type T (0 = empty) stored in bricks of 4x4x4
// voxels found through a VoxelTable. Points of a depth image come in raster order, so
// consecutive points mostly fall in the brick looked up last: most accesses skip the hash
// table, and the bricks of one keyframe fit in the processor's cache where a table of one
// slot per voxel would not.

#include <array>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "libccmd/io/ply.h"

namespace ccmd {

struct VoxelIndex {
  std::uint32_t x, y, z;  // each in [0, 2^21)
};

inline std::uint64_t PackVoxel(std::uint32_t x, std::uint32_t y, std::uint32_t z) {
  return (static_cast<std::uint64_t>(x) << 42) | (static_cast<std::uint64_t>(y) << 21) | z;
}

class VoxelGrid {
 public:
  explicit VoxelGrid(double voxel_size) : inverse_size_(static_cast<float>(1.0 / voxel_size)) {}

  VoxelIndex Index(const Eigen::Vector3f& p) const {
    return {Index(p.x()), Index(p.y()), Index(p.z())};
  }
  std::uint64_t Key(const Eigen::Vector3f& p) const {
    return PackVoxel(Index(p.x()), Index(p.y()), Index(p.z()));
  }
  static std::uint64_t KeyOf(const VoxelIndex& v) { return PackVoxel(v.x, v.y, v.z); }
  // The voxel of every point (the same as Index for each), four coordinates at a time.
  void Indices(const std::vector<Eigen::Vector3f>& points, std::vector<VoxelIndex>* out) const;

  // The voxel's integer coordinates, for tests and tools.
  Eigen::Vector3i Coordinates(std::uint64_t key) const {
    const auto axis = [](std::uint64_t bits) { return static_cast<int>(bits & kMask) - kOffset; };
    return {axis(key >> 42), axis(key >> 21), axis(key)};
  }

 private:
  static constexpr int kOffset = 1 << 20;
  static constexpr std::uint64_t kMask = (1u << 21) - 1;
  static constexpr float kLimit = static_cast<float>(kOffset - 1);

  // floor(v / size) + offset, clamped to [0, 2^21 - 1]. Branch-free, so that loops over
  // points vectorise: the clamps compile to max/min (a NaN becomes the lower bound), and
  // truncation towards zero is corrected to the floor by one comparison.
  std::uint32_t Index(float v) const {
    float scaled = v * inverse_size_;
    scaled = scaled > -kLimit ? scaled : -kLimit;
    scaled = scaled < kLimit ? scaled : kLimit;
    const int truncated = static_cast<int>(scaled);
    const int floor = truncated - (static_cast<float>(truncated) > scaled ? 1 : 0);
    return static_cast<std::uint32_t>(floor + kOffset);
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

// A set of voxels: one bit per voxel in 64-bit words of 4x4x4 voxels, found like VoxelBricks
// finds its bricks. The words of a keyframe (a few thousand) fit in the first-level cache.
class VoxelSet {
 public:
  VoxelSet() { cache_.fill(CacheEntry{~0ull, -1}); }  // ~0 is no brick's key

  void Clear() {
    table_.Clear(words_.size());
    words_.clear();
    cache_.fill(CacheEntry{~0ull, -1});
    last_key_ = ~0ull;
    last_ = -1;
  }

  // Adds the voxel; returns 1 if it was absent, 0 if present.
  std::uint8_t Insert(const VoxelIndex& v) {
    std::uint64_t& word = words_[Word(v, /*create=*/true)];
    const std::uint64_t bit = 1ull << Local(v);
    const std::uint8_t absent = (word & bit) == 0;
    word |= bit;
    return absent;
  }

  bool Contains(const VoxelIndex& v) {
    const std::int32_t w = Word(v, /*create=*/false);
    return w >= 0 && (words_[w] >> Local(v)) & 1u;
  }

  // Removes the voxel (nothing happens if it is absent). Its word stays allocated.
  void Erase(const VoxelIndex& v) {
    const std::int32_t w = Word(v, /*create=*/false);
    if (w >= 0) words_[w] &= ~(1ull << Local(v));
  }

  std::size_t MemoryBytes() const {
    return table_.MemoryBytes() + words_.capacity() * sizeof(std::uint64_t) + sizeof(cache_);
  }

 private:
  struct CacheEntry {
    std::uint64_t key;
    std::int32_t index;  // -1: absent
  };
  static constexpr int kCacheBits = 10;

  static std::uint32_t Local(const VoxelIndex& v) {
    return (v.x & 3u) | ((v.y & 3u) << 2) | ((v.z & 3u) << 4);
  }

  // Index of the voxel's word (-1 if absent and !create). A row of a depth image crosses a
  // few dozen words and the next row the same ones: the last word and a small direct-mapped
  // cache answer most lookups before the table.
  std::int32_t Word(const VoxelIndex& v, bool create) {
    const std::uint64_t key = PackVoxel(v.x >> 2, v.y >> 2, v.z >> 2);
    if (key == last_key_ && (last_ >= 0 || !create)) return last_;
    CacheEntry& cached =
        cache_[static_cast<std::size_t>((key * 0x9E3779B97F4A7C15ull) >> (64 - kCacheBits))];
    if (cached.key != key || (cached.index < 0 && create)) {
      if (create) {
        bool inserted = false;
        std::int32_t& index = table_.FindOrInsert(key, &inserted);
        if (inserted) {
          index = static_cast<std::int32_t>(words_.size());
          words_.push_back(0);
        }
        cached = {key, index};
      } else {
        const std::int32_t* index = table_.Find(key);
        cached = {key, index ? *index : -1};
      }
    }
    last_key_ = key;
    last_ = cached.index;
    return last_;
  }

  VoxelTable table_;
  std::vector<std::uint64_t> words_;
  std::array<CacheEntry, 1 << kCacheBits> cache_;
  std::uint64_t last_key_ = ~0ull;
  std::int32_t last_ = -1;
};

template <typename T>
class VoxelBricks {
 public:
  VoxelBricks() { cache_.fill(CacheEntry{~0ull, -1}); }  // ~0 is no brick's key

  // Empties the map, keeping its memory.
  void Clear() {
    table_.Clear(bricks_.size());
    bricks_.clear();
    cache_.fill(CacheEntry{~0ull, -1});
    last_key_ = ~0ull;
    last_ = -1;
  }

  // The voxel's value, its brick created (all values 0) if absent. Valid until the next At.
  T& At(const VoxelIndex& v) {
    const std::uint64_t key = BrickKey(v);
    if (key != last_key_ || last_ < 0) {
      CacheEntry& cached = cache_[CacheSlot(key)];
      if (cached.key != key || cached.index < 0) {
        bool inserted = false;
        std::int32_t& index = table_.FindOrInsert(key, &inserted);
        if (inserted) {
          index = static_cast<std::int32_t>(bricks_.size());
          bricks_.emplace_back();
          bricks_.back().fill(T{0});
        }
        cached = {key, index};
      }
      last_key_ = key;
      last_ = cached.index;
    }
    return bricks_[last_][Local(v)];
  }

  // The voxel's value, 0 if its brick is absent.
  T Get(const VoxelIndex& v) {
    const std::uint64_t key = BrickKey(v);
    if (key != last_key_) {
      CacheEntry& cached = cache_[CacheSlot(key)];
      if (cached.key != key) {
        const std::int32_t* index = table_.Find(key);
        cached = {key, index ? *index : -1};  // remembers absent bricks too
      }
      last_key_ = key;
      last_ = cached.index;
    }
    return last_ < 0 ? T{0} : bricks_[last_][Local(v)];
  }

  std::size_t bricks() const { return bricks_.size(); }
  std::size_t MemoryBytes() const {
    return table_.MemoryBytes() + bricks_.capacity() * sizeof(bricks_[0]) + sizeof(cache_);
  }

 private:
  // A row of a depth image crosses a few dozen bricks and the next row crosses the same ones:
  // a small direct-mapped cache in front of the table answers most brick lookups.
  struct CacheEntry {
    std::uint64_t key;
    std::int32_t index;  // -1: the brick is absent
  };
  static constexpr int kCacheBits = 10;

  static std::uint64_t BrickKey(const VoxelIndex& v) {
    return PackVoxel(v.x >> 2, v.y >> 2, v.z >> 2);
  }
  static std::size_t CacheSlot(std::uint64_t key) {
    return static_cast<std::size_t>((key * 0x9E3779B97F4A7C15ull) >> (64 - kCacheBits));
  }
  static std::size_t Local(const VoxelIndex& v) {
    return (v.x & 3u) | ((v.y & 3u) << 2) | ((v.z & 3u) << 4);
  }

  VoxelTable table_;
  std::vector<std::array<T, 64>> bricks_;
  std::array<CacheEntry, 1 << kCacheBits> cache_;
  std::uint64_t last_key_ = ~0ull;
  std::int32_t last_ = -1;
};

// Keeps one point per voxel of `voxel_size` metres: the one with the largest label (the first
// of them if several share it). Without labels, the first point of each voxel. Survivors keep
// their order. Every attribute of the cloud is filtered alike.
void VoxelFilterLargestLabel(PointCloud* cloud, double voxel_size);

}  // namespace ccmd
