#include "libccmd/features/descriptor.h"

#include <limits>
#include <vector>

namespace ccmd {

CCMD_POPCNT_CLONES Descriptor MedoidDescriptor(const std::vector<Descriptor>& descriptors) {
  const std::size_t n = descriptors.size();
  std::size_t best = 0;
  int best_sum = std::numeric_limits<int>::max();
  for (std::size_t i = 0; i < n; ++i) {
    int sum = 0;
    for (std::size_t j = 0; j < n && sum < best_sum; ++j) {
      if (i != j) sum += HammingDistance(descriptors[i], descriptors[j]);
    }
    if (sum < best_sum) {
      best_sum = sum;
      best = i;
    }
  }
  return descriptors[best];
}

}  // namespace ccmd
