#pragma once

// Descriptor matching for tracking and mapping, in the ORB-SLAM manner: candidates come from
// projecting map points into the image (or from brute force), the best Hamming distance must
// pass a threshold and a ratio test, and matches whose orientation change disagrees with the
// dominant rotation are dropped.

#include <utility>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/tracking/frame.h"

namespace ccmd {

constexpr int kMatchHigh = 100;  // Hamming distance accepted for projection matches
constexpr int kMatchLow = 50;    // strict threshold (fusion, brute force)

// Matches the map points of `last` (already tracked there) into `current`, whose pose is the
// prediction. Search radius = radius * scale of the last keypoint's octave. Returns matches.
int SearchFromLastFrame(TrackingFrame* current, const TrackingFrame& last, float radius,
                        const OrbExtractor& orb, const PinholeCamera& camera);

// Projects candidate map points (not yet matched in `current`) and matches them.
// `radius` multiplies ORB-SLAM's viewing-angle dependent window. Increases the points'
// visible counters for those predicted in view. Returns the number of new matches.
int SearchLocalPoints(TrackingFrame* current, const std::vector<MapPointPtr>& candidates,
                      float radius, const OrbExtractor& orb, const PinholeCamera& camera);

// Brute-force matching of the keyframe's map points against the frame's descriptors (ratio
// test and rotation consistency). Fills current->points; returns the number of matches.
int SearchByDescriptor(TrackingFrame* current, const Keyframe& keyframe, float ratio = 0.75f);

// Projects map points into a keyframe and fuses duplicates: a keypoint without a map point gets
// the observation, one with a different map point is merged into the better observed one.
// Returns the number of fused or added observations.
int FusePoints(LocalMap* map, Keyframe* keyframe, const std::vector<MapPointPtr>& points,
               const OrbExtractor& orb, const PinholeCamera& camera, float radius = 3.0f);

// Whether keypoint i lies where a point predicted at pixel `uv`, with virtual right coordinate
// `u_right_predicted`, would be seen: the reprojection error, in its octave's sigmas, within
// the 95 % chi-square gate (2 dof, or 3 where the keypoint has depth).
bool WithinReprojectionGate(const FrameFeatures& features, int i, const Eigen::Vector2d& uv,
                            double u_right_predicted, const OrbExtractor& orb);

// Pairs of keypoints in two keyframes that neither links to a map point and at least one has
// no depth for, that show the same point: descriptor distance within kMatchLow and below
// `ratio` times the next candidate's, the keypoint in `b` within the 95 % gate of the epipolar
// line of the one in `a`, one keypoint of `b` per pair, rotations consistent with the dominant
// one. Returns (keypoint in a, keypoint in b) pairs, for triangulation.
std::vector<std::pair<int, int>> SearchForTriangulation(const Keyframe& a, const Keyframe& b,
                                                        const OrbExtractor& orb,
                                                        const PinholeCamera& camera,
                                                        float ratio = 0.6f);

// Keeps the matches whose rotation (angle difference) falls in the three most populated
// histogram bins. `rotations[i]` in degrees; returns the indices to drop.
std::vector<int> RotationOutliers(const std::vector<float>& rotations);

}  // namespace ccmd
