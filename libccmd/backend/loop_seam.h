#pragma once

// The seam of a loop: where the candidate side's map points are found again in the query side's
// keyframes, the transform between the sides is refined on their depths, and the matches are
// merged so that both sides are tied in the optimisations that follow. Used by LoopCloser for a
// fusion of two maps (JoinSeam) and for a loop inside one map (RefineLoopOnSeam, TieSeam).

#include <optional>
#include <unordered_set>
#include <vector>

#include "libccmd/backend/loop_options.h"
#include "libccmd/backend/loop_verification.h"
#include "libccmd/backend/server_map.h"
#include "libccmd/geometry/camera.h"

namespace ccmd {

// Step 3 for both kinds of loop: the matched points become one (the query's observation moves
// to the candidate-side point) and the two keyframes become covisible.
void MergeLoopMatches(ServerMap* map, const LoopMatch& match);

// A candidate-side map point found in a query-side keyframe (JoinSeam).
struct SeamMatch {
  ServerKeyframe* keyframe = nullptr;
  int keypoint = -1;
  GlobalMapPointId point;  // resolved through the map (it may be merged meanwhile)
};
// The points `points` projected into each of `keyframes` (all seen through `camera`, all in
// `map`'s frame): per keypoint the point of the smallest descriptor distance within
// `radius_px` (times 1.2 to the keypoint's octave), at most `max_hamming`, whose projected
// depth is within `depth_m` plus 3 sigmas of the keypoint's (keypoints without depth: within
// the radius only). Points a keyframe already observes are skipped.
std::vector<SeamMatch> SearchSeam(const ServerMap& map,
                                  const std::vector<ServerKeyframe*>& keyframes,
                                  const PinholeCamera& camera,
                                  const std::vector<GlobalMapPointId>& points, double radius_px,
                                  double depth_m, int max_hamming, const DepthNoise& depth_noise);
// The rigid transform D, in the map's frame, that moves the query side onto the candidate side
// (candidate point ~ D * query-side position) fitted to the matches with depth: the query-side
// position is the keypoint's measured depth back-projected. Weighted by the depth noise, outliers
// dropped in rounds. Empty with fewer than `min_pairs` pairs; `inliers` receives how many agreed.
std::optional<Pose> AlignSeam(const ServerMap& map, const std::vector<SeamMatch>& matches,
                              const PinholeCamera& camera, const DepthNoise& depth_noise,
                              int min_pairs, int* inliers = nullptr);

// What JoinSeam did (for the log and tests).
struct SeamJoin {
  int searched = 0;      // matches found before the refinement
  int pair_inliers = 0;  // 3D pairs that agreed with the refinement
  bool corrected = false;
  // The first refinement was larger than trusted and a second search from it agreed.
  bool confirmed_by_refit = false;
  Pose correction = Pose::Identity();  // D (AlignSeam): the query side onto the candidate side
  double shift_m = 0;  // how far the query's camera moved relative to the other side
  int merged = 0;      // points merged or observations added after it
};
// Step 3 after a fusion, before the loop's own matches are merged: the candidate's window
// points (LoopVerificationOptions::window_keyframes) are searched in the query's keyframe and
// its strongest covisible neighbours of the same agent (SeamOptions::keyframes); the transform
// is refined on them (AlignSeam) and applied to the keyframes in `moved` (the side that
// entered the other's frame; a refinement larger than SeamOptions::max_correction_* only if
// the search repeated from it agrees); then they are searched again, tighter, and merged, and the
// keyframes become covisible with the candidate side.
SeamJoin JoinSeam(ServerMap* fused, const LoopMatch& match, const PinholeCamera& query_camera,
                  const std::vector<ServerKeyframe*>& moved, const LoopCloserOptions& options);

// The two sides of a loop's seam: the candidate side's keyframes and their map points, and the
// query side's keyframes (the query and its strongest covisible neighbours of its agent).
struct SeamSides {
  std::unordered_set<const ServerKeyframe*> candidate_side;
  std::vector<GlobalMapPointId> points;
  std::vector<ServerKeyframe*> query_keyframes;
};

// The seam searched tightly from the current poses: matches merged (or observations added),
// and the query side's keyframes covisible with the candidate side's. Returns how many.
int TieSeam(ServerMap* map, const SeamSides& sides, const PinholeCamera& camera,
            const LoopCloserOptions& options);
// The verified pose of a loop's query inside one map refined on the seam around the loop, as
// for a fusion (kept when the refinement is not a small one); `sides` receives the seam. The
// map's poses are as they were on return.
LoopMatch RefineLoopOnSeam(ServerMap* map, const LoopMatch& match, const PinholeCamera& camera,
                           const LoopCloserOptions& options, SeamSides* sides);
// A loop inside one map: the query's verified pose refined on the seam around the loop (the
// candidate's window without the query's covisible keyframes, searched in the query and its
// neighbours placed where the verified pose puts them), or the verified pose if the refinement
// is not a small one (SeamOptions::max_correction_*). The map's poses are unchanged.
Pose RefineLoopPose(ServerMap* map, const LoopMatch& match, const PinholeCamera& camera,
                    const LoopCloserOptions& options);

}  // namespace ccmd
