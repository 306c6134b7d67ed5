#pragma once

// Options of loop closing (LoopCloser) and of the seams it refines and ties (loop_seam.h).

#include "libccmd/backend/loop_verification.h"
#include "libccmd/backend/map_optimization.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

// How a fusion's seam is refined and tied (JoinSeam). The verified loop measures the query's
// pose from one keyframe's matches; the candidate side's map points, projected into the query
// side's keyframes around the loop, find many more, whose depths fix the transform between the
// maps better, and which, merged, tie both sides in the global BA that follows.
struct SeamOptions {
  bool enabled = true;
  int keyframes = 10;            // query-side keyframes searched: the query and its neighbours
  double search_radius_px = 10;  // before the refinement (at octave 0; grows with the octave)
  double merge_radius_px = 4;    // after it
  double search_depth_m = 0.05;  // |keypoint depth - projected depth| accepted before
  double merge_depth_m = 0.02;   // ... and after the refinement (plus 3 depth sigmas)
  int max_hamming = 50;
  int min_pairs = 20;  // 3D pairs (depth on the query side) needed to refine the transform
  // A refinement larger than this (how far it moves and turns the query's camera) is not
  // trusted on its own (the verified loop was wrong, or the matches): a fusion takes it only if
  // the search repeated from it agrees (JoinSeam).
  double max_correction_m = 0.05;
  double max_correction_deg = 2.0;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Where two maps overlap besides the loop that confirmed their fusion. That loop may join a
// place one agent came back to after the other saw it, from another viewpoint and with few
// matches, while the maps overlap elsewhere where their views agree closely; and whatever an
// agent drifted between such places lies between the maps at the others, where no query may
// ever look again (the agents have moved on, the query agent cools down). Pairs of the query
// agent's keyframes and the other map's that are close (cameras within max_distance_m, optical
// axes within max_angle_deg) and share fewer than tied_points map points, one per place (the
// closest; queries at least spacing_m apart), at most max_pairs, are: verified before the
// fusion, which is made at the one with the most inliers if it beats the confirming loop
// (StrongerFusionLoop); verified and closed after it like the loops of the confirming group
// (UncomparedOverlaps, CloseEarlierLoops); and, one per keyframe, checked for each keyframe
// the query agent makes while it cools down after the fusion (UncomparedNeighbour).
struct FusionOverlapOptions {
  int max_pairs = 4;  // 0: none
  double max_distance_m = 0.3;
  double max_angle_deg = 30;
  double spacing_m = 0.5;
  int tied_points = 10;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct LoopCloserOptions {
  LoopVerificationOptions verification;
  SeamOptions seam;
  FusionOverlapOptions overlap;
  int loop_candidates = 4;   // verified per query, best score first
  int loop_consistency = 2;  // consecutive confirming keyframes needed
  // How far apart two loops' map-to-map transforms may put the later query (metres, degrees).
  double consistency_translation = 0.05;
  double consistency_rotation_deg = 3.0;
  int consistency_max_gap = 3;  // keyframe ids between two confirming queries
  // When the query's agent stops (session ended, or idle): neighbours of each side of its
  // waiting loop verified against the other side in place of its next keyframes
  // (LoopCloser::AgentStopped), at most this many on each side; 0: none.
  int neighbour_checks = 3;
  int exclude_recent_keyframes = 25;  // same-agent neighbours in id that never count as loops
  int loop_cooldown_keyframes =
      10;  // after a loop, the agent's next keyframes seek no loop in their own map
  // A loop inside a map whose verified pose of the query differs from the query's pose in the
  // map by less than this is already closed: its edge and matches are kept, but there is
  // nothing to correct (no pose graph, no global BA). An agent circling a room finds such
  // loops on every pass; optimising the whole map for each would grow without bound.
  double min_correction_m = 0.005;
  double min_correction_deg = 0.25;
  MapPoseGraphOptions pose_graph;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

}  // namespace ccmd
