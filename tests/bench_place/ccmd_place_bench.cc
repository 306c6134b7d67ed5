// ccmd_place_bench: measures bag-of-words place recognition.
//
//  recognition: keyframes of a synthetic sequence that circles a room several times are fed
//    in time order to a BowDatabase; each one queries the keyframes older than --separation
//    seconds (the same pass is never a loop). Ground truth says which older keyframes show
//    the same place (camera centres within 0.3 m, optical axes within 30 degrees, and at least
//    half of each view visible in the other). Reported per vocabulary: recall at 100%
//    precision of the top candidate (raw L1 score and the score normalised by the previous
//    keyframe's, as DBoW2 does), top-1 and top-3 recall, average precision. Reference in the
//    same run: the same protocol with exhaustive descriptor matching instead of BoW.
//  speed: descriptors -> BoW vector per 1000 features against a brute-force nearest-word
//    search, and query time against database size against a brute-force L1 scan.

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <map>
#include <memory>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "libccmd/features/bow_database.h"
#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/features/orb_extractor.h"
#include "libccmd/features/training_data.h"
#include "libccmd/features/vocabulary_builder.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"

namespace {

using namespace ccmd;

// ---- Evaluation keyframes and ground truth ------------------------------------------------

struct EvalKeyframe {
  double t = 0;
  Pose T_world_cam;
  cv::Mat descriptors;
  std::vector<Eigen::Vector3d> points_world;  // a grid of the view's surface points
  cv::Mat depth_small;                        // CV_32F metres, 1/4 resolution, 0 = none
};

struct EvalSequence {
  std::string name;
  PinholeCamera camera;
  std::vector<EvalKeyframe> keyframes;
  std::vector<std::vector<char>> same_place;   // strict: a revisit that must be found
  std::vector<std::vector<char>> overlapping;  // loose: a candidate that is not a false loop
};

EvalKeyframe MakeKeyframe(double t, const Pose& T_world_cam, const cv::Mat& bgr,
                          const cv::Mat& depth_m, const PinholeCamera& camera,
                          const OrbExtractor& orb) {
  EvalKeyframe k;
  k.t = t;
  k.T_world_cam = T_world_cam;
  cv::Mat gray;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  if (gray.size() != depth_m.size()) cv::resize(gray, gray, depth_m.size(), 0, 0, cv::INTER_AREA);
  k.descriptors = orb.Extract(gray).descriptors;
  for (int v = 10; v < depth_m.rows; v += 20) {
    for (int u = 10; u < depth_m.cols; u += 20) {
      const float z = depth_m.at<float>(v, u);
      if (z > 0) k.points_world.push_back(T_world_cam * camera.BackProject(u, v, z));
    }
  }
  cv::resize(depth_m, k.depth_small, cv::Size(depth_m.cols / 4, depth_m.rows / 4), 0, 0,
             cv::INTER_NEAREST);
  return k;
}

// Fraction of a's surface samples that b sees (inside its image, not occluded).
double Overlap(const EvalKeyframe& a, const EvalKeyframe& b, const PinholeCamera& camera) {
  if (a.points_world.empty()) return 0;
  const Pose T_b_world = b.T_world_cam.inverse();
  int seen = 0;
  for (const auto& p : a.points_world) {
    const Eigen::Vector3d q = T_b_world * p;
    if (q.z() < 0.1) continue;
    const Eigen::Vector2d uv = camera.Project(q);
    const int u = static_cast<int>(uv.x() / 4), v = static_cast<int>(uv.y() / 4);
    if (u < 0 || v < 0 || u >= b.depth_small.cols || v >= b.depth_small.rows) continue;
    const float d = b.depth_small.at<float>(v, u);
    if (d > 0 && std::abs(q.z() - d) < 0.05 * d + 0.02) ++seen;
  }
  return static_cast<double>(seen) / a.points_world.size();
}

// Same place: camera centres within 0.3 m, optical axes within 30 degrees, and each view
// sees at least half of the other. Overlapping (a candidate that is no false loop, since
// geometric verification can relate the two views): each sees at least 30% of the other.
void ComputeGroundTruth(EvalSequence* seq) {
  const int n = static_cast<int>(seq->keyframes.size());
  seq->same_place.assign(n, std::vector<char>(n, 0));
  seq->overlapping.assign(n, std::vector<char>(n, 0));
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < i; ++j) {
      const EvalKeyframe& a = seq->keyframes[i];
      const EvalKeyframe& b = seq->keyframes[j];
      const double overlap = std::min(Overlap(a, b, seq->camera), Overlap(b, a, seq->camera));
      const double distance = (a.T_world_cam.translation() - b.T_world_cam.translation()).norm();
      const double cos_angle = a.T_world_cam.linear().col(2).dot(b.T_world_cam.linear().col(2));
      seq->overlapping[i][j] = seq->overlapping[j][i] = overlap >= 0.3;
      seq->same_place[i][j] = seq->same_place[j][i] =
          distance <= 0.3 && cos_angle >= std::cos(30.0 * M_PI / 180.0) && overlap >= 0.5;
    }
  }
}

