#include "libccmd/features/bow_vocabulary.h"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <set>

#include "libccmd/util/random.h"
#include "proto/crc32c.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

Descriptor RandomDescriptor(Rng& rng) {
  Descriptor d;
  for (auto& byte : d) byte = static_cast<std::uint8_t>(rng.Next());
  return d;
}

Descriptor Flip(Descriptor d, std::initializer_list<int> bits) {
  for (int bit : bits) d[bit / 8] ^= static_cast<std::uint8_t>(1u << (bit % 8));
  return d;
}

Descriptor WithBits(std::initializer_list<int> bits) { return Flip(Descriptor{}, bits); }

cv::Mat ToMat(const std::vector<Descriptor>& rows) {
  cv::Mat m(static_cast<int>(rows.size()), 32, CV_8UC1);
  for (std::size_t i = 0; i < rows.size(); ++i)
    std::memcpy(m.ptr(static_cast<int>(i)), rows[i].data(), 32);
  return m;
}

// `clusters` random centres, each with `per_cluster` members a few bits away, spread over
// `images` images.
std::vector<cv::Mat> ClusteredImages(int clusters, int per_cluster, int images,
                                     std::uint64_t seed) {
  Rng rng(seed);
  std::vector<std::vector<Descriptor>> rows(images);
  for (int c = 0; c < clusters; ++c) {
    const Descriptor centre = RandomDescriptor(rng);
    for (int i = 0; i < per_cluster; ++i) {
      rows[rng.UniformInt(0, images - 1)].push_back(
          Flip(centre, {rng.UniformInt(0, 255), rng.UniformInt(0, 255), rng.UniformInt(0, 255)}));
    }
  }
  std::vector<cv::Mat> mats;
  for (const auto& r : rows) mats.push_back(ToMat(r));
  return mats;
}

VocabularyOptions Small(int k, int depth) {
  VocabularyOptions o;
  o.branching = k;
  o.depth = depth;
  return o;
}

TEST(VocabularyTest, CentroidsAreBitwiseMajorities) {
  // Cluster A: three descriptors near zero; bit 1 is set in all three, bits 0, 2, 3 in one
  // each, so the majority is exactly {bit 1}. Cluster B: r and r with one bit flipped twice
  // over, so the majority is r. A and B are ~128 bits apart.
  Rng rng(3);
  const Descriptor r = RandomDescriptor(rng);
  const std::vector<Descriptor> rows = {WithBits({0, 1}), WithBits({1, 2}), WithBits({1, 3}), r,
                                        Flip(r, {200}),   Flip(r, {201})};
  const std::vector<cv::Mat> images = {ToMat(rows)};
  auto vocabulary = Vocabulary::Train(images, Small(2, 1));
  ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();
  ASSERT_EQ(vocabulary->word_count(), 2);
  std::set<Descriptor> centroids = {vocabulary->NodeDescriptor(vocabulary->NodeOfWord(0)),
                                    vocabulary->NodeDescriptor(vocabulary->NodeOfWord(1))};
  EXPECT_EQ(centroids, (std::set<Descriptor>{WithBits({1}), r}));
  const WordId a = vocabulary->WordOf(rows[0]);
  EXPECT_EQ(vocabulary->WordOf(rows[1]), a);
  EXPECT_EQ(vocabulary->WordOf(rows[2]), a);
  const WordId b = vocabulary->WordOf(rows[3]);
  EXPECT_NE(a, b);
  EXPECT_EQ(vocabulary->WordOf(rows[4]), b);
  EXPECT_EQ(vocabulary->WordOf(rows[5]), b);
}

TEST(VocabularyTest, IdfWeightsAndTfIdfVectorByHand) {
  Rng rng(5);
  const Descriptor a = RandomDescriptor(rng), b = RandomDescriptor(rng), c = RandomDescriptor(rng);
  // Word A is in images 1 and 4, B in 1, 2 and 3, C in 2 and 3 (N = 4).
  const std::vector<cv::Mat> images = {ToMat({a, Flip(a, {9}), b}), ToMat({b, c}),
                                       ToMat({c, Flip(b, {17})}), ToMat({a})};
  auto v = Vocabulary::Train(images, Small(3, 1));
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  ASSERT_EQ(v->word_count(), 3);
  const WordId wa = v->WordOf(a), wb = v->WordOf(b), wc = v->WordOf(c);
  EXPECT_NEAR(v->Weight(wa), std::log(4.0 / 2.0), 1e-6);
  EXPECT_NEAR(v->Weight(wb), std::log(4.0 / 3.0), 1e-6);
  EXPECT_NEAR(v->Weight(wc), std::log(4.0 / 2.0), 1e-6);
  EXPECT_EQ(v->training_images(), 4);
  // Image 1 has A twice and B once: tf-idf (2 log 2, log 4/3), L1-normalised.
  const BowVector bow = v->Transform(images[0]);
  const double wa_total = 2 * std::log(2.0), wb_total = std::log(4.0 / 3.0);
  ASSERT_EQ(bow.size(), 2u);
  EXPECT_NEAR(bow.Weight(wa), wa_total / (wa_total + wb_total), 1e-6);
  EXPECT_NEAR(bow.Weight(wb), wb_total / (wa_total + wb_total), 1e-6);
}

