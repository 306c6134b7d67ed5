#include "libccmd/features/bow_vocabulary.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstring>
#include <thread>

#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"
#include "proto/byte_io.h"
#include "proto/crc32c.h"

// File layout (little-endian), format version 1:
//   offset 0   8 bytes  magic "CCMDVOC\0"
//          8   u32      format version (1)
//         12   u32      branching k
//         16   u32      depth L
//         20   u32      node count (root included)
//         24   u32      word count (= leaves)
//         28   u32      training images (N of the IDF)
//         32   u32      weighting (1 = TF-IDF)
//         36   u32      scoring (1 = L1)
//         40   nodes 1..count-1 in breadth-first order: u32 parent, 32 bytes descriptor
//              (a parent precedes its children; children of one node are consecutive)
//              word weights: f32 per word; words are the leaves in node order
//         end  u32      CRC32C of every byte before it
// The tree is fully determined by the parents, so a reader checks them instead of trusting
// separate child lists.

namespace ccmd {
namespace {

// The hot loops are compiled with and without popcnt (CCMD_POPCNT_CLONES, descriptor.h):
// 7-10x faster training and transforms where the CPU has it.

constexpr WordId kNoWord = 0xFFFFFFFFu;
constexpr char kMagic[8] = {'C', 'C', 'M', 'D', 'V', 'O', 'C', '\0'};
constexpr std::size_t kHeaderSize = 40;
constexpr std::size_t kNodeRecordSize = 4 + 32;
constexpr std::uint32_t kWeightingTfIdf = 1;
constexpr std::uint32_t kScoringL1 = 1;

struct Cluster {
  Descriptor centroid;
  std::vector<std::uint32_t> members;
};

// Bitwise majority of the members (a bit is set when more than half of them have it): the
// centroid that minimises the summed Hamming distance bit by bit. Bits are counted eight at
// a time, one byte lane per bit, so that a descriptor costs 32 additions.
Descriptor Majority(const std::vector<Descriptor>& all, const std::vector<std::uint32_t>& members) {
  static const std::array<std::uint64_t, 256> kSpread = [] {
    std::array<std::uint64_t, 256> table{};
    for (int v = 0; v < 256; ++v) {
      for (int bit = 0; bit < 8; ++bit) {
        if ((v >> bit) & 1) table[v] |= std::uint64_t{1} << (8 * bit);
      }
    }
    return table;
  }();
  std::array<std::uint32_t, 256> ones{};
  std::array<std::uint64_t, 32> lanes{};
  int pending = 0;
  auto flush = [&] {
    for (int b = 0; b < 32; ++b) {
      for (int bit = 0; bit < 8; ++bit) ones[b * 8 + bit] += (lanes[b] >> (8 * bit)) & 0xFF;
      lanes[b] = 0;
    }
    pending = 0;
  };
  for (std::uint32_t index : members) {
    const Descriptor& d = all[index];
    for (int b = 0; b < 32; ++b) lanes[b] += kSpread[d[b]];
    if (++pending == 255) flush();  // a byte lane holds at most 255
  }
  flush();
  Descriptor centroid{};
  const std::size_t n = members.size();
  for (int i = 0; i < 256; ++i) {
    if (2 * static_cast<std::size_t>(ones[i]) > n) {
      centroid[i / 8] |= static_cast<std::uint8_t>(1u << (i % 8));
    }
  }
  return centroid;
}

// Splits `members` into at most k clusters. Fewer when there are fewer distinct descriptors;
// a single cluster means the node cannot be split.
CCMD_POPCNT_CLONES std::vector<Cluster> ClusterNode(const std::vector<Descriptor>& all,
                                                    const std::vector<std::uint32_t>& members,
                                                    int k, int max_iterations, std::uint64_t seed) {
  std::vector<Cluster> clusters;
  const std::size_t n = members.size();
  if (n <= static_cast<std::size_t>(k)) {
    // Each distinct descriptor is its own cluster.
    std::vector<std::uint32_t> sorted = members;
    std::stable_sort(sorted.begin(), sorted.end(),
                     [&](std::uint32_t a, std::uint32_t b) { return all[a] < all[b]; });
    for (std::uint32_t index : sorted) {
      if (clusters.empty() || clusters.back().centroid != all[index]) {
        clusters.push_back({all[index], {}});
      }
      clusters.back().members.push_back(index);
    }
    return clusters;
  }

  // k-means++ seeding: each next centre is drawn with probability proportional to the
  // squared distance to the nearest centre chosen so far.
  Rng rng(seed);
  std::vector<Descriptor> centers;
  centers.reserve(k);
  centers.push_back(all[members[rng.UniformInt(0, static_cast<int>(n) - 1)]]);
  std::vector<double> dist2(n);
  for (std::size_t i = 0; i < n; ++i) {
    const double d = HammingDistance(all[members[i]], centers[0]);
    dist2[i] = d * d;
  }
  while (static_cast<int>(centers.size()) < k) {
    double total = 0;
    for (double d : dist2) total += d;
    if (total <= 0) break;  // every descriptor coincides with a centre
    const double target = rng.Uniform() * total;
    double cumulative = 0;
    std::size_t pick = n;
    for (std::size_t i = 0; i < n; ++i) {
      if (dist2[i] <= 0) continue;
      cumulative += dist2[i];
      pick = i;
      if (cumulative > target) break;
    }
    centers.push_back(all[members[pick]]);
    for (std::size_t i = 0; i < n; ++i) {
      const double d = HammingDistance(all[members[i]], centers.back());
      dist2[i] = std::min(dist2[i], d * d);
    }
  }

  // Lloyd rounds with the Hamming distance and majority centroids, until no descriptor
  // changes cluster. The last step is always an assignment, so members and centres agree.
  const int c = static_cast<int>(centers.size());
  std::vector<int> assignment(n, -1);
  std::vector<std::vector<std::uint32_t>> groups(c);
  for (int iteration = 0;; ++iteration) {
    bool changed = false;
    for (auto& g : groups) g.clear();
    for (std::size_t i = 0; i < n; ++i) {
      const Descriptor& d = all[members[i]];
      int best = 0, best_distance = HammingDistance(d, centers[0]);
      for (int j = 1; j < c; ++j) {
        const int distance = HammingDistance(d, centers[j]);
        if (distance < best_distance) {
          best_distance = distance;
          best = j;
        }
      }
      changed |= assignment[i] != best;
      assignment[i] = best;
      groups[best].push_back(members[i]);
    }
    if (!changed || iteration >= max_iterations) break;
    for (int j = 0; j < c; ++j) {
      if (!groups[j].empty()) centers[j] = Majority(all, groups[j]);
    }
  }
  for (int j = 0; j < c; ++j) {
    if (!groups[j].empty()) clusters.push_back({centers[j], std::move(groups[j])});
  }
  return clusters;
}

Status CheckDescriptorMatrix(const cv::Mat& m, std::size_t index) {
  if (m.empty()) return Status::Ok();
  if (m.type() != CV_8UC1 || m.cols != 32) {
    return InvalidArgument("descriptor matrix " + std::to_string(index) +
                           " is not N x 32 CV_8U (ORB)");
  }
  return Status::Ok();
}

// Walks a descriptor from the root to its leaf (nearest child at every level; ties to the
// first child). `*node_at_level`, if given, receives the node passed at `level` (the leaf
// if the path ends above it).
CCMD_POPCNT_CLONES NodeId Descend(const NodeId* first_child, const std::uint8_t* child_count,
                                  const Descriptor* nodes, const std::uint8_t* levels,
                                  const std::uint8_t* descriptor, int level,
                                  NodeId* node_at_level) {
  NodeId node = 0;
  if (node_at_level) *node_at_level = 0;
  while (child_count[node] > 0) {
    if (node_at_level && levels[node] == level) *node_at_level = node;
    const NodeId first = first_child[node];
    const NodeId end = first + child_count[node];
    NodeId best = first;
    int best_distance = HammingDistance(nodes[first].data(), descriptor);
    for (NodeId c = first + 1; c < end; ++c) {
      const int distance = HammingDistance(nodes[c].data(), descriptor);
      if (distance < best_distance) {
        best_distance = distance;
        best = c;
      }
    }
    node = best;
  }
  if (node_at_level && levels[node] <= level) *node_at_level = node;
  return node;
}

template <typename Fn>
void ParallelFor(int count, int threads, Fn&& fn) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  threads = std::min(threads, count);
  if (threads <= 1) {
    for (int i = 0; i < count; ++i) fn(i);
    return;
  }
  std::atomic<int> next{0};
  std::vector<std::thread> workers;
  for (int t = 0; t < threads; ++t) {
    workers.emplace_back([&] {
      for (int i = next++; i < count; i = next++) fn(i);
    });
  }
  for (auto& w : workers) w.join();
}

}  // namespace

