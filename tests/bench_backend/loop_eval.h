#pragma once

// Loop detection measured against ground truth, for ccmd_backend_bench.
//
// The bench records every message the agents send (in the order the back-end received them)
// and, per keyframe, the ground-truth pose and a small depth image of its frame. From these:
//   - PlaceGroundTruth says whether two keyframes show the same place (a revisit the detector
//     should find), whether they overlap enough for a loop between them not to be a false one,
//     and how far a measured relative transform is from the true one;
//   - EvaluateDetector replays the messages into one server map per agent and runs the loop
//     detector's steps on every keyframe, with the back-end's code and options (PlaceIndex,
//     the candidate steps of LoopCloser, VerifyLoop, LoopConsistency), counting
//     what each step gets right and wrong.

#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/backend/backend.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/util/json.h"
#include "proto/messages.h"

namespace ccmd::bench {

// One message as the back-end received it (keyframes without their RGB-D payload).
struct RecordedMessage {
  AgentId agent;
  std::shared_ptr<const KeyframeMessage> keyframe;  // exactly one is set
  std::shared_ptr<const PoseUpdateMessage> pose_update;
};

struct PlaceGroundTruthOptions {
  // Same place (a revisit): camera centres and optical axes close, and each view sees at least
  // `same_place_overlap` of the other's surface.
  double same_place_distance = 0.5;  // metres
  double same_place_angle_deg = 35.0;
  double same_place_overlap = 0.5;
  // A BoW candidate is a good one (geometric verification can relate it) when each view sees
  // at least this much of the other (the "correct" candidate of docs/place_recognition.md).
  double related_overlap = 0.3;
  // A verified loop is correct when its relative transform is right within these (the
  // consistency tolerances of BackendOptions: beyond them the detector itself treats two
  // transforms as different). What a loop adds to the map is that transform, so a loop is false
  // exactly when it is wrong; a right transform between views outside the same-place
  // definition (a wider baseline) is still a correct loop. The bench widens them to what the
  // agents' own maps show against the ground truth (CovisiblePairErrors): a loop cannot be
  // judged more finely than the map and the ground truth agree.
  double max_translation_error = 0.05;  // metres
  double max_rotation_error_deg = 3.0;
};

struct Relation {
  double distance = 0;   // between camera centres, metres
  double angle_deg = 0;  // between optical axes
  double overlap = 0;    // the smaller of the two views' shares seen by the other
  bool same_place = false;
  bool related = false;  // a good BoW candidate
};

struct TransformError {
  double translation = 0;  // metres
  double rotation_deg = 0;
};

class PlaceGroundTruth {
 public:
  explicit PlaceGroundTruth(const PlaceGroundTruthOptions& options) : options_(options) {}

  // `depth_small`: the keyframe's depth (CV_32F metres, 0 = none) at the size `camera` has.
  void Add(const GlobalKeyframeId& id, const Pose& T_world_cam, const cv::Mat& depth_small,
           const PinholeCamera& camera);
  bool Has(const GlobalKeyframeId& id) const { return views_.count(id) > 0; }
  std::size_t size() const { return views_.size(); }

  Relation Relate(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const;
  // Relate(a, b).same_place, with the surface overlap computed only when pose is close.
  bool SamePlace(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const;
  // Error of a measured T_a_b (b's camera in a's camera frame) against the true one.
  TransformError Error(const GlobalKeyframeId& a, const GlobalKeyframeId& b,
                       const Pose& T_a_b) const;
  Pose TrueRelative(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const;
  bool TransformRight(const TransformError& e) const {
    return e.translation <= options_.max_translation_error &&
           e.rotation_deg <= options_.max_rotation_error_deg;
  }
  const PlaceGroundTruthOptions& options() const { return options_; }
  void SetTransformTolerance(double translation, double rotation_deg) {
    options_.max_translation_error = translation;
    options_.max_rotation_error_deg = rotation_deg;
  }

 private:
  struct View {
    Pose T_world_cam;
    cv::Mat depth_small;
    PinholeCamera camera;
    std::vector<Eigen::Vector3d> surface_world;  // a grid of the view's surface points
  };
  // Share of a's surface samples that b sees (inside its image, not occluded).
  double SeenShare(const View& a, const View& b) const;

  PlaceGroundTruthOptions options_;
  std::map<GlobalKeyframeId, View> views_;
  mutable std::map<std::pair<GlobalKeyframeId, GlobalKeyframeId>, double> overlap_cache_;
};

// One verified candidate of the offline pass, or one loop the live back-end accepted.
struct LoopCheck {
  GlobalKeyframeId query, candidate;
  int inliers = 0;
  Relation relation;
  TransformError error;
  bool correct = false;  // the transform is right
};

struct DetectorEvaluation {
  int keyframes = 0;
  int queries = 0;                  // detection queries run (the vocabulary was ready)
  int revisit_queries = 0;          // a same-place keyframe was among the allowed candidates
  int candidates = 0;               // proposed by BoW (after the back-end's filter and limit)
  int candidates_related = 0;       // of which overlap the query
  int bow_top1_related = 0;         // revisit queries whose best candidate overlaps the query
  int bow_topn_related = 0;         // revisit queries with an overlapping proposed candidate
  std::vector<LoopCheck> verified;  // every verified candidate
  int revisits_found = 0;           // revisit queries with a correct verified loop
  int missed_no_candidate = 0;      // revisit queries without one, and no good candidate proposed
  int missed_verification = 0;      // ... a good candidate was proposed but not verified
  std::vector<LoopCheck>
      consistent;  // first verified candidate that completed the consistency rule
  double seconds = 0;
};

// Replays `messages` (keyframes and pose updates in the order the back-end received them)
// into one server map per agent; each keyframe is queried on arrival as LoopCloser::Process
// does it (keyframes that arrive before an online vocabulary exists are queried after the
// first training, like the back-end's late queries). Every proposed candidate is verified
// (the back-end stops at the first that verifies: that one feeds the consistency rule here
// too). Loops are not closed and maps not fused, and the cool-down after a loop is not
// applied, so every keyframe is a query.
DetectorEvaluation EvaluateDetector(const std::vector<RecordedMessage>& messages,
                                    const std::map<AgentId, PinholeCamera>& cameras,
                                    const BackendOptions& options, const PlaceGroundTruth& truth);

// Reference for the transform errors: every pair of covisible keyframes of one agent, their
// relative pose in the agent's map (`messages` replayed into one map per agent, every pose
// update applied) against the true one. Loops cannot be expected to be more accurate than the
// maps and ground truth they are measured with.
std::vector<TransformError> CovisiblePairErrors(const std::vector<RecordedMessage>& messages,
                                                const PlaceGroundTruth& truth);
// Prints the reference and returns its figures; `p95` receives the 95th percentiles.
Json ReportCovisiblePairs(const std::vector<TransformError>& pairs, TransformError* p95);

// The live back-end's loops checked against ground truth.
std::vector<LoopCheck> CheckLoopEvents(const std::vector<LoopEvent>& events,
                                       const PlaceGroundTruth& truth);

// Prints the tables and returns the figures as JSON.
Json ReportDetector(const DetectorEvaluation& evaluation, const PlaceGroundTruth& truth);
Json ReportLoopEvents(const std::vector<LoopCheck>& checks, const std::vector<LoopEvent>& events);

}  // namespace ccmd::bench