template <typename Fn>
void ParallelFor(int count, int threads, Fn&& fn) {
  std::atomic<int> next{0};
  auto work = [&] {
    for (int i = next++; i < count; i = next++) fn(i);
  };
  std::vector<std::thread> workers;
  for (int t = 1; t < threads; ++t) workers.emplace_back(work);
  work();
  for (auto& w : workers) w.join();
}

// Keyframes every `step` frames of a path through the room of `seed`.
EvalSequence RenderSequence(const std::string& name, std::uint64_t seed, const Trajectory& path,
                            int step, int threads) {
  SyntheticSequenceOptions options;
  options.seed = seed;
  RoomSceneOptions room = options.room;
  room.seed = seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  EvalSequence seq;
  seq.name = name;
  seq.camera = SyntheticCamera();
  std::vector<int> frames;
  for (int f = 0; f < static_cast<int>(path.size()); f += step) frames.push_back(f);
  seq.keyframes.resize(frames.size());
  const OrbExtractor orb;
  ParallelFor(static_cast<int>(frames.size()), threads, [&](int i) {
    const int f = frames[i];
    const RenderedFrame r =
        RenderFrame(scene, seq.camera, path[f].T_world_cam, FrameRenderOptions(options, f));
    seq.keyframes[i] =
        MakeKeyframe(path[f].timestamp, path[f].T_world_cam, r.bgr, r.depth_true, seq.camera, orb);
  });
  ComputeGroundTruth(&seq);
  return seq;
}

// Loops that do not retrace each other: radius, height, heading and pitch change per loop,
// so a revisit sees the place from another viewpoint. `strength` scales the changes (1: up
// to 0.2 m in radius, 15 degrees in heading, 6 in pitch, 0.15 m in height).
Trajectory VariedLoops(int loops, double strength) {
  const LoopPathOptions base;
  Trajectory path;
  const double radius_scale[] = {1.0, 0.82, 1.12, 0.9};
  const double yaw_ahead[] = {35, 50, 22, 42};
  const double pitch[] = {-14, -8, -20, -11};
  const double height[] = {1.35, 1.5, 1.22, 1.42};
  for (int l = 0; l < loops; ++l) {
    LoopPathOptions o = base;
    const double scale = 1.0 + strength * (radius_scale[l % 4] - 1.0);
    o.radius_x *= scale;
    o.radius_y *= scale;
    o.yaw_ahead_deg = base.yaw_ahead_deg + strength * (yaw_ahead[l % 4] - base.yaw_ahead_deg);
    o.pitch_deg = base.pitch_deg + strength * (pitch[l % 4] - base.pitch_deg);
    o.height = base.height + strength * (height[l % 4] - base.height);
    o.start_time = base.start_time + l * o.loop_period_s;
    const Trajectory loop = MakeLoopPath(static_cast<int>(o.loop_period_s * 30), 30.0, o);
    path.insert(path.end(), loop.begin(), loop.end());
  }
  return path;
}

