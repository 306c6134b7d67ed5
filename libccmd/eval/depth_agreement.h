#pragma once

// How well a recording's ground truth agrees with its own depth: one frame's depth, moved into
// another frame by the ground-truth motion, should land on the depth that frame measured. Used
// to check a dataset's conventions without running any SLAM: the sign of a focal length
// (ICL-NUIM), and which camera of an RGB-D rig the ground-truth poses give (7-Scenes gives the
// depth camera's; a camera on the wrong side of the rig shows as more disagreement when the
// view turns, where the offset between the two cameras moves their centres apart).

#include <opencv2/core.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"

namespace ccmd {

struct DepthAgreementOptions {
  int step = 4;             // pixels of frame a, every step-th in both directions
  double max_error = 0.05;  // metres: within it a pixel agrees
};

struct DepthAgreement {
  double median_error = 0;  // metres, over the pixels compared (a median: occlusions aside)
  int compared = 0;         // pixels of a that landed on a valid depth of b
  int agreeing = 0;         // of those, within max_error
};

// Frame a's depth (uint16 millimetres, `depth_camera`'s image) moved into frame b and compared
// with b's depth. `T_world_a`, `T_world_b`: the ground-truth poses; `T_pose_depth`: the depth
// camera in the frame those poses give (identity when they are the depth camera's own).
DepthAgreement CompareDepthByGroundTruth(const cv::Mat& depth_a_mm, const cv::Mat& depth_b_mm,
                                         const PinholeCamera& depth_camera, const Pose& T_world_a,
                                         const Pose& T_world_b, const Pose& T_pose_depth,
                                         const DepthAgreementOptions& options = {});

}  // namespace ccmd
