#include "libccmd/features/bow_vector.h"

#include <algorithm>

namespace ccmd {

BowVector BowVector::FromEntries(std::vector<BowEntry> entries) {
  std::sort(entries.begin(), entries.end(),
            [](const BowEntry& a, const BowEntry& b) { return a.word < b.word; });
  BowVector v;
  v.entries_.reserve(entries.size());
  for (std::size_t i = 0; i < entries.size();) {
    double sum = 0;
    std::size_t j = i;
    for (; j < entries.size() && entries[j].word == entries[i].word; ++j) sum += entries[j].weight;
    if (sum > 0) v.entries_.push_back({entries[i].word, sum});
    i = j;
  }
  return v;
}

double BowVector::Weight(WordId word) const {
  auto it = std::lower_bound(entries_.begin(), entries_.end(), word,
                             [](const BowEntry& e, WordId w) { return e.word < w; });
  return it != entries_.end() && it->word == word ? it->weight : 0.0;
}

double BowVector::L1Norm() const {
  double sum = 0;
  for (const BowEntry& e : entries_) sum += e.weight;
  return sum;
}

void BowVector::NormalizeL1() {
  const double norm = L1Norm();
  if (norm <= 0) return;
  for (BowEntry& e : entries_) e.weight /= norm;
}

double L1Score(const BowVector& a, const BowVector& b) {
  const double norm_a = a.L1Norm(), norm_b = b.L1Norm();
  if (norm_a <= 0 || norm_b <= 0) return 0.0;
  const auto& x = a.entries();
  const auto& y = b.entries();
  double score = 0;
  std::size_t i = 0, j = 0;
  while (i < x.size() && j < y.size()) {
    if (x[i].word < y[j].word) {
      ++i;
    } else if (y[j].word < x[i].word) {
      ++j;
    } else {
      score += std::min(x[i].weight / norm_a, y[j].weight / norm_b);
      ++i;
      ++j;
    }
  }
  return std::min(score, 1.0);  // rounding can exceed 1 by an ulp for identical vectors
}

FeatureVector FeatureVector::FromAssignments(const std::vector<NodeId>& node_of_feature) {
  std::vector<std::pair<NodeId, int>> pairs;
  pairs.reserve(node_of_feature.size());
  for (std::size_t i = 0; i < node_of_feature.size(); ++i) {
    pairs.emplace_back(node_of_feature[i], static_cast<int>(i));
  }
  std::sort(pairs.begin(), pairs.end());
  FeatureVector fv;
  for (const auto& [node, feature] : pairs) {
    if (fv.groups_.empty() || fv.groups_.back().first != node) fv.groups_.push_back({node, {}});
    fv.groups_.back().second.push_back(feature);
  }
  return fv;
}

const std::vector<int>& FeatureVector::Features(NodeId node) const {
  static const std::vector<int> kNone;
  auto it = std::lower_bound(groups_.begin(), groups_.end(), node,
                             [](const Group& g, NodeId n) { return g.first < n; });
  return it != groups_.end() && it->first == node ? it->second : kNone;
}

}  // namespace ccmd
