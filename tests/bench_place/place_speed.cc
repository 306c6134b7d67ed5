// Speed half of ccmd_place_bench: vocabulary transform against a brute-force nearest-word
// search, and database queries against a brute-force L1 scan, in the same run.

#include <algorithm>
#include <cstdio>
#include <string>
#include <vector>

#include "libccmd/features/bow_database.h"
#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/util/json.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"

namespace {

using namespace ccmd;

// Results are added here so that the compiler cannot drop the timed work.
volatile std::uint64_t g_sink = 0;

// Runs fn() until at least `seconds` have passed; returns seconds per call.
template <typename Fn>
double TimePerCall(Fn&& fn, double seconds = 0.5) {
  int calls = 0;
  const Stopwatch watch;
  do {
    fn();
    ++calls;
  } while (watch.ElapsedSeconds() < seconds);
  return watch.ElapsedSeconds() / calls;
}

// The leaf whose descriptor is nearest (what a flat vocabulary of the same words would do).
WordId NearestWord(const Vocabulary& v, const std::uint8_t* d) {
  WordId best = 0;
  int best_distance = 1000;
  for (int w = 0; w < v.word_count(); ++w) {
    const int distance = HammingDistance(v.NodeDescriptor(v.NodeOfWord(w)).data(), d);
    if (distance < best_distance) best_distance = distance, best = static_cast<WordId>(w);
  }
  return best;
}

cv::Mat RandomSubset(const cv::Mat& descriptors, double keep, Rng& rng) {
  cv::Mat out;
  for (int r = 0; r < descriptors.rows; ++r) {
    if (rng.Bernoulli(keep)) out.push_back(descriptors.row(r));
  }
  return out;
}

}  // namespace

int RunSpeed(const std::vector<std::pair<std::string, const Vocabulary*>>& vocabularies,
             const std::vector<cv::Mat>& images, Json* json) {
  if (images.empty()) return 1;
  // ---- Transform ----
  std::printf(
      "\n| vocabulary | words | BoW vector ms/1000 features | + direct index | "
      "brute-force nearest word ms/1000 | speed-up | same word as brute force |\n");
  std::printf("|---|---:|---:|---:|---:|---:|---:|\n");
  Json transform = Json::MakeArray();
  const std::size_t sample_images = std::min<std::size_t>(images.size(), 20);
  long features = 0;
  for (std::size_t i = 0; i < sample_images; ++i) features += images[i].rows;
  for (const auto& [name, v] : vocabularies) {
    const double bow_s = TimePerCall([&] {
      for (std::size_t i = 0; i < sample_images; ++i)
        g_sink = g_sink + v->Transform(images[i]).size();
    });
    const double direct_s = TimePerCall([&] {
      FeatureVector fv;
      for (std::size_t i = 0; i < sample_images; ++i)
        g_sink = g_sink + v->Transform(images[i], Vocabulary::kDefaultDirectIndexLevel, &fv).size();
    });
    // Brute force on 200 descriptors (it is slow), scaled to 1000.
    const cv::Mat& probe = images[0];
    const int probe_rows = std::min(200, probe.rows);
    const double brute_s = TimePerCall(
        [&] {
          for (int r = 0; r < probe_rows; ++r)
            g_sink = g_sink + NearestWord(*v, probe.ptr<std::uint8_t>(r));
        },
        0.3);
    int same = 0;
    for (int r = 0; r < probe_rows; ++r) {
      same += NearestWord(*v, probe.ptr<std::uint8_t>(r)) == v->WordOf(probe.ptr<std::uint8_t>(r));
    }
    const double bow_ms = bow_s * 1e3 / features * 1000;
    const double direct_ms = direct_s * 1e3 / features * 1000;
    const double brute_ms = brute_s * 1e3 / probe_rows * 1000;
    std::printf("| %s | %d | %.3f | %.3f | %.1f | %.0fx | %.2f |\n", name.c_str(), v->word_count(),
                bow_ms, direct_ms, brute_ms, brute_ms / bow_ms,
                static_cast<double>(same) / probe_rows);
    Json j = Json::MakeObject();
    j["vocabulary"] = name;
    j["words"] = v->word_count();
    j["bow_ms_per_1000"] = bow_ms;
    j["bow_direct_ms_per_1000"] = direct_ms;
    j["brute_force_ms_per_1000"] = brute_ms;
    j["same_word_fraction"] = static_cast<double>(same) / probe_rows;
    transform.Push(j);
  }
  (*json)["transform"] = transform;

  // ---- Query time against database size ----
  std::printf(
      "\n| vocabulary | keyframes | add ms/keyframe | query ms (inverted index) | "
      "query ms (brute-force L1 scan) | speed-up |\n");
  std::printf("|---|---:|---:|---:|---:|---:|\n");
  Json query = Json::MakeArray();
  for (std::size_t vi = 0; vi < vocabularies.size();
       vi += std::max<std::size_t>(1, vocabularies.size() - 1)) {
    const auto& [name, v] = vocabularies[vi];
    Rng rng(5);
    // Keyframes: random 70% subsets of the training images' features (real word statistics).
    const int max_size = 10000;
    std::vector<BowVector> entries;
    entries.reserve(max_size);
    for (int i = 0; i < max_size; ++i) {
      const cv::Mat& image = images[rng.UniformInt(0, static_cast<int>(images.size()) - 1)];
      entries.push_back(v->Transform(RandomSubset(image, 0.7, rng)));
    }
    std::vector<BowVector> queries;
    for (int i = 0; i < 50; ++i) {
      queries.push_back(v->Transform(
          RandomSubset(images[rng.UniformInt(0, static_cast<int>(images.size()) - 1)], 0.7, rng)));
    }
    BowDatabase db;
    int added = 0;
    for (int size : {100, 1000, 10000}) {
      const Stopwatch add_watch;
      const int before = added;
      for (; added < size; ++added) {
        db.Add({AgentId(added % 4), KeyframeId(added)}, MapId(0), entries[added]).IgnoreError();
      }
      const double add_ms = add_watch.ElapsedMillis() / (size - before);
      PlaceQueryOptions options;
      options.max_results = 10;
      std::size_t qi = 0;
      const double query_s = TimePerCall(
          [&] { g_sink = g_sink + db.Query(queries[qi++ % queries.size()], options).size(); });
      qi = 0;
      const double brute_s = TimePerCall([&] {
        const BowVector& q = queries[qi++ % queries.size()];
        std::vector<std::pair<double, int>> scores(size);
        for (int i = 0; i < size; ++i) scores[i] = {L1Score(q, entries[i]), i};
        std::partial_sort(scores.begin(), scores.begin() + std::min(10, size), scores.end(),
                          [](auto& a, auto& b) { return a.first > b.first; });
        g_sink = g_sink + scores[0].second;
      });
      std::printf("| %s | %d | %.3f | %.3f | %.3f | %.1fx |\n", name.c_str(), size, add_ms,
                  query_s * 1e3, brute_s * 1e3, brute_s / query_s);
      Json j = Json::MakeObject();
      j["vocabulary"] = name;
      j["keyframes"] = size;
      j["add_ms"] = add_ms;
      j["query_ms"] = query_s * 1e3;
      j["brute_force_query_ms"] = brute_s * 1e3;
      query.Push(j);
    }
  }
  (*json)["query"] = query;
  std::fflush(stdout);
  return 0;
}
