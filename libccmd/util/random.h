#pragma once

// Small, fast, seedable random numbers for simulation and tests. Results depend only on
// the seed (never on std::random_device or the standard library's distributions, whose
// output differs between implementations), so synthetic data is identical everywhere.

#include <cmath>
#include <cstdint>

namespace ccmd {

// splitmix64: turns any seed (including 0) into well-mixed 64-bit values.
inline std::uint64_t SplitMix64(std::uint64_t* state) {
  std::uint64_t z = (*state += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// Mixes several integers into one seed (e.g. sequence seed and frame index).
inline std::uint64_t MixSeed(std::uint64_t a, std::uint64_t b) {
  std::uint64_t state = a ^ (b * 0xD1B54A32D192ED03ull);
  return SplitMix64(&state);
}

// xoshiro256** by Blackman and Vigna.
class Rng {
 public:
  explicit Rng(std::uint64_t seed = 1) {
    std::uint64_t state = seed;
    for (auto& word : s_) word = SplitMix64(&state);
  }

  std::uint64_t Next() {
    const std::uint64_t result = Rotl(s_[1] * 5, 7) * 9;
    const std::uint64_t t = s_[1] << 17;
    s_[2] ^= s_[0];
    s_[3] ^= s_[1];
    s_[1] ^= s_[2];
    s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = Rotl(s_[3], 45);
    return result;
  }

  // Uniform in [0, 1).
  double Uniform() { return (Next() >> 11) * 0x1.0p-53; }
  double Uniform(double lo, double hi) { return lo + (hi - lo) * Uniform(); }
  // Uniform integer in [lo, hi] (inclusive).
  int UniformInt(int lo, int hi) {
    return lo + static_cast<int>(Uniform() * (static_cast<double>(hi) - lo + 1.0));
  }
  bool Bernoulli(double p) { return Uniform() < p; }

  // Standard normal (Box-Muller; the second value is cached).
  double Normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    double u1 = Uniform();
    while (u1 <= 1e-300) u1 = Uniform();
    const double u2 = Uniform();
    const double r = std::sqrt(-2.0 * std::log(u1));
    spare_ = r * std::sin(2.0 * M_PI * u2);
    has_spare_ = true;
    return r * std::cos(2.0 * M_PI * u2);
  }
  double Normal(double mean, double sigma) { return mean + sigma * Normal(); }

 private:
  static std::uint64_t Rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  std::uint64_t s_[4];
  double spare_ = 0.0;
  bool has_spare_ = false;
};

}  // namespace ccmd