StatusOr<EvalSequence> LoadRealSequence(const std::string& name, const std::string& folder,
                                        int step) {
  SourceOptions options;
  options.configs_dir = CCMD_CONFIG_DIR;
  CCMD_ASSIGN_OR_RETURN(auto source, OpenSource("tum:" + folder, options));
  const Trajectory gt = source->GroundTruth();
  EvalSequence seq;
  seq.name = name;
  seq.camera = source->camera();
  const OrbExtractor orb;
  RgbdFrame frame;
  for (int i = 0;; ++i) {
    Status s = source->Read(&frame);
    if (s.code() == StatusCode::kEndOfStream) break;
    CCMD_RETURN_IF_ERROR(s);
    if (i % step != 0 || i >= static_cast<int>(gt.size())) continue;
    cv::Mat depth_m;
    frame.depth_mm.convertTo(depth_m, CV_32F, 1e-3);
    seq.keyframes.push_back(
        MakeKeyframe(frame.timestamp, gt[i].T_world_cam, frame.bgr, depth_m, seq.camera, orb));
  }
  ComputeGroundTruth(&seq);
  return seq;
}

// ---- Detection protocol -------------------------------------------------------------------

struct Detection {
  int query = -1, top = -1;
  bool positive = false;  // some keyframe in the database shows the same place
  bool detected = false;  // there was a candidate at all
  bool strict = false;    // the top candidate shows the same place (strict definition)
  double score = 0, normalised = 0;
  bool correct = false;       // the top candidate overlaps the query (no false loop)
  bool correct_top3 = false;  // one of the best three does
  // A true positive: a revisit exists and the top candidate overlaps; a false positive: the
  // top candidate does not overlap. Queries without a revisit whose top candidate overlaps
  // anyway count as neither.
  bool tp() const { return positive && correct; }
  bool fp() const { return detected && !correct; }
};

struct Metrics {
  int queries = 0, positives = 0;
  double recall_p100 = 0, recall_p100_normalised = 0, top1 = 0, top1_strict = 0, top3 = 0;
  double ap = 0;
  double extra_seconds = 0;  // e.g. online training time
};

// Highest recall with no false detection: detections sorted by score, counted until the first
// wrong one (a group of equal scores containing a wrong one counts as wrong).
double RecallAtFullPrecision(std::vector<Detection> d, bool normalised, int positives) {
  auto key = [&](const Detection& x) { return normalised ? x.normalised : x.score; };
  std::sort(d.begin(), d.end(),
            [&](const Detection& a, const Detection& b) { return key(a) > key(b); });
  int correct = 0;
  for (std::size_t i = 0; i < d.size();) {
    std::size_t j = i;
    bool wrong = false;
    int group_correct = 0;
    for (; j < d.size() && key(d[j]) == key(d[i]); ++j) {
      if (d[j].fp()) wrong = true;
      group_correct += d[j].tp();
    }
    if (wrong) break;
    correct += group_correct;
    i = j;
  }
  return positives > 0 ? static_cast<double>(correct) / positives : 0;
}

double AveragePrecision(std::vector<Detection> d, int positives) {
  std::sort(d.begin(), d.end(),
            [](const Detection& a, const Detection& b) { return a.score > b.score; });
  double ap = 0;
  int tp = 0, fp = 0;
  for (std::size_t i = 0; i < d.size(); ++i) {
    tp += d[i].tp();
    fp += d[i].fp();
    if (d[i].tp()) ap += static_cast<double>(tp) / (tp + fp);
  }
  return positives > 0 ? ap / positives : 0;
}

Metrics Summarise(const std::vector<Detection>& detections) {
  Metrics m;
  m.queries = static_cast<int>(detections.size());
  int top1 = 0, top1_strict = 0, top3 = 0;
  for (const auto& d : detections) {
    m.positives += d.positive;
    top1 += d.tp();
    top1_strict += d.positive && d.strict;
    top3 += d.positive && d.correct_top3;
  }
  if (m.positives > 0) {
    m.top1 = static_cast<double>(top1) / m.positives;
    m.top1_strict = static_cast<double>(top1_strict) / m.positives;
    m.top3 = static_cast<double>(top3) / m.positives;
  }
  m.recall_p100 = RecallAtFullPrecision(detections, false, m.positives);
  m.recall_p100_normalised = RecallAtFullPrecision(detections, true, m.positives);
  m.ap = AveragePrecision(detections, m.positives);
  return m;
}

// `scorer(q, candidates)` returns the candidates' scores for query q; `self_score(q)` the
// score of q against the keyframe before it (for normalisation).
using Scorer = std::function<std::vector<std::pair<double, int>>(int q, int database_end)>;