Status VocabularyOptions::Validate() const {
  if (branching < 2 || branching > Vocabulary::kMaxBranching) {
    return InvalidArgument("branching must be in [2, " + std::to_string(Vocabulary::kMaxBranching) +
                           "]");
  }
  if (depth < 1 || depth > Vocabulary::kMaxDepth) {
    return InvalidArgument("depth must be in [1, " + std::to_string(Vocabulary::kMaxDepth) + "]");
  }
  if (max_iterations < 1) return InvalidArgument("max_iterations must be at least 1");
  if (threads < 0) return InvalidArgument("threads must be >= 0 (0: all cores)");
  return Status::Ok();
}

void VocabularyOptions::Describe(OptionsWriter* out) const {
  out->Add("branching", branching);
  out->Add("depth", depth);
  out->Add("max_iterations", max_iterations);
  out->Add("seed", seed);
  out->Add("threads", threads);
}

StatusOr<Vocabulary> Vocabulary::Train(std::span<const cv::Mat> images,
                                       const VocabularyOptions& options, VocabularyStats* stats) {
  const Stopwatch watch;
  CCMD_RETURN_IF_ERROR(options.Validate().WithContext("vocabulary options"));
  std::vector<Descriptor> all;
  for (std::size_t i = 0; i < images.size(); ++i) {
    CCMD_RETURN_IF_ERROR(CheckDescriptorMatrix(images[i], i));
    for (int r = 0; r < images[i].rows; ++r) all.push_back(DescriptorRow(images[i], r));
  }
  if (all.empty()) return InvalidArgument("no descriptors to train a vocabulary on");
  if (all.size() >= kMaxNodes / static_cast<std::size_t>(options.depth)) {
    return OutOfRange("too many descriptors (" + std::to_string(all.size()) +
                      ") for one vocabulary; subsample them");
  }

  Vocabulary v;
  v.branching_ = options.branching;
  v.depth_ = options.depth;
  v.parent_.push_back(0);
  v.descriptors_.push_back(Descriptor{});

  // Breadth-first, one level at a time: node ids grow level by level and children of one
  // node are consecutive. Each node's clustering is seeded by its id, so the tree does not
  // depend on the thread count.
  std::vector<NodeId> level_nodes = {0};
  std::vector<std::vector<std::uint32_t>> level_members(1);
  level_members[0].resize(all.size());
  for (std::size_t i = 0; i < all.size(); ++i) level_members[0][i] = static_cast<std::uint32_t>(i);
  for (int level = 0; level < options.depth && !level_nodes.empty(); ++level) {
    std::vector<std::vector<Cluster>> clusters(level_nodes.size());
    ParallelFor(static_cast<int>(level_nodes.size()), options.threads, [&](int i) {
      if (level_members[i].size() < 2) return;  // one descriptor: a leaf
      clusters[i] = ClusterNode(all, level_members[i], options.branching, options.max_iterations,
                                MixSeed(options.seed, level_nodes[i]));
      if (clusters[i].size() < 2) clusters[i].clear();  // identical descriptors: a leaf
    });
    std::vector<NodeId> next_nodes;
    std::vector<std::vector<std::uint32_t>> next_members;
    for (std::size_t i = 0; i < level_nodes.size(); ++i) {
      for (Cluster& cluster : clusters[i]) {
        next_nodes.push_back(static_cast<NodeId>(v.parent_.size()));
        v.parent_.push_back(level_nodes[i]);
        v.descriptors_.push_back(cluster.centroid);
        next_members.push_back(std::move(cluster.members));
      }
    }
    level_nodes = std::move(next_nodes);
    level_members = std::move(next_members);
  }
  v.Index();
  CCMD_RETURN_IF_ERROR(v.SetIdfFrom(images));
  if (stats) {
    stats->images = static_cast<int>(images.size());
    stats->descriptors = all.size();
    stats->nodes = v.node_count();
    stats->words = v.word_count();
    stats->seconds = watch.ElapsedSeconds();
  }
  return v;
}

