#include "tests/bench_backend/loop_eval.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "libccmd/backend/ingest.h"
#include "libccmd/backend/loop_verification.h"
#include "libccmd/backend/place_index.h"
#include "libccmd/backend/server_map.h"
#include "libccmd/util/timer.h"

namespace ccmd::bench {
namespace {

constexpr double kDegree = M_PI / 180.0;

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

double Max(const std::vector<double>& v) {
  return v.empty() ? 0 : *std::max_element(v.begin(), v.end());
}

double Share(int part, int whole) { return whole > 0 ? static_cast<double>(part) / whole : 0; }

std::string Name(const GlobalKeyframeId& id) {
  char name[48];
  std::snprintf(name, sizeof(name), "a%d/kf%llu", static_cast<int>(id.agent.value()),
                static_cast<unsigned long long>(id.keyframe.value()));
  return name;
}

Json CheckJson(const LoopCheck& c) {
  Json j;
  j["query_agent"] = c.query.agent.value();
  j["query_keyframe"] = c.query.keyframe.value();
  j["candidate_agent"] = c.candidate.agent.value();
  j["candidate_keyframe"] = c.candidate.keyframe.value();
  j["inliers"] = c.inliers;
  j["distance_m"] = c.relation.distance;
  j["angle_deg"] = c.relation.angle_deg;
  j["overlap"] = c.relation.overlap;
  j["same_place"] = c.relation.same_place;
  j["translation_error_m"] = c.error.translation;
  j["rotation_error_deg"] = c.error.rotation_deg;
  j["correct"] = c.correct;
  return j;
}

void PrintCheck(const char* label, const LoopCheck& c) {
  std::printf(
      "    %s %s ~ %s: %d inliers, centres %.2f m and axes %.0f deg apart, overlap %.2f (%s), "
      "transform "
      "error %.1f mm %.2f deg\n",
      label, Name(c.query).c_str(), Name(c.candidate).c_str(), c.inliers, c.relation.distance,
      c.relation.angle_deg, c.relation.overlap, c.relation.same_place ? "same place" : "wider",
      c.error.translation * 1e3, c.error.rotation_deg);
}

// Error statistics of a set of checks (only those flagged by `use`).
struct ErrorSummary {
  std::vector<double> translation, rotation;
  void Add(const LoopCheck& c) {
    translation.push_back(c.error.translation);
    rotation.push_back(c.error.rotation_deg);
  }
  void Print(const char* label) const {
    if (translation.empty()) return;
    std::printf(
        "  %s transform error: translation median %.1f mm, max %.1f mm; rotation median %.2f deg, "
        "max %.2f "
        "deg (%zu loops)\n",
        label, Median(translation) * 1e3, Max(translation) * 1e3, Median(rotation), Max(rotation),
        translation.size());
  }
  Json ToJson() const {
    Json j;
    j["count"] = translation.size();
    j["translation_median_m"] = Median(translation);
    j["translation_max_m"] = Max(translation);
    j["rotation_median_deg"] = Median(rotation);
    j["rotation_max_deg"] = Max(rotation);
    return j;
  }
};

}  // namespace

// ---------------------------------------------------------------- ground truth

void PlaceGroundTruth::Add(const GlobalKeyframeId& id, const Pose& T_world_cam,
                           const cv::Mat& depth_small, const PinholeCamera& camera) {
  View view;
  view.T_world_cam = T_world_cam;
  view.depth_small = depth_small;
  view.camera = camera;
  // About 32 x 24 samples whatever the image size: enough to measure a share to a few percent.
  const int step = std::max(1, depth_small.cols / 32);
  for (int v = step / 2; v < depth_small.rows; v += step) {
    for (int u = step / 2; u < depth_small.cols; u += step) {
      const float z = depth_small.at<float>(v, u);
      if (z > 0) view.surface_world.push_back(T_world_cam * camera.BackProject(u, v, z));
    }
  }
  views_[id] = std::move(view);
}

double PlaceGroundTruth::SeenShare(const View& a, const View& b) const {
  if (a.surface_world.empty()) return 0;
  const Pose T_b_world = b.T_world_cam.inverse();
  int seen = 0;
  for (const Eigen::Vector3d& p : a.surface_world) {
    const Eigen::Vector3d q = T_b_world * p;
    if (q.z() < 0.1) continue;
    const Eigen::Vector2d uv = b.camera.Project(q);
    const int u = static_cast<int>(std::floor(uv.x())), v = static_cast<int>(std::floor(uv.y()));
    if (u < 0 || v < 0 || u >= b.depth_small.cols || v >= b.depth_small.rows) continue;
    // Seen unless something nearer hides it (the tolerance covers sensor noise).
    const float d = b.depth_small.at<float>(v, u);
    if (d > 0 && std::abs(q.z() - d) < 0.05 * d + 0.02) ++seen;
  }
  return static_cast<double>(seen) / a.surface_world.size();
}

Relation PlaceGroundTruth::Relate(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const {
  Relation r;
  const auto ia = views_.find(a), ib = views_.find(b);
  if (ia == views_.end() || ib == views_.end()) return r;
  const View& va = ia->second;
  const View& vb = ib->second;
  r.distance = (va.T_world_cam.translation() - vb.T_world_cam.translation()).norm();
  const double cos_angle = va.T_world_cam.linear().col(2).dot(vb.T_world_cam.linear().col(2));
  r.angle_deg = std::acos(std::clamp(cos_angle, -1.0, 1.0)) / kDegree;
  const auto key = a < b ? std::make_pair(a, b) : std::make_pair(b, a);
  auto cached = overlap_cache_.find(key);
  if (cached == overlap_cache_.end()) {
    cached = overlap_cache_.emplace(key, std::min(SeenShare(va, vb), SeenShare(vb, va))).first;
  }
  r.overlap = cached->second;
  r.related = r.overlap >= options_.related_overlap;
  r.same_place = r.distance <= options_.same_place_distance &&
                 r.angle_deg <= options_.same_place_angle_deg &&
                 r.overlap >= options_.same_place_overlap;
  return r;
}

bool PlaceGroundTruth::SamePlace(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const {
  const auto ia = views_.find(a), ib = views_.find(b);
  if (ia == views_.end() || ib == views_.end()) return false;
  const Pose& ta = ia->second.T_world_cam;
  const Pose& tb = ib->second.T_world_cam;
  if ((ta.translation() - tb.translation()).norm() > options_.same_place_distance) return false;
  if (ta.linear().col(2).dot(tb.linear().col(2)) <
      std::cos(options_.same_place_angle_deg * kDegree))
    return false;
  return Relate(a, b).same_place;
}

Pose PlaceGroundTruth::TrueRelative(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const {
  return views_.at(a).T_world_cam.inverse() * views_.at(b).T_world_cam;
}

TransformError PlaceGroundTruth::Error(const GlobalKeyframeId& a, const GlobalKeyframeId& b,
                                       const Pose& T_a_b) const {
  TransformError e;
  const auto ia = views_.find(a), ib = views_.find(b);
  if (ia == views_.end() || ib == views_.end()) {
    e.translation = e.rotation_deg = std::numeric_limits<double>::infinity();
    return e;
  }
  const Pose T_a_b_true = ia->second.T_world_cam.inverse() * ib->second.T_world_cam;
  e.translation = TranslationDistance(T_a_b_true, T_a_b);
  e.rotation_deg = RotationDistance(T_a_b_true, T_a_b) / kDegree;
  return e;
}

// ---------------------------------------------------------------- offline detector

namespace {

// One server map per agent, fed with the recorded messages as the back-end's ingest would
// (no fusion: every agent stays in its own frame).
class AgentMaps {
 public:
  ServerMap* Of(AgentId agent) {
    auto& map = maps_[agent];
    if (!map) map = std::make_unique<ServerMap>(MapId(agent.value()));
    return map.get();
  }
  // True when `m` added a keyframe.
  bool Apply(const RecordedMessage& m) {
    ServerMap* map = Of(m.agent);
    if (m.pose_update) {
      ApplyPoseUpdates(map, m.agent, *m.pose_update);
      return false;
    }
    return m.keyframe && AddKeyframeMessage(map, m.agent, *m.keyframe, Pose::Identity()).ok();
  }
  const std::map<AgentId, std::unique_ptr<ServerMap>>& all() const { return maps_; }

 private:
  std::map<AgentId, std::unique_ptr<ServerMap>> maps_;
};

class OfflineDetector {
 public:
  OfflineDetector(const std::map<AgentId, PinholeCamera>& cameras, const BackendOptions& options,
                  const PlaceGroundTruth& truth, DetectorEvaluation* out)
      : cameras_(cameras),
        options_(options),
        truth_(truth),
        place_(options.place),
        consistency_(options.loops),
        out_(out) {}

  void Receive(const RecordedMessage& m) {
    if (!maps_.Apply(m)) return;
    ++out_->keyframes;
    Detect({m.agent, m.keyframe->id}, /*stored=*/false);
    while (!late_.empty()) {
      const GlobalKeyframeId late = late_.front();
      late_.erase(late_.begin());
      Detect(late, /*stored=*/true);
    }
  }

 private:
  // The steps of LoopCloser::Process up to acceptance, on per-agent maps.
  void Detect(const GlobalKeyframeId& id, bool stored) {
    ServerMap* qmap = maps_.Of(id.agent);
    ServerKeyframe* query = qmap->keyframe(id);
    if (!query) return;
    const bool ready = place_.ready();
    std::vector<PlaceHit> hits;
    LoopCandidateRule rule;
    if (ready) {
      rule = MakeLoopCandidateRule(place_, id, *query, options_.loops.exclude_recent_keyframes);
      hits = QueryLoopCandidates(place_, query->Descriptors(), rule,
                                 options_.loops.loop_candidates * 3);
    }
    // What the index held when the query ran: the allowed candidates, and among them revisits.
    bool revisit = false;
    if (ready && truth_.Has(id)) {
      for (const GlobalKeyframeId& other : indexed_) {
        if (rule.Allowed(other) && truth_.SamePlace(id, other)) {
          revisit = true;
          break;
        }
      }
    }
    if (!stored) {
      const std::vector<GlobalKeyframeId> late = place_.Add(id, query->Descriptors());
      late_.insert(late_.end(), late.begin(), late.end());
      indexed_.push_back(id);
    }
    if (!ready || !truth_.Has(id)) return;

    ++out_->queries;
    out_->revisit_queries += revisit;
    // No cool-down here: every keyframe is a query.
    hits = SelectLoopCandidates(
        std::move(hits), /*cooling_down=*/false, MapId(id.agent.value()),
        [](AgentId agent) { return std::optional<MapId>(MapId(agent.value())); },
        options_.loops.loop_candidates);
    bool topn_related = false;
    for (std::size_t k = 0; k < hits.size(); ++k) {
      const bool related = truth_.Relate(id, hits[k].keyframe).related;
      out_->candidates++;
      out_->candidates_related += related;
      topn_related |= related;
      if (k == 0 && revisit) out_->bow_top1_related += related;
    }
    if (revisit) out_->bow_topn_related += topn_related;

    bool found = false, first = true;
    for (const PlaceHit& hit : hits) {
      ServerMap* cmap = maps_.Of(hit.keyframe.agent);
      ServerKeyframe* candidate = cmap->keyframe(hit.keyframe);
      if (!candidate) continue;
      const auto match =
          VerifyLoop(query, cameras_.at(id.agent), candidate, *cmap, options_.loops.verification);
      if (!match) continue;
      LoopCheck check;
      check.query = id;
      check.candidate = hit.keyframe;
      check.inliers = match->inliers;
      check.relation = truth_.Relate(hit.keyframe, id);
      check.error = truth_.Error(hit.keyframe, id,
                                 candidate->T_map_cam.inverse() * match->T_candidate_map_query);
      check.correct = truth_.TransformRight(check.error);
      out_->verified.push_back(check);
      found |= check.correct;
      if (first) Consistency(query, hit.keyframe.agent, match->T_candidate_map_query, check);
      first = false;
    }
    if (revisit && found) {
      ++out_->revisits_found;
    } else if (revisit) {
      ++(topn_related ? out_->missed_verification : out_->missed_no_candidate);
    }
  }

  // The back-end's consistency rule, with one map per agent.
  void Consistency(ServerKeyframe* query, AgentId candidate_agent,
                   const Pose& T_candidate_map_query, const LoopCheck& check) {
    if (consistency_.Confirm(query->id, MapId(candidate_agent.value()), T_candidate_map_query,
                             query->T_map_cam))
      out_->consistent.push_back(check);
  }

  const std::map<AgentId, PinholeCamera>& cameras_;
  const BackendOptions& options_;
  const PlaceGroundTruth& truth_;
  PlaceIndex place_;
  LoopConsistency consistency_;
  DetectorEvaluation* out_;
  AgentMaps maps_;
  std::vector<GlobalKeyframeId> late_;
  std::vector<GlobalKeyframeId> indexed_;
};

}  // namespace

DetectorEvaluation EvaluateDetector(const std::vector<RecordedMessage>& messages,
                                    const std::map<AgentId, PinholeCamera>& cameras,
                                    const BackendOptions& options, const PlaceGroundTruth& truth) {
  DetectorEvaluation evaluation;
  const Stopwatch watch;
  OfflineDetector detector(cameras, options, truth, &evaluation);
  for (const RecordedMessage& m : messages) detector.Receive(m);
  evaluation.seconds = watch.ElapsedSeconds();
  return evaluation;
}

std::vector<TransformError> CovisiblePairErrors(const std::vector<RecordedMessage>& messages,
                                                const PlaceGroundTruth& truth) {
  AgentMaps maps;
  for (const RecordedMessage& m : messages) maps.Apply(m);
  std::vector<TransformError> errors;
  for (const auto& [agent, map] : maps.all()) {
    for (const auto& [id, kf] : map->keyframes()) {
      for (const auto& [other_id, weight] : kf->covisibility) {
        const ServerKeyframe* other = map->keyframe(other_id);
        if (!other || !(id < other_id) || !truth.Has(id) || !truth.Has(other_id)) continue;
        errors.push_back(truth.Error(id, other_id, kf->T_map_cam.inverse() * other->T_map_cam));
      }
    }
  }
  return errors;
}

std::vector<LoopCheck> CheckLoopEvents(const std::vector<LoopEvent>& events,
                                       const PlaceGroundTruth& truth) {
  std::vector<LoopCheck> checks;
  for (const LoopEvent& e : events) {
    LoopCheck c;
    c.query = e.query;
    c.candidate = e.candidate;
    c.inliers = e.inliers;
    c.relation = truth.Relate(e.candidate, e.query);
    c.error = truth.Error(e.candidate, e.query, e.T_candidate_query);
    c.correct = truth.TransformRight(c.error);
    checks.push_back(c);
  }
  return checks;
}

// ---------------------------------------------------------------- reports

Json ReportDetector(const DetectorEvaluation& ev, const PlaceGroundTruth& truth) {
  const PlaceGroundTruthOptions& o = truth.options();
  int tp = 0, tp_same_place = 0;
  ErrorSummary correct_errors, all_errors;
  for (const LoopCheck& c : ev.verified) {
    all_errors.Add(c);
    if (!c.correct) continue;
    ++tp;
    tp_same_place += c.relation.same_place;
    correct_errors.Add(c);
  }
  const int fp = static_cast<int>(ev.verified.size()) - tp;
  const int fn = ev.revisit_queries - ev.revisits_found;
  int consistent_correct = 0;
  for (const LoopCheck& c : ev.consistent) consistent_correct += c.correct;
  const int consistent_false = static_cast<int>(ev.consistent.size()) - consistent_correct;

  std::printf(
      "loop detector, offline (the back-end's PlaceIndex, candidate filter, VerifyLoop and "
      "consistency rule "
      "and options; every keyframe queried on arrival, no cool-down, no loop closed; %.1f s):\n",
      ev.seconds);
  std::printf(
      "  ground truth: same place (a revisit) = centres within %.2f m, optical axes within %.0f "
      "deg, each "
      "view sees >= %.0f%% of the other; a good BoW candidate: each view sees >= %.0f%% of the "
      "other; a "
      "verified loop is correct when its transform is within %.0f mm and %.1f deg of the true "
      "one\n",
      o.same_place_distance, o.same_place_angle_deg, o.same_place_overlap * 100,
      o.related_overlap * 100, o.max_translation_error * 1e3, o.max_rotation_error_deg);
  std::printf("  %d keyframes, %d queries, %d with a revisit among the allowed candidates\n",
              ev.keyframes, ev.queries, ev.revisit_queries);
  std::printf(
      "  BoW: %d candidates proposed, %d overlap the query (%.3f); reference, revisit queries "
      "whose best "
      "candidate overlaps: top-1 %d/%d = %.3f, any proposed %d/%d = %.3f\n",
      ev.candidates, ev.candidates_related, Share(ev.candidates_related, ev.candidates),
      ev.bow_top1_related, ev.revisit_queries, Share(ev.bow_top1_related, ev.revisit_queries),
      ev.bow_topn_related, ev.revisit_queries, Share(ev.bow_topn_related, ev.revisit_queries));
  std::printf(
      "  verified: %zu, correct (TP) %d (%d between same-place views, %d wider), false (FP) %d; "
      "precision %.3f\n",
      ev.verified.size(), tp, tp_same_place, tp - tp_same_place, fp,
      Share(tp, static_cast<int>(ev.verified.size())));
  std::printf(
      "  revisits with a correct verified loop %d/%d: recall %.3f (FN %d: %d without a good "
      "candidate, %d "
      "whose good candidates failed verification); BoW top-1 reference %.3f\n",
      ev.revisits_found, ev.revisit_queries, Share(ev.revisits_found, ev.revisit_queries), fn,
      ev.missed_no_candidate, ev.missed_verification,
      Share(ev.bow_top1_related, ev.revisit_queries));
  std::printf("  consistent (what the back-end would accept): %zu, correct %d, false %d\n",
              ev.consistent.size(), consistent_correct, consistent_false);
  correct_errors.Print("correct verified loops:");
  all_errors.Print("all verified loops:");
  for (const LoopCheck& c : ev.verified) {
    if (!c.correct) PrintCheck("false verified loop", c);
  }
  for (const LoopCheck& c : ev.consistent) {
    if (!c.correct) PrintCheck("FALSE CONSISTENT LOOP", c);
  }

  Json j;
  j["keyframes"] = ev.keyframes;
  j["queries"] = ev.queries;
  j["revisit_queries"] = ev.revisit_queries;
  j["candidates"] = ev.candidates;
  j["candidates_related"] = ev.candidates_related;
  j["bow_top1_recall"] = Share(ev.bow_top1_related, ev.revisit_queries);
  j["bow_topn_recall"] = Share(ev.bow_topn_related, ev.revisit_queries);
  j["verified"] = ev.verified.size();
  j["true_positives"] = tp;
  j["false_positives"] = fp;
  j["true_positives_same_place"] = tp_same_place;
  j["false_negatives"] = fn;
  j["missed_no_candidate"] = ev.missed_no_candidate;
  j["missed_verification"] = ev.missed_verification;
  j["precision"] = Share(tp, static_cast<int>(ev.verified.size()));
  j["recall"] = Share(ev.revisits_found, ev.revisit_queries);
  j["consistent"] = ev.consistent.size();
  j["consistent_false"] = consistent_false;
  j["correct_transform_error"] = correct_errors.ToJson();
  j["verified_transform_error"] = all_errors.ToJson();
  j["seconds"] = ev.seconds;
  Json list = Json::MakeArray();
  for (const LoopCheck& c : ev.verified) list.Push(CheckJson(c));
  j["verified_loops"] = list;
  return j;
}

Json ReportCovisiblePairs(const std::vector<TransformError>& errors, TransformError* p95_out) {
  ErrorSummary pairs;
  for (const TransformError& e : errors) {
    pairs.translation.push_back(e.translation);
    pairs.rotation.push_back(e.rotation_deg);
  }
  std::vector<double> sorted_t = pairs.translation, sorted_r = pairs.rotation;
  std::sort(sorted_t.begin(), sorted_t.end());
  std::sort(sorted_r.begin(), sorted_r.end());
  const auto p95 = [](const std::vector<double>& v) {
    return v.empty() ? 0.0 : v[(v.size() - 1) * 95 / 100];
  };
  std::printf(
      "  reference, covisible keyframe pairs of one agent (its map against ground truth): "
      "translation median "
      "%.1f mm, p95 %.1f mm, max %.1f mm; rotation median %.2f deg, p95 %.2f deg, max %.2f deg "
      "(%zu pairs)\n",
      Median(pairs.translation) * 1e3, p95(sorted_t) * 1e3, Max(pairs.translation) * 1e3,
      Median(pairs.rotation), p95(sorted_r), Max(pairs.rotation), pairs.translation.size());
  p95_out->translation = p95(sorted_t);
  p95_out->rotation_deg = p95(sorted_r);
  Json j = pairs.ToJson();
  j["translation_p95_m"] = p95(sorted_t);
  j["rotation_p95_deg"] = p95(sorted_r);
  return j;
}

Json ReportLoopEvents(const std::vector<LoopCheck>& checks, const std::vector<LoopEvent>& events) {
  int correct = 0, same_place = 0;
  ErrorSummary errors;
  Json list = Json::MakeArray();
  std::printf("loops the back-end accepted, against ground truth:\n");
  for (std::size_t i = 0; i < checks.size(); ++i) {
    const LoopCheck& c = checks[i];
    correct += c.correct;
    same_place += c.relation.same_place;
    errors.Add(c);
    PrintCheck(c.correct ? (events[i].fusion ? "fusion ok" : "loop ok  ")
                         : (events[i].fusion ? "FALSE FUSION" : "FALSE LOOP"),
               c);
    Json x = CheckJson(c);
    x["fusion"] = events[i].fusion;
    list.Push(x);
  }
  const int wrong = static_cast<int>(checks.size()) - correct;
  std::printf("  accepted %zu (%d of them same place), correct %d, false %d\n", checks.size(),
              same_place, correct, wrong);
  errors.Print("accepted loops:");
  Json j;
  j["accepted"] = checks.size();
  j["correct"] = correct;
  j["false"] = wrong;
  j["transform_error"] = errors.ToJson();
  j["loops"] = list;
  return j;
}

}  // namespace ccmd::bench
