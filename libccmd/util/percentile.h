#pragma once

// The q-quantile of samples (nearest rank, q in [0, 1]); 0 for none.

#include <algorithm>
#include <cstddef>
#include <vector>

namespace ccmd {

inline double Percentile(std::vector<double> samples, double q) {
  if (samples.empty()) return 0;
  const std::size_t k =
      std::min(samples.size() - 1, static_cast<std::size_t>(q * (samples.size() - 1) + 0.5));
  std::nth_element(samples.begin(), samples.begin() + k, samples.end());
  return samples[k];
}

}  // namespace ccmd