void Vocabulary::Index() {
  const std::size_t n = parent_.size();
  first_child_.assign(n, 0);
  child_count_.assign(n, 0);
  level_.assign(n, 0);
  for (std::size_t i = 1; i < n; ++i) {
    const NodeId p = parent_[i];
    if (child_count_[p] == 0) first_child_[p] = static_cast<NodeId>(i);
    ++child_count_[p];
    level_[i] = static_cast<std::uint8_t>(level_[p] + 1);
  }
  word_of_node_.assign(n, kNoWord);
  node_of_word_.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (child_count_[i] == 0) {
      word_of_node_[i] = static_cast<WordId>(node_of_word_.size());
      node_of_word_.push_back(static_cast<NodeId>(i));
    }
  }
  weights_.assign(node_of_word_.size(), 0.0f);
}

WordId Vocabulary::WordOf(const std::uint8_t* descriptor) const {
  return word_of_node_[Descend(first_child_.data(), child_count_.data(), descriptors_.data(),
                               level_.data(), descriptor, 0, nullptr)];
}

WordId Vocabulary::WordOf(const std::uint8_t* descriptor, int level, NodeId* node_at_level) const {
  return word_of_node_[Descend(first_child_.data(), child_count_.data(), descriptors_.data(),
                               level_.data(), descriptor, level, node_at_level)];
}

