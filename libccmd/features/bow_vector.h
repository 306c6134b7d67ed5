#pragma once

// Bag-of-words vectors of an image and the L1 similarity score between two of them, plus the
// "feature vector" (direct index) that groups an image's features by vocabulary node for
// guided matching. Produced by Vocabulary::Transform (bow_vocabulary.h).

#include <cstdint>
#include <utility>
#include <vector>

namespace ccmd {

// Words are the leaves of a vocabulary tree, numbered 0..word_count-1; nodes are all tree
// nodes (root = 0). Both are indices into one vocabulary and mean nothing without it.
using WordId = std::uint32_t;
using NodeId = std::uint32_t;

struct BowEntry {
  WordId word = 0;
  double weight = 0;
  bool operator==(const BowEntry&) const = default;
};

// A sparse vector of positive word weights, sorted by word, one entry per word.
class BowVector {
 public:
  BowVector() = default;

  // From (word, weight) pairs in any order: weights of the same word are summed, and entries
  // whose weight is not positive are dropped (TF-IDF weights are never negative).
  static BowVector FromEntries(std::vector<BowEntry> entries);

  const std::vector<BowEntry>& entries() const { return entries_; }
  std::size_t size() const { return entries_.size(); }
  bool empty() const { return entries_.empty(); }

  // Weight of `word`, 0 when absent.
  double Weight(WordId word) const;
  double L1Norm() const;
  // Scales the weights to sum to 1 (nothing to do for an empty vector).
  void NormalizeL1();

  bool operator==(const BowVector&) const = default;

 private:
  std::vector<BowEntry> entries_;
};

// The L1 score of DBoW2 (Nister and Stewenius 2006; Galvez-Lopez and Tardos 2012):
//   s(a, b) = 1 - 1/2 * | a/|a|_1 - b/|b|_1 |_1,
// 1 for identical word distributions, 0 when no word is shared or either vector is empty.
// With positive weights it equals the sum over shared words of min(a_i/|a|, b_i/|b|), which
// is how it is computed (only shared words are visited).
double L1Score(const BowVector& a, const BowVector& b);

// Direct index of one image: for each vocabulary node at a chosen level (see
// Vocabulary::Transform), the indices of the image's features whose path passes through it.
// Two images' features need only be compared within the same node.
class FeatureVector {
 public:
  using Group = std::pair<NodeId, std::vector<int>>;

  FeatureVector() = default;
  // `node_of_feature[i]` is the node of feature i.
  static FeatureVector FromAssignments(const std::vector<NodeId>& node_of_feature);

  // Sorted by node; features in each group in increasing index order.
  const std::vector<Group>& groups() const { return groups_; }
  std::size_t size() const { return groups_.size(); }
  bool empty() const { return groups_.empty(); }
  // Features of `node` (empty when none).
  const std::vector<int>& Features(NodeId node) const;

 private:
  std::vector<Group> groups_;
};

}  // namespace ccmd