std::vector<Detection> Detect(const EvalSequence& seq, double separation,
                              const std::function<void(int q)>& before_query, const Scorer& scorer,
                              const std::function<double(int q)>& previous_score) {
  std::vector<Detection> detections;
  const int n = static_cast<int>(seq.keyframes.size());
  int database_end = 0;  // keyframes [0, database_end) are old enough to be candidates
  for (int q = 0; q < n; ++q) {
    if (before_query) before_query(q);
    while (database_end < q && seq.keyframes[database_end].t < seq.keyframes[q].t - separation) {
      ++database_end;
    }
    if (database_end == 0) continue;
    Detection d;
    for (int j = 0; j < database_end; ++j) d.positive |= seq.same_place[q][j] != 0;
    auto ranked = scorer(q, database_end);
    std::sort(ranked.begin(), ranked.end(), [](auto& a, auto& b) {
      return a.first != b.first ? a.first > b.first : a.second < b.second;
    });
    if (!ranked.empty()) {
      d.detected = true;
      d.query = q;
      d.top = ranked[0].second;
      d.strict = seq.same_place[q][ranked[0].second] != 0;
      d.score = ranked[0].first;
      d.correct = seq.overlapping[q][ranked[0].second] != 0;
      for (std::size_t k = 0; k < ranked.size() && k < 3; ++k) {
        d.correct_top3 |= seq.overlapping[q][ranked[k].second] != 0;
      }
      const double previous = q > 0 ? previous_score(q) : 0;
      d.normalised = previous > 0 ? d.score / previous : 0;
    }
    detections.push_back(d);
  }
  return detections;
}

bool g_verbose = false;

// The false positives that score above the weakest true positive, for inspection.
void PrintFalsePositives(const EvalSequence& seq, std::vector<Detection> d) {
  std::sort(d.begin(), d.end(), [](auto& a, auto& b) { return a.score > b.score; });
  double weakest_tp = 1.0;
  for (const auto& x : d) {
    if (x.tp()) weakest_tp = std::min(weakest_tp, x.score);
  }
  for (const auto& x : d) {
    if (!x.fp() || x.score < weakest_tp) continue;
    const EvalKeyframe& a = seq.keyframes[x.query];
    const EvalKeyframe& b = seq.keyframes[x.top];
    const double angle = std::acos(
        std::clamp(a.T_world_cam.linear().col(2).dot(b.T_world_cam.linear().col(2)), -1.0, 1.0));
    std::fprintf(stderr,
                 "  false positive: keyframe %d -> %d score %.3f (weakest true %.3f), overlap "
                 "%.2f/%.2f, %.2f m, %.0f deg, %.1f s apart\n",
                 x.query, x.top, x.score, weakest_tp, Overlap(a, b, seq.camera),
                 Overlap(b, a, seq.camera),
                 (a.T_world_cam.translation() - b.T_world_cam.translation()).norm(),
                 angle * 180 / M_PI, a.t - b.t);
  }
}

// BoW detection with a fixed vocabulary, through BowDatabase (the component under test).
Metrics EvaluateVocabulary(const EvalSequence& seq, const Vocabulary& vocabulary,
                           double separation) {
  std::vector<BowVector> bows;
  for (const auto& k : seq.keyframes) bows.push_back(vocabulary.Transform(k.descriptors));
  BowDatabase db;
  int added = 0;
  auto scorer = [&](int q, int end) {
    for (; added < end; ++added) {
      db.Add({AgentId(0), KeyframeId(added)}, MapId(0), bows[added]).IgnoreError();
    }
    PlaceQueryOptions options;
    options.max_results = 3;
    std::vector<std::pair<double, int>> ranked;
    for (const auto& c : db.Query(bows[q], options)) {
      ranked.emplace_back(c.score, static_cast<int>(c.keyframe.keyframe.value()));
    }
    return ranked;
  };
  const std::vector<Detection> detections = Detect(
      seq, separation, nullptr, scorer, [&](int q) { return L1Score(bows[q], bows[q - 1]); });
  if (g_verbose) PrintFalsePositives(seq, detections);
  return Summarise(detections);
}