void Vocabulary::Words(const cv::Mat& descriptors, std::vector<WordId>* words) const {
  words->resize(descriptors.rows);
  for (int r = 0; r < descriptors.rows; ++r) {
    (*words)[r] = WordOf(descriptors.ptr<std::uint8_t>(r));
  }
}

BowVector Vocabulary::Transform(const cv::Mat& descriptors) const {
  CCMD_CHECK(!empty()) << "Transform on an empty vocabulary";
  CCMD_CHECK(CheckDescriptorMatrix(descriptors, 0).ok()) << "descriptors must be N x 32 CV_8U";
  std::vector<BowEntry> entries;
  entries.reserve(descriptors.rows);
  for (int r = 0; r < descriptors.rows; ++r) {
    const WordId word = WordOf(descriptors.ptr<std::uint8_t>(r));
    if (weights_[word] > 0) entries.push_back({word, weights_[word]});
  }
  BowVector bow = BowVector::FromEntries(std::move(entries));
  bow.NormalizeL1();
  return bow;
}

BowVector Vocabulary::Transform(const cv::Mat& descriptors, int direct_index_level,
                                FeatureVector* features) const {
  CCMD_CHECK(!empty()) << "Transform on an empty vocabulary";
  CCMD_CHECK(CheckDescriptorMatrix(descriptors, 0).ok()) << "descriptors must be N x 32 CV_8U";
  std::vector<BowEntry> entries;
  entries.reserve(descriptors.rows);
  std::vector<NodeId> nodes(descriptors.rows);
  for (int r = 0; r < descriptors.rows; ++r) {
    const WordId word = WordOf(descriptors.ptr<std::uint8_t>(r), direct_index_level, &nodes[r]);
    if (weights_[word] > 0) entries.push_back({word, weights_[word]});
  }
  if (features) *features = FeatureVector::FromAssignments(nodes);
  BowVector bow = BowVector::FromEntries(std::move(entries));
  bow.NormalizeL1();
  return bow;
}

