#include "libccmd/dense/voxel_grid.h"

#include <algorithm>
#include <bit>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace ccmd {

void VoxelGrid::Indices(const std::vector<Eigen::Vector3f>& points,
                        std::vector<VoxelIndex>* out) const {
  static_assert(sizeof(Eigen::Vector3f) == 3 * sizeof(float));
  static_assert(sizeof(VoxelIndex) == 3 * sizeof(std::uint32_t));
  out->resize(points.size());
  // Every coordinate gets the same operation, so the points are one flat array of floats.
  const std::size_t n = 3 * points.size();
  const float* in = points.empty() ? nullptr : points[0].data();
  auto* o = reinterpret_cast<std::uint32_t*>(out->data());
  std::size_t i = 0;
#if defined(__SSE2__)
  const __m128 scale = _mm_set1_ps(inverse_size_);
  const __m128 low = _mm_set1_ps(-kLimit), high = _mm_set1_ps(kLimit);
  const __m128i offset = _mm_set1_epi32(kOffset);
  for (; i + 4 <= n; i += 4) {
    // max(x, low) returns low for NaN (the second operand), as Index does.
    const __m128 scaled =
        _mm_min_ps(_mm_max_ps(_mm_mul_ps(_mm_loadu_ps(in + i), scale), low), high);
    const __m128i truncated = _mm_cvttps_epi32(scaled);
    // Where truncation rounded up (negative non-integers), subtract one: the mask is -1 there.
    const __m128i above = _mm_castps_si128(_mm_cmpgt_ps(_mm_cvtepi32_ps(truncated), scaled));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(o + i),
                     _mm_add_epi32(_mm_add_epi32(truncated, above), offset));
  }
#endif
  for (; i < n; ++i) o[i] = Index(in[i]);
}

void VoxelTable::Allocate(std::size_t capacity) {
  slots_.assign(capacity, Slot{0, 0, 0});
  mask_ = capacity - 1;
  shift_ = 64 - std::countr_zero(capacity);
  stamp_ = 1;
  size_ = 0;
}

void VoxelTable::Clear(std::size_t expected) {
  // Load factor at most 1/2 keeps probe sequences short.
  const std::size_t wanted = std::bit_ceil(std::max<std::size_t>(1024, 2 * expected));
  // A table much larger than needed spreads a small job over many cache lines: shrink it.
  if (slots_.size() < wanted || slots_.size() > 8 * wanted) {
    Allocate(wanted);
    return;
  }
  size_ = 0;
  if (++stamp_ == 0) {  // wrapped after 2^32 clears: stale stamps could match again
    Allocate(slots_.size());
  }
}

void VoxelTable::Grow() {
  std::vector<Slot> old;
  old.swap(slots_);
  const std::uint32_t old_stamp = stamp_;
  Allocate(old.size() * 2);
  for (const Slot& s : old) {
    if (s.stamp != old_stamp) continue;
    bool inserted = false;
    FindOrInsert(s.key, &inserted) = s.value;
  }
}

std::int32_t& VoxelTable::FindOrInsert(std::uint64_t key, bool* inserted) {
  if (slots_.empty()) Allocate(1024);
  if (2 * (size_ + 1) > slots_.size()) Grow();
  for (std::size_t i = SlotOf(key);; i = (i + 1) & mask_) {
    Slot& s = slots_[i];
    if (s.stamp != stamp_) {
      s.key = key;
      s.value = 0;
      s.stamp = stamp_;
      ++size_;
      *inserted = true;
      return s.value;
    }
    if (s.key == key) {
      *inserted = false;
      return s.value;
    }
  }
}

const std::int32_t* VoxelTable::Find(std::uint64_t key) const {
  if (slots_.empty()) return nullptr;
  for (std::size_t i = SlotOf(key);; i = (i + 1) & mask_) {
    const Slot& s = slots_[i];
    if (s.stamp != stamp_) return nullptr;
    if (s.key == key) return &s.value;
  }
}

void VoxelFilterLargestLabel(PointCloud* cloud, double voxel_size) {
  const std::size_t n = cloud->size();
  if (n == 0) return;
  const VoxelGrid grid(voxel_size);
  // Each voxel holds 1 + its ordinal; winner[ordinal] is the index of its best point.
  VoxelBricks<std::uint32_t> ordinals;
  std::vector<std::uint32_t> winner;
  const bool labelled = cloud->HasLabels();
  for (std::size_t i = 0; i < n; ++i) {
    std::uint32_t& ordinal = ordinals.At(grid.Index(cloud->points[i]));
    if (ordinal == 0) {
      winner.push_back(static_cast<std::uint32_t>(i));
      ordinal = static_cast<std::uint32_t>(winner.size());
    } else if (labelled && cloud->labels[i] > cloud->labels[winner[ordinal - 1]]) {
      winner[ordinal - 1] = static_cast<std::uint32_t>(i);
    }
  }
  if (winner.size() == n) return;
  std::sort(winner.begin(), winner.end());
  const auto compact = [&](auto& values) {
    if (values.empty()) return;
    for (std::size_t k = 0; k < winner.size(); ++k) values[k] = values[winner[k]];
    values.resize(winner.size());
  };
  compact(cloud->points);
  compact(cloud->colors);
  compact(cloud->normals);
  compact(cloud->labels);
}

}  // namespace ccmd