// The server's online policy: until the first online training, `fallback` (may be null: no
// detection); then vocabularies retrained by a VocabularyBuilder on the keyframes received,
// with every keyframe transformed again after each training.
Metrics EvaluateOnline(const EvalSequence& seq, const Vocabulary* fallback,
                       const VocabularyBuilderOptions& builder_options, double separation,
                       int* trainings) {
  VocabularyBuilder builder(builder_options);
  std::shared_ptr<const Vocabulary> current;
  if (fallback) current = std::make_shared<Vocabulary>(*fallback);
  std::vector<BowVector> bows;
  BowDatabase db;
  int added = 0;
  double training_seconds = 0;
  *trainings = 0;
  auto retransform = [&](int upto) {
    bows.clear();
    for (int i = 0; i <= upto; ++i)
      bows.push_back(current->Transform(seq.keyframes[i].descriptors));
    db.Clear();
    added = 0;
  };
  auto before = [&](int q) {
    builder.Add(seq.keyframes[q].descriptors).IgnoreError();
    if (builder.TrainingDue()) {
      VocabularyStats stats;
      auto v = builder.Train(&stats);
      if (v.ok()) {
        current = std::make_shared<Vocabulary>(std::move(v).value());
        training_seconds += stats.seconds;
        ++*trainings;
        retransform(q);
        return;
      }
    }
    if (current) bows.push_back(current->Transform(seq.keyframes[q].descriptors));
  };
  auto scorer = [&](int q, int end) {
    std::vector<std::pair<double, int>> ranked;
    if (!current) return ranked;
    for (; added < end; ++added) {
      db.Add({AgentId(0), KeyframeId(added)}, MapId(0), bows[added]).IgnoreError();
    }
    PlaceQueryOptions options;
    options.max_results = 3;
    for (const auto& c : db.Query(bows[q], options)) {
      ranked.emplace_back(c.score, static_cast<int>(c.keyframe.keyframe.value()));
    }
    return ranked;
  };
  auto previous = [&](int q) { return current ? L1Score(bows[q], bows[q - 1]) : 0.0; };
  Metrics m = Summarise(Detect(seq, separation, before, scorer, previous));
  m.extra_seconds = training_seconds;
  return m;
}

// Reference: exhaustive matching of (a subsample of) the descriptors; the score is the
// fraction of query features with a mutual nearest neighbour passing Lowe's ratio test.
Metrics EvaluateExhaustive(const EvalSequence& seq, double separation, int features) {
  std::vector<std::vector<Descriptor>> sub;
  for (const auto& k : seq.keyframes) {
    std::vector<Descriptor> d;
    const int rows = k.descriptors.rows;
    const int take = std::min(rows, features);
    for (int i = 0; i < take; ++i)
      d.push_back(
          DescriptorRow(k.descriptors, static_cast<int>(static_cast<long>(i) * rows / take)));
    sub.push_back(std::move(d));
  }
  auto match_score = [&](int a, int b) {
    const auto& A = sub[a];
    const auto& B = sub[b];
    if (A.empty() || B.empty()) return 0.0;
    std::vector<int> best_b(B.size(), 1000), best_b_index(B.size(), -1);
    std::vector<int> best_a(A.size(), -1);
    std::vector<char> ratio_ok(A.size(), 0);
    for (std::size_t i = 0; i < A.size(); ++i) {
      int best = 1000, second = 1000, arg = -1;
      for (std::size_t j = 0; j < B.size(); ++j) {
        const int d = HammingDistance(A[i], B[j]);
        if (d < best)
          second = best, best = d, arg = static_cast<int>(j);
        else if (d < second)
          second = d;
        if (d < best_b[j]) best_b[j] = d, best_b_index[j] = static_cast<int>(i);
      }
      best_a[i] = arg;
      ratio_ok[i] = best <= 50 && best < 0.8 * second;
    }
    int matches = 0;
    for (std::size_t i = 0; i < A.size(); ++i) {
      matches += ratio_ok[i] && best_a[i] >= 0 && best_b_index[best_a[i]] == static_cast<int>(i);
    }
    return static_cast<double>(matches) / A.size();
  };
  auto scorer = [&](int q, int end) {
    std::vector<std::pair<double, int>> ranked(end);
    for (int j = 0; j < end; ++j) ranked[j] = {match_score(q, j), j};
    return ranked;
  };
  return Summarise(
      Detect(seq, separation, nullptr, scorer, [&](int q) { return match_score(q, q - 1); }));
}