Status Vocabulary::SetIdfFrom(std::span<const cv::Mat> images) {
  if (parent_.empty()) return InvalidArgument("vocabulary has no tree");
  if (images.empty()) return InvalidArgument("no images to count word frequencies over");
  for (std::size_t i = 0; i < images.size(); ++i) {
    CCMD_RETURN_IF_ERROR(CheckDescriptorMatrix(images[i], i));
  }
  const std::size_t words = node_of_word_.size();
  std::vector<std::uint32_t> documents(words, 0);
  std::vector<std::uint32_t> last_image(words, 0);  // image index + 1 that last counted a word
  std::vector<WordId> image_words;
  for (std::size_t i = 0; i < images.size(); ++i) {
    Words(images[i], &image_words);
    for (WordId w : image_words) {
      if (last_image[w] != i + 1) {
        last_image[w] = static_cast<std::uint32_t>(i + 1);
        ++documents[w];
      }
    }
  }
  const double n = static_cast<double>(images.size());
  // A word no training image reaches is as rare as can be: weighted as if seen once.
  for (std::size_t w = 0; w < words; ++w) {
    weights_[w] = static_cast<float>(std::log(n / std::max<std::uint32_t>(documents[w], 1)));
  }
  training_images_ = static_cast<int>(images.size());
  return Status::Ok();
}

std::vector<std::uint8_t> Vocabulary::Serialize() const {
  ByteWriter w(kHeaderSize + (parent_.size() - 1) * kNodeRecordSize + weights_.size() * 4 + 4);
  w.PutBytes(kMagic, sizeof(kMagic));
  w.PutU32(kFormatVersion);
  w.PutU32(static_cast<std::uint32_t>(branching_));
  w.PutU32(static_cast<std::uint32_t>(depth_));
  w.PutU32(static_cast<std::uint32_t>(parent_.size()));
  w.PutU32(static_cast<std::uint32_t>(weights_.size()));
  w.PutU32(static_cast<std::uint32_t>(training_images_));
  w.PutU32(kWeightingTfIdf);
  w.PutU32(kScoringL1);
  for (std::size_t i = 1; i < parent_.size(); ++i) {
    w.PutU32(parent_[i]);
    w.PutBytes(descriptors_[i].data(), 32);
  }
  for (float weight : weights_) w.PutF32(weight);
  w.PutU32(Crc32c(w.bytes()));
  return w.Take();
}

std::uint32_t Vocabulary::Fingerprint() const {
  const std::vector<std::uint8_t> bytes = Serialize();
  return Crc32c(bytes.data(), bytes.size() - 4);  // the CRC the file stores
}

