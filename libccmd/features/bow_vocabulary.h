#pragma once

// A vocabulary tree over 256-bit ORB descriptors for place recognition (the bag-of-words
// scheme of Nister and Stewenius 2006 for binary features, as DBoW2 uses it; written here
// from the published description).
//
// Training clusters the descriptors hierarchically: the root's descriptors are split into at
// most `branching` clusters by k-medians (k-means++ seeding with a fixed seed; Hamming
// distance; a centroid is the bitwise majority of its members), then every cluster is split
// again, down to `depth` levels. The leaves are the words. Each word carries an inverse
// document frequency weight idf = log(N / n_w) counted over the N training images (n_w of
// them contain the word), so words seen everywhere weigh little.
//
// Transform walks each descriptor down the tree (nearest child at every level) to its word
// and builds the image's TF-IDF vector, L1-normalised for the L1 score (bow_vector.h).
//
// Thread safety: a Vocabulary is immutable after Train/Load except for SetIdfFrom; its const
// methods may be called from any number of threads at once. To replace the vocabulary a
// running system uses, build a new one and swap a shared_ptr.

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/bow_vector.h"
#include "libccmd/features/descriptor.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct VocabularyOptions {
  int branching = 10;  // k: children per node
  // L: levels below the root (up to k^L words). 5 rather than DBoW2's 6: as good on
  // synthetic revisits and better on real images (docs/place_recognition.md).
  int depth = 5;
  int max_iterations = 12;  // k-medians rounds per node (stops earlier once assignments settle)
  std::uint64_t seed = 1;   // k-means++ seeding; the same seed and data give the same tree
  int threads = 1;          // nodes of one level are clustered in parallel (same result)

  // Empty string when valid, else the reason.
  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct VocabularyStats {
  int images = 0;               // training images (documents for the IDF)
  std::size_t descriptors = 0;  // descriptors clustered
  int nodes = 0;
  int words = 0;
  double seconds = 0;  // wall time of the training
};

class Vocabulary {
 public:
  static constexpr std::uint32_t kFormatVersion = 1;
  // Bounds a file must respect (checked before anything is allocated from its header).
  static constexpr int kMaxBranching = 64;
  static constexpr int kMaxDepth = 16;
  static constexpr std::uint32_t kMaxNodes = 1u << 25;
  // Level of the direct index when callers have no reason to choose another: with k = 10,
  // about 100 nodes, each holding the features that are worth comparing (ORB-SLAM's choice
  // of 4 levels up from the leaves of a 6-level tree).
  static constexpr int kDefaultDirectIndexLevel = 2;

  Vocabulary() = default;

  // Trains on the descriptors of a set of images: each matrix is one image's descriptors
  // (N x 32, CV_8U; empty matrices count as images without features). InvalidArgument for
  // bad options or matrices, or when there are no descriptors at all.
  static StatusOr<Vocabulary> Train(std::span<const cv::Mat> images,
                                    const VocabularyOptions& options,
                                    VocabularyStats* stats = nullptr);

  bool empty() const { return weights_.empty(); }
  int branching() const { return branching_; }
  int depth() const { return depth_; }
  int node_count() const { return static_cast<int>(parent_.size()); }
  int word_count() const { return static_cast<int>(weights_.size()); }
  int training_images() const { return training_images_; }

  // The word of one descriptor (32 bytes). Precondition: !empty().
  WordId WordOf(const std::uint8_t* descriptor) const;
  WordId WordOf(const Descriptor& descriptor) const { return WordOf(descriptor.data()); }
  // Also the node passed through at `level` (0 = root; the leaf itself if the path ends
  // above that level).
  WordId WordOf(const std::uint8_t* descriptor, int level, NodeId* node_at_level) const;

  // IDF weight of a word (0 for words present in every training image).
  double Weight(WordId word) const { return weights_[word]; }

  // The L1-normalised TF-IDF vector of one image's descriptors (N x 32, CV_8U). Words of
  // weight 0 are left out. Precondition: !empty() and the matrix has that layout.
  BowVector Transform(const cv::Mat& descriptors) const;
  // Also the direct index: features grouped by their node at `direct_index_level`.
  BowVector Transform(const cv::Mat& descriptors, int direct_index_level,
                      FeatureVector* features) const;

  // Recounts the IDF weights over `images` (tree unchanged): adapts a vocabulary trained
  // elsewhere to the images of a new environment at the cost of one transform per feature.
  Status SetIdfFrom(std::span<const cv::Mat> images);

  // Versioned binary form (see bow_vocabulary.cc for the layout) and files holding it.
  std::vector<std::uint8_t> Serialize() const;
  // kCorrupt for anything malformed (bad magic, CRC, truncation, inconsistent tree),
  // kUnsupported for another format version. Never aborts on bad input.
  static StatusOr<Vocabulary> Deserialize(std::span<const std::uint8_t> bytes);
  Status Save(const std::string& path) const;  // atomic: readers never see a partial file
  static StatusOr<Vocabulary> Load(const std::string& path);

  // CRC32C of the serialised form: identifies a vocabulary (BoW vectors of two different
  // vocabularies must never be compared).
  std::uint32_t Fingerprint() const;

  // Tree inspection (tests, statistics).
  NodeId Parent(NodeId node) const { return parent_[node]; }
  int Level(NodeId node) const { return level_[node]; }
  bool IsLeaf(NodeId node) const { return child_count_[node] == 0; }
  const Descriptor& NodeDescriptor(NodeId node) const { return descriptors_[node]; }
  NodeId NodeOfWord(WordId word) const { return node_of_word_[word]; }

 private:
  // Fills first_child_, child_count_, level_ and the word <-> leaf maps from parent_.
  // Precondition: parents precede their children, children of a node are contiguous.
  void Index();
  // Word of every descriptor of an image (rows of an N x 32 CV_8U matrix).
  void Words(const cv::Mat& descriptors, std::vector<WordId>* words) const;

  int branching_ = 0;
  int depth_ = 0;
  int training_images_ = 0;
  std::vector<NodeId> parent_;           // per node; the root's parent is 0
  std::vector<Descriptor> descriptors_;  // per node; the root's is unused (zero)
  std::vector<NodeId> first_child_;
  std::vector<std::uint8_t> child_count_;
  std::vector<std::uint8_t> level_;
  std::vector<WordId> word_of_node_;  // kNoWord for inner nodes
  std::vector<NodeId> node_of_word_;
  std::vector<float> weights_;  // IDF per word
};

}  // namespace ccmd