// ---- Output -------------------------------------------------------------------------------

struct Row {
  std::string sequence, vocabulary;
  int words = 0;
  Metrics m;
};

void PrintRows(const std::vector<Row>& rows) {
  std::printf(
      "\n| sequence | vocabulary | words | queries (with revisit) | R@P100 | R@P100 normalised | "
      "top-1 | top-1 strict | top-3 | AP | extra s |\n");
  std::printf("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
  for (const Row& r : rows) {
    std::printf("| %s | %s | %d | %d (%d) | %.3f | %.3f | %.3f | %.3f | %.3f | %.3f | %.1f |\n",
                r.sequence.c_str(), r.vocabulary.c_str(), r.words, r.m.queries, r.m.positives,
                r.m.recall_p100, r.m.recall_p100_normalised, r.m.top1, r.m.top1_strict, r.m.top3,
                r.m.ap, r.m.extra_seconds);
  }
  std::fflush(stdout);
}

Json RowsJson(const std::vector<Row>& rows) {
  Json array = Json::MakeArray();
  for (const Row& r : rows) {
    Json j = Json::MakeObject();
    j["sequence"] = r.sequence;
    j["vocabulary"] = r.vocabulary;
    j["words"] = r.words;
    j["queries"] = r.m.queries;
    j["positives"] = r.m.positives;
    j["recall_at_precision_1"] = r.m.recall_p100;
    j["recall_at_precision_1_normalised"] = r.m.recall_p100_normalised;
    j["top1_recall"] = r.m.top1;
    j["top1_recall_strict"] = r.m.top1_strict;
    j["top3_recall"] = r.m.top3;
    j["average_precision"] = r.m.ap;
    j["extra_seconds"] = r.m.extra_seconds;
    array.Push(j);
  }
  return array;
}

}  // namespace

int RunSpeed(const std::vector<std::pair<std::string, const Vocabulary*>>& vocabularies,
             const std::vector<cv::Mat>& images, Json* json);