StatusOr<Vocabulary> Vocabulary::Deserialize(std::span<const std::uint8_t> bytes) {
  if (bytes.size() < kHeaderSize + 4) {
    return Corrupt("vocabulary truncated: " + std::to_string(bytes.size()) + " bytes");
  }
  if (std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    return Corrupt("not a CCMD vocabulary (bad magic)");
  }
  ByteReader header(bytes.subspan(sizeof(kMagic), kHeaderSize - sizeof(kMagic)));
  std::uint32_t version, branching, depth, nodes, words, images, weighting, scoring;
  CCMD_RETURN_IF_ERROR(header.ReadU32(&version));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&branching));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&depth));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&nodes));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&words));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&images));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&weighting));
  CCMD_RETURN_IF_ERROR(header.ReadU32(&scoring));
  if (version != kFormatVersion) {
    return Unsupported("vocabulary format version " + std::to_string(version) +
                       " (this build reads " + std::to_string(kFormatVersion) + ")");
  }
  std::uint32_t stored_crc;
  ByteReader crc_reader(bytes.subspan(bytes.size() - 4));
  CCMD_RETURN_IF_ERROR(crc_reader.ReadU32(&stored_crc));
  if (Crc32c(bytes.data(), bytes.size() - 4) != stored_crc) {
    return Corrupt("vocabulary CRC mismatch (file damaged or truncated)");
  }
  if (weighting != kWeightingTfIdf || scoring != kScoringL1) {
    return Unsupported("vocabulary weighting/scoring " + std::to_string(weighting) + "/" +
                       std::to_string(scoring) + " (only TF-IDF with L1 is known)");
  }
  if (branching < 2 || branching > static_cast<std::uint32_t>(kMaxBranching) || depth < 1 ||
      depth > static_cast<std::uint32_t>(kMaxDepth)) {
    return Corrupt("vocabulary branching " + std::to_string(branching) + " / depth " +
                   std::to_string(depth) + " out of range");
  }
  if (nodes < 1 || nodes > kMaxNodes || words < 1 || words > nodes || images < 1) {
    return Corrupt("vocabulary counts out of range: " + std::to_string(nodes) + " nodes, " +
                   std::to_string(words) + " words, " + std::to_string(images) + " images");
  }
  const std::uint64_t expected =
      kHeaderSize + std::uint64_t{nodes - 1} * kNodeRecordSize + std::uint64_t{words} * 4 + 4;
  if (bytes.size() != expected) {
    return Corrupt("vocabulary size " + std::to_string(bytes.size()) + " bytes, header says " +
                   std::to_string(expected));
  }

  // Sizes are now bounded by the (already present) byte count.
  Vocabulary v;
  v.branching_ = static_cast<int>(branching);
  v.depth_ = static_cast<int>(depth);
  v.training_images_ = static_cast<int>(images);
  v.parent_.resize(nodes);
  v.descriptors_.resize(nodes);
  std::vector<std::uint32_t> children(nodes, 0);
  std::vector<std::uint8_t> level(nodes, 0);
  ByteReader r(bytes.subspan(kHeaderSize, bytes.size() - kHeaderSize - 4));
  for (std::uint32_t i = 1; i < nodes; ++i) {
    std::uint32_t parent;
    CCMD_RETURN_IF_ERROR(r.ReadU32(&parent));
    CCMD_RETURN_IF_ERROR(r.ReadBytes(32, v.descriptors_[i].data()));
    if (parent >= i || (i > 1 && parent < v.parent_[i - 1])) {
      return Corrupt("vocabulary node " + std::to_string(i) + ": parent " + std::to_string(parent) +
                     " out of order");
    }
    if (++children[parent] > branching) {
      return Corrupt("vocabulary node " + std::to_string(parent) + " has more than " +
                     std::to_string(branching) + " children");
    }
    level[i] = static_cast<std::uint8_t>(level[parent] + 1);
    if (level[i] > depth) {
      return Corrupt("vocabulary node " + std::to_string(i) + " deeper than " +
                     std::to_string(depth) + " levels");
    }
    v.parent_[i] = parent;
  }
  const auto leaves = static_cast<std::uint32_t>(std::count(children.begin(), children.end(), 0u));
  if (leaves != words) {
    return Corrupt("vocabulary has " + std::to_string(leaves) + " leaves but " +
                   std::to_string(words) + " word weights");
  }
  v.Index();
  for (std::uint32_t w = 0; w < words; ++w) {
    float weight;
    CCMD_RETURN_IF_ERROR(r.ReadF32(&weight));
    if (!std::isfinite(weight) || weight < 0) {
      return Corrupt("vocabulary word " + std::to_string(w) + " has weight " +
                     std::to_string(weight));
    }
    v.weights_[w] = weight;
  }
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  return v;
}

Status Vocabulary::Save(const std::string& path) const {
  if (empty()) return InvalidArgument("saving an empty vocabulary");
  const std::vector<std::uint8_t> bytes = Serialize();
  return WriteFileAtomic(
             path, std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()))
      .WithContext("writing vocabulary " + path);
}

StatusOr<Vocabulary> Vocabulary::Load(const std::string& path) {
  constexpr std::uint64_t kMaxBytes =
      kHeaderSize + std::uint64_t{kMaxNodes} * (kNodeRecordSize + 4) + 4;
  auto data = ReadFileToString(path, kMaxBytes);
  if (!data.ok()) return data.status().WithContext("reading vocabulary " + path);
  auto v = Deserialize(std::span<const std::uint8_t>(
      reinterpret_cast<const std::uint8_t*>(data->data()), data->size()));
  if (!v.ok()) return v.status().WithContext("vocabulary " + path);
  return v;
}

}  // namespace ccmd
