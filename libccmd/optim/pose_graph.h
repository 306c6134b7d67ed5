#pragma once

// SE(3) pose-graph optimisation with Ceres (as in Ceres' pose_graph_3d example): nodes are
// keyframe poses T_world_node, edges relative-pose measurements T_a_b between two nodes with a
// weight. Used after a loop closure: sequential, covisibility and loop edges spread the loop
// correction along the map.

#include <vector>

#include "libccmd/geometry/pose.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct PoseGraphNode {
  Pose T_world_node = Pose::Identity();
  bool fixed = false;
};

struct PoseGraphEdge {
  int a = 0, b = 0;
  Pose T_a_b = Pose::Identity();  // measured pose of b in a's frame
  // Square roots of the information: residuals are (angle-axis radians, metres) scaled by these.
  double sqrt_info_rotation = 1.0;
  double sqrt_info_translation = 1.0;
};

struct PoseGraphOptions {
  int max_iterations = 50;
  double huber_delta = 0.0;  // 0: no robust kernel

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct PoseGraphSummary {
  int iterations = 0;
  double initial_cost = 0, final_cost = 0;
  double seconds = 0;
};

// Optimises the non-fixed nodes in place. At least one node must be fixed (the gauge).
StatusOr<PoseGraphSummary> OptimizePoseGraph(std::vector<PoseGraphNode>* nodes,
                                             const std::vector<PoseGraphEdge>& edges,
                                             const PoseGraphOptions& options = {});

}  // namespace ccmd