int main(int argc, char** argv) {
  CLI::App app{
      "Bag-of-words place recognition benchmark: precision/recall on synthetic revisits "
      "for several vocabularies, and transform/query speed."};
  std::uint64_t eval_seed = 7, train_seed = 101;
  int threads = 2, loops = 3, step = 7, train_step = 4, reference_features = 300;
  double separation = 5.0;
  bool skip_recognition = false, skip_speed = false, skip_reference = false, quick = false;
  std::string json_path, datasets_dir = CCMD_SHARED_DATASETS;
  app.add_option("--eval-seed", eval_seed, "Room of the evaluation sequences")
      ->capture_default_str();
  app.add_option("--train-seed", train_seed, "First room of the synthetic training data")
      ->capture_default_str();
  app.add_option("--loops", loops, "Loops around the room per evaluation sequence")
      ->capture_default_str();
  app.add_option("--step", step, "Frames between evaluation keyframes")->capture_default_str();
  app.add_option("--train-step", train_step, "Frames between synthetic training images")
      ->capture_default_str();
  app.add_option("--separation", separation, "Seconds before a keyframe becomes a loop candidate")
      ->capture_default_str();
  app.add_option("--threads", threads, "Render/extract/train threads")->capture_default_str();
  app.add_option("--reference-features", reference_features,
                 "Descriptors per keyframe for exhaustive matching")
      ->capture_default_str();
  app.add_option("--datasets", datasets_dir, "Folder with the real datasets")
      ->capture_default_str();
  app.add_option("--json", json_path, "Write all results as JSON");
  app.add_flag("--no-recognition", skip_recognition);
  app.add_flag("--no-speed", skip_speed);
  app.add_flag("--no-reference", skip_reference, "Skip exhaustive matching");
  app.add_flag("--verbose", g_verbose, "Print the false positives that outscore a true one");
  app.add_flag("--quick", quick, "Fewer vocabularies (for a smoke test)");
  CLI11_PARSE(app, argc, argv);

  Json json = Json::MakeObject();
  const Stopwatch total;

  // Training data: synthetic rooms other than the evaluation room, and the real datasets.
  TrainingImageOptions image_options;
  image_options.threads = threads;
  image_options.step = 1;
  // Rooms 1-3 every train_step frames; the six-room set takes every second of those images
  // and rooms 4-6 at twice the step (the same number of images from more rooms).
  std::vector<cv::Mat> synthetic_training, six_rooms;
  const int training_rooms = quick ? 1 : 3;
  for (int r = 0; r < (quick ? 1 : 6); ++r) {
    const bool first_set = r < training_rooms;
    const std::string spec = "frames=480,seed=" + std::to_string(train_seed + r) +
                             ",step=" + std::to_string(train_step * (first_set ? 1 : 2));
    auto images = DescriptorsFromSynthetic(spec, image_options);
    if (!images.ok()) {
      std::fprintf(stderr, "%s\n", images.status().ToString().c_str());
      return 1;
    }
    for (std::size_t i = 0; i < images->descriptors.size(); ++i) {
      if (first_set) synthetic_training.push_back(images->descriptors[i]);
      if (!first_set || i % 2 == 0) six_rooms.push_back(images->descriptors[i]);
    }
  }
  std::vector<cv::Mat> real_training;
  for (const char* name : {"7scenes_redkitchen_0000_0599", "tum_fr1_desk_9"}) {
    const std::string folder = JoinPath(datasets_dir, name);
    if (!IsDirectory(folder)) continue;
    auto images = DescriptorsFromTumDataset(folder, image_options);
    if (images.ok()) {
      real_training.insert(real_training.end(), images->descriptors.begin(),
                           images->descriptors.end());
    } else {
      std::fprintf(stderr, "skipping %s: %s\n", name, images.status().ToString().c_str());
    }
  }
  std::fprintf(stderr, "training data: %zu synthetic images (%d rooms), %zu real images\n",
               synthetic_training.size(), training_rooms, real_training.size());

  struct Trained {
    std::string name;
    std::unique_ptr<Vocabulary> vocabulary;
  };
  std::vector<Trained> trained;
  Json training_json = Json::MakeArray();
  auto train = [&](const std::string& name, const std::vector<cv::Mat>& images, int k, int depth) {
    VocabularyOptions o;
    o.branching = k;
    o.depth = depth;
    o.threads = threads;
    VocabularyStats stats;
    auto v = Vocabulary::Train(images, o, &stats);
    if (!v.ok()) {
      std::fprintf(stderr, "training %s: %s\n", name.c_str(), v.status().ToString().c_str());
      return;
    }
    std::fprintf(stderr, "trained %s: %d words from %zu descriptors in %.2f s\n", name.c_str(),
                 stats.words, stats.descriptors, stats.seconds);
    Json j = Json::MakeObject();
    j["name"] = name;
    j["words"] = stats.words;
    j["descriptors"] = stats.descriptors;
    j["images"] = stats.images;
    j["seconds"] = stats.seconds;
    j["file_bytes"] = v->Serialize().size();
    training_json.Push(j);
    trained.push_back({name, std::make_unique<Vocabulary>(std::move(v).value())});
  };
  const std::vector<cv::Mat> one_room(
      synthetic_training.begin(),
      synthetic_training.begin() + synthetic_training.size() / training_rooms);
  if (quick) {
    train("synthetic k10 L4", synthetic_training, 10, 4);
  } else {
    train("synthetic k10 L6", synthetic_training, 10, 6);
    train("synthetic k10 L5", synthetic_training, 10, 5);
    train("synthetic k10 L4", synthetic_training, 10, 4);
    train("synthetic k10 L3", synthetic_training, 10, 3);
    train("synthetic 1 room k10 L5", one_room, 10, 5);
    train("synthetic 6 rooms k10 L5", six_rooms, 10, 5);
    train("synthetic 6 rooms k10 L6", six_rooms, 10, 6);
    if (!real_training.empty()) {
      train("real k10 L6", real_training, 10, 6);
      train("real k10 L5", real_training, 10, 5);
      train("real k10 L4", real_training, 10, 4);
    }
  }
  json["training"] = training_json;

  if (!skip_recognition) {
    std::vector<EvalSequence> sequences;
    const Trajectory retrace = MakeLoopPath(480 * loops, 30.0);
    sequences.push_back(RenderSequence("retraced loops", eval_seed, retrace, step, threads));
    sequences.push_back(
        RenderSequence("half-varied loops", eval_seed, VariedLoops(loops, 0.5), step, threads));
    sequences.push_back(
        RenderSequence("varied loops", eval_seed, VariedLoops(loops, 1.0), step, threads));
    const std::string kitchen = JoinPath(datasets_dir, "7scenes_redkitchen_0000_0599");
    if (!quick && IsDirectory(kitchen)) {
      auto real = LoadRealSequence("7-Scenes redkitchen", kitchen, 3);
      if (real.ok())
        sequences.push_back(std::move(real).value());
      else
        std::fprintf(stderr, "skipping 7-Scenes: %s\n", real.status().ToString().c_str());
    }
    std::vector<Row> rows;
    for (const EvalSequence& seq : sequences) {
      const std::size_t first_row = rows.size();
      std::fprintf(stderr, "evaluating on %s (%zu keyframes)\n", seq.name.c_str(),
                   seq.keyframes.size());
      for (const Trained& t : trained) {
        rows.push_back({seq.name, t.name, t.vocabulary->word_count(),
                        EvaluateVocabulary(seq, *t.vocabulary, separation)});
      }
      // Online: trained from the keyframes received so far (k=10, L=4 and L=5).
      for (int depth : quick ? std::vector<int>{4} : std::vector<int>{4, 5}) {
        VocabularyBuilderOptions bo;
        bo.vocabulary.branching = 10;
        bo.vocabulary.depth = depth;
        bo.vocabulary.threads = threads;
        bo.first_training = 20;
        int trainings = 0;
        Metrics m = EvaluateOnline(seq, nullptr, bo, separation, &trainings);
        rows.push_back({seq.name,
                        "online k10 L" + std::to_string(depth) + " (" + std::to_string(trainings) +
                            " trainings)",
                        0, m});
        if (!trained.empty()) {
          const Trained& fallback = trained[quick ? 0 : 1];  // synthetic k10 L5
          m = EvaluateOnline(seq, fallback.vocabulary.get(), bo, separation, &trainings);
          rows.push_back(
              {seq.name, fallback.name + " then online k10 L" + std::to_string(depth), 0, m});
        }
      }
      // IDF recounted on the first 20 keyframes of the sequence (tree from elsewhere).
      if (!trained.empty() && seq.keyframes.size() > 20) {
        Vocabulary adapted = *trained[quick ? 0 : 1].vocabulary;
        std::vector<cv::Mat> first;
        for (int i = 0; i < 20; ++i) first.push_back(seq.keyframes[i].descriptors);
        if (adapted.SetIdfFrom(first).ok()) {
          rows.push_back({seq.name, trained[quick ? 0 : 1].name + ", IDF from first 20 keyframes",
                          adapted.word_count(), EvaluateVocabulary(seq, adapted, separation)});
        }
      }
      if (!skip_reference) {
        const Stopwatch watch;
        Metrics m = EvaluateExhaustive(seq, separation, reference_features);
        m.extra_seconds = watch.ElapsedSeconds();
        rows.push_back(
            {seq.name,
             "reference: exhaustive matching (" + std::to_string(reference_features) + " features)",
             0, m});
      }
      PrintRows(std::vector<Row>(rows.begin() + first_row, rows.end()));
    }
    json["recognition"] = RowsJson(rows);
  }

  if (!skip_speed && !trained.empty()) {
    std::vector<std::pair<std::string, const Vocabulary*>> list;
    for (const Trained& t : trained) {
      if (t.name.rfind("synthetic k10", 0) == 0) list.emplace_back(t.name, t.vocabulary.get());
    }
    Json speed = Json::MakeObject();
    RunSpeed(list, synthetic_training, &speed);
    json["speed"] = speed;
  }
  json["seconds"] = total.ElapsedSeconds();
  if (!json_path.empty()) {
    if (auto s = WriteJsonFile(json, json_path); !s.ok()) {
      std::fprintf(stderr, "%s\n", s.ToString().c_str());
      return 1;
    }
  }
  return 0;
}