TEST(VocabularyTest, WordsInEveryImageWeighNothing) {
  Rng rng(6);
  const Descriptor a = RandomDescriptor(rng), b = RandomDescriptor(rng);
  const std::vector<cv::Mat> images = {ToMat({a, b}), ToMat({a}), ToMat({Flip(a, {3})})};
  auto v = Vocabulary::Train(images, Small(2, 1));
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->Weight(v->WordOf(a)), 0.0);
  const BowVector bow = v->Transform(images[0]);
  ASSERT_EQ(bow.size(), 1u);  // only b's word: a's carries no information
  EXPECT_EQ(bow.entries()[0].word, v->WordOf(b));
  EXPECT_DOUBLE_EQ(bow.entries()[0].weight, 1.0);
  EXPECT_TRUE(v->Transform(images[1]).empty());
}

TEST(VocabularyTest, TreeShapeRespectsBranchingAndDepth) {
  const auto images = ClusteredImages(40, 30, 20, 7);
  auto v = Vocabulary::Train(images, Small(4, 3));
  ASSERT_TRUE(v.ok());
  EXPECT_LE(v->word_count(), 64);
  EXPECT_GT(v->word_count(), 16);
  std::vector<int> children(v->node_count(), 0);
  for (int n = 1; n < v->node_count(); ++n) {
    ++children[v->Parent(n)];
    EXPECT_EQ(v->Level(n), v->Level(v->Parent(n)) + 1);
    EXPECT_LE(v->Level(n), 3);
  }
  for (int n = 0; n < v->node_count(); ++n) {
    EXPECT_LE(children[n], 4);
    EXPECT_EQ(children[n] == 0, v->IsLeaf(n));
  }
}

TEST(VocabularyTest, TrainingIsDeterministicAndThreadCountFree) {
  const auto images = ClusteredImages(60, 20, 10, 8);
  VocabularyOptions one = Small(5, 3), two = Small(5, 3);
  two.threads = 2;
  auto a = Vocabulary::Train(images, one), b = Vocabulary::Train(images, one),
       c = Vocabulary::Train(images, two);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  EXPECT_EQ(a->Serialize(), b->Serialize());
  EXPECT_EQ(a->Serialize(), c->Serialize());
  VocabularyOptions other = one;
  other.seed = 99;
  auto d = Vocabulary::Train(images, other);
  ASSERT_TRUE(d.ok());
  EXPECT_NE(a->Fingerprint(), d->Fingerprint());
}

TEST(VocabularyTest, DirectIndexGroupsByAncestorAtLevel) {
  const auto images = ClusteredImages(50, 20, 5, 9);
  auto v = Vocabulary::Train(images, Small(4, 4));
  ASSERT_TRUE(v.ok());
  for (int level : {1, 2, 3}) {
    FeatureVector fv;
    const BowVector bow = v->Transform(images[0], level, &fv);
    EXPECT_EQ(bow, v->Transform(images[0]));
    int features = 0;
    for (const auto& [node, indices] : fv.groups()) {
      for (int i : indices) {
        ++features;
        // Walk up from the feature's leaf: the group's node is on the path, at `level`
        // unless the path ends above it.
        NodeId n = v->NodeOfWord(v->WordOf(images[0].ptr<std::uint8_t>(i)));
        while (v->Level(n) > level) n = v->Parent(n);
        EXPECT_EQ(n, node);
      }
    }
    EXPECT_EQ(features, images[0].rows);
  }
}

TEST(VocabularyTest, SameWordsAfterSaveAndLoad) {
  const auto images = ClusteredImages(80, 25, 12, 10);
  auto v = Vocabulary::Train(images, Small(6, 3));
  ASSERT_TRUE(v.ok());
  testing::TempDir dir;
  const std::string path = dir.File("vocabulary.bin");
  ASSERT_TRUE(v->Save(path).ok());
  auto loaded = Vocabulary::Load(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
  EXPECT_EQ(loaded->word_count(), v->word_count());
  EXPECT_EQ(loaded->node_count(), v->node_count());
  EXPECT_EQ(loaded->branching(), 6);
  EXPECT_EQ(loaded->depth(), 3);
  EXPECT_EQ(loaded->Fingerprint(), v->Fingerprint());
  // Fresh descriptors (not training data) too.
  Rng rng(12);
  for (int i = 0; i < 500; ++i) {
    const Descriptor d = RandomDescriptor(rng);
    EXPECT_EQ(loaded->WordOf(d), v->WordOf(d));
  }
  for (const cv::Mat& image : images) {
    for (int r = 0; r < image.rows; ++r) {
      EXPECT_EQ(loaded->WordOf(image.ptr<std::uint8_t>(r)), v->WordOf(image.ptr<std::uint8_t>(r)));
    }
    EXPECT_EQ(loaded->Transform(image), v->Transform(image));  // weights survive exactly
  }
}

TEST(VocabularyTest, SetIdfFromRecountsWeights) {
  Rng rng(13);
  const Descriptor a = RandomDescriptor(rng), b = RandomDescriptor(rng);
  auto v = Vocabulary::Train(std::vector<cv::Mat>{ToMat({a}), ToMat({b})}, Small(2, 1));
  ASSERT_TRUE(v.ok());
  EXPECT_NEAR(v->Weight(v->WordOf(a)), std::log(2.0), 1e-6);
  // In the new environment a is everywhere and b in one image of five.
  ASSERT_TRUE(v->SetIdfFrom(std::vector<cv::Mat>{ToMat({a, b}), ToMat({a}), ToMat({a}), ToMat({a}),
                                                 ToMat({a})})
                  .ok());
  EXPECT_EQ(v->Weight(v->WordOf(a)), 0.0);
  EXPECT_NEAR(v->Weight(v->WordOf(b)), std::log(5.0), 1e-6);
  EXPECT_EQ(v->training_images(), 5);
}

TEST(VocabularyTest, BadTrainingInput) {
  EXPECT_EQ(Vocabulary::Train({}, Small(4, 2)).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(Vocabulary::Train(std::vector<cv::Mat>{cv::Mat()}, Small(4, 2)).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(
      Vocabulary::Train(std::vector<cv::Mat>{cv::Mat(3, 16, CV_8UC1)}, Small(4, 2)).status().code(),
      StatusCode::kInvalidArgument);
  EXPECT_EQ(Vocabulary::Train(ClusteredImages(3, 3, 2, 1), Small(1, 2)).status().code(),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(Vocabulary::Train(ClusteredImages(3, 3, 2, 1), Small(4, 0)).status().code(),
            StatusCode::kInvalidArgument);
}

// ---- Corrupted and truncated files --------------------------------------------------------

std::vector<std::uint8_t> SmallVocabularyBytes() {
  auto v = Vocabulary::Train(ClusteredImages(20, 10, 4, 21), Small(3, 2));
  EXPECT_TRUE(v.ok());
  return v->Serialize();
}

void PutU32(std::vector<std::uint8_t>* bytes, std::size_t offset, std::uint32_t value) {
  for (int i = 0; i < 4; ++i) (*bytes)[offset + i] = static_cast<std::uint8_t>(value >> (8 * i));
}

// Rewrites the trailing CRC so that only the structural checks can reject the bytes.
void FixCrc(std::vector<std::uint8_t>* bytes) {
  PutU32(bytes, bytes->size() - 4, Crc32c(bytes->data(), bytes->size() - 4));
}

StatusCode DecodeCode(const std::vector<std::uint8_t>& bytes) {
  return Vocabulary::Deserialize(bytes).status().code();
}

TEST(VocabularyFileTest, IntactBytesDecode) {
  const auto bytes = SmallVocabularyBytes();
  auto v = Vocabulary::Deserialize(bytes);
  ASSERT_TRUE(v.ok()) << v.status().ToString();
  EXPECT_EQ(v->Serialize(), bytes);
  EXPECT_EQ(std::string(bytes.begin(), bytes.begin() + 7), "CCMDVOC");
}

TEST(VocabularyFileTest, EveryTruncationIsAnError) {
  const auto bytes = SmallVocabularyBytes();
  for (std::size_t n = 0; n < bytes.size(); ++n) {
    const std::vector<std::uint8_t> cut(bytes.begin(), bytes.begin() + n);
    EXPECT_EQ(DecodeCode(cut), StatusCode::kCorrupt) << n;
  }
  std::vector<std::uint8_t> longer = bytes;
  longer.push_back(0);
  EXPECT_EQ(DecodeCode(longer), StatusCode::kCorrupt);
}

TEST(VocabularyFileTest, EveryFlippedByteIsAnError) {
  const auto bytes = SmallVocabularyBytes();
  for (std::size_t i = 0; i < bytes.size(); ++i) {
    std::vector<std::uint8_t> bad = bytes;
    bad[i] ^= 0x20;
    const StatusCode code = DecodeCode(bad);
    // Bytes 8..11 hold the version: another version is reported as such.
    if (i >= 8 && i < 12) {
      EXPECT_EQ(code, StatusCode::kUnsupported) << i;
    } else {
      EXPECT_EQ(code, StatusCode::kCorrupt) << i;
    }
  }
}

TEST(VocabularyFileTest, InconsistentTreeWithValidCrcIsCorrupt) {
  const auto bytes = SmallVocabularyBytes();
  const std::size_t kNodes = 40;  // node records start here: u32 parent + 32 bytes
  auto node_parent_offset = [&](std::size_t node) { return kNodes + (node - 1) * 36; };
  {  // A node claiming itself as parent.
    auto bad = bytes;
    PutU32(&bad, node_parent_offset(5), 5);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // Parents out of breadth-first order (node 2 under node 1, node 3 under the root).
    auto bad = bytes;
    PutU32(&bad, node_parent_offset(2), 1);
    PutU32(&bad, node_parent_offset(3), 0);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // Four children of the root in a branching-3 tree.
    auto bad = bytes;
    PutU32(&bad, node_parent_offset(4), 0);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // Word count that does not match the leaves (file size adjusted to match the header).
    auto bad = bytes;
    std::uint32_t words = bad[24] | bad[25] << 8 | bad[26] << 16 | bad[27] << 24;
    PutU32(&bad, 24, words - 1);
    bad.erase(bad.end() - 8, bad.end() - 4);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // A NaN weight.
    auto bad = bytes;
    PutU32(&bad, bad.size() - 8, 0x7FC00000u);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // A header announcing 2^31 nodes: rejected before any allocation.
    auto bad = bytes;
    PutU32(&bad, 20, 0x80000000u);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
  {  // Depth 0 and branching 1.
    auto bad = bytes;
    PutU32(&bad, 16, 0);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
    bad = bytes;
    PutU32(&bad, 12, 1);
    FixCrc(&bad);
    EXPECT_EQ(DecodeCode(bad), StatusCode::kCorrupt);
  }
}

// Random damage with the CRC recomputed, so that only the structural checks stand between
// the bytes and the tree walk: decoding never crashes, and whatever decodes is usable.
TEST(VocabularyFileTest, RandomDamageBehindAValidCrcNeverCrashes) {
  const auto bytes = SmallVocabularyBytes();
  Rng rng(31);
  int decoded = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    auto bad = bytes;
    const int edits = rng.UniformInt(1, 4);
    for (int e = 0; e < edits; ++e) {
      const int at = rng.UniformInt(8, static_cast<int>(bad.size()) - 5);  // keep magic and CRC
      bad[at] = static_cast<std::uint8_t>(rng.Next());
    }
    FixCrc(&bad);
    auto v = Vocabulary::Deserialize(bad);
    if (!v.ok()) continue;
    ++decoded;
    for (int i = 0; i < 20; ++i) {
      const WordId w = v->WordOf(RandomDescriptor(rng));
      ASSERT_LT(w, static_cast<WordId>(v->word_count()));
    }
    EXPECT_EQ(v->Serialize(), bad);
  }
  EXPECT_GT(decoded, 0);  // descriptor bytes may change freely
}

TEST(VocabularyFileTest, LoadErrors) {
  testing::TempDir dir;
  EXPECT_FALSE(Vocabulary::Load(dir.File("missing.bin")).ok());
  {
    std::ofstream out(dir.File("text.bin"));
    out << "this is not a vocabulary file at all, but it is long enough to have a header";
  }
  auto text = Vocabulary::Load(dir.File("text.bin"));
  EXPECT_EQ(text.status().code(), StatusCode::kCorrupt);
  const auto bytes = SmallVocabularyBytes();
  {
    std::ofstream out(dir.File("half.bin"), std::ios::binary);
    out.write(reinterpret_cast<const char*>(bytes.data()), bytes.size() / 2);
  }
  EXPECT_EQ(Vocabulary::Load(dir.File("half.bin")).status().code(), StatusCode::kCorrupt);
  EXPECT_FALSE(Vocabulary().Save(dir.File("empty.bin")).ok());
}

}  // namespace
}  // namespace ccmd
