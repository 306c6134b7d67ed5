#pragma once

// Evaluation of a split-replay run from the files it left: the server's trajectories, dense
// map and statistics, the agents' statistics, and the processes' CPU use. Produces
// results.json, report.md and PNG plots in the run folder.

#include <array>
#include <string>
#include <vector>

#include "libccmd/io/ply.h"
#include "libccmd/io/split.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"

namespace ccmd {

struct ReplayProcess {
  std::string name;  // "agent1", ..., "server"
  double cpu_seconds = 0;
  double wall_seconds = 0;
  double max_rss_mb = 0;
  int exit_code = 0;
  std::vector<std::pair<double, double>> cpu_percent;  // (seconds since start, % of one core)
};

struct ReplayRunInfo {
  std::string dataset_dir;
  std::string command;  // as typed
  std::string config;   // camera/tracking config used ("" = from the dataset)
  int agents = 0;
  std::string rate;  // realtime or max
  double wall_seconds = 0;
  std::vector<FrameRange> segments;
  std::vector<ReplayProcess> processes;
  std::string link;  // the shaped link's spec ("" = loopback)
  Json link_stats;   // its counters (null on loopback)
  // The server's memory as its statistics file said once a second: (seconds since start,
  // keyframes in its maps, resident MB).
  std::vector<std::array<double, 3>> server_memory;
};

struct ReferenceOptions {
  std::string reference_ply;  // "" = surface.ply in the dataset, else built from ground truth
  int first = 0;              // ground-truth build: from this frame
  // Frames are taken where the view has changed: a frame joins when the camera has moved
  // max_move_m or turned max_turn_deg since the last frame taken, or stride frames have passed.
  int stride = 10;
  double max_move_m = 0.05;
  double max_turn_deg = 5.0;
  int downsample = 2;  // each at 1/downsample resolution
  double voxel_m = 0.01;
  // Set when the camera config registers depth to colour (a Depth block): the reference's
  // depth goes through the same registration as the agents' frames.
  std::optional<DepthToColorCalibration> registration;
  // The camera whose poses the ground truth gives, in the colour camera's frame (the config's
  // Trajectory.camera): the registered depth is placed at ground truth * its inverse.
  Pose T_color_trajectory = Pose::Identity();
  // Set when the config moves depth taken apart from its colour image to the colour image's
  // time (Tracking.depthLagCompensation): each depth image is then placed at the ground truth
  // of its own time, as the agents place it.
  bool depth_at_own_time = false;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Sets `options`' registration and ground-truth camera from a camera config (its Depth block
// and Trajectory.camera); leaves them when the file does not exist.
Status ReadReferenceCamera(const std::string& camera_file, ReferenceOptions* options);

// The reference surface for reconstruction error: a given PLY (meshes are sampled), the
// dataset's surface.ply (synthetic sequences), or a cloud back-projected from the dataset's
// depth at its ground-truth poses (TUM, 7-Scenes). `source` says which.
StatusOr<PointCloud> LoadOrBuildReference(const TumSequence& dataset,
                                          const ReferenceOptions& options, std::string* source);

// Reads the run folder (the server's results, agents/) and computes every figure; writes
// results.json, report.md and plots/ there. Returns the results.
StatusOr<Json> EvaluateReplay(const std::string& run_dir, const TumSequence& dataset,
                              const ReplayRunInfo& info, const ReferenceOptions& reference);

// One run of the sampling-rate / keyframe-selection grid (the CCMD-SLAM paper's Table V).
struct AblationRow {
  int downsample = 2;     // r = 1 / downsample
  bool selection = true;  // RGB-D only for keyframes the covisibility selection picks
  std::string run_dir;    // relative to the main run's folder
  Json results;           // that run's results.json
};

// Adds the grid to the main run's report.md (a table: RGB-D keyframes and bytes, map points,
// reconstruction error, fused ATE) and results.json ("ablation").
Status AppendAblation(const std::string& run_dir, const std::vector<AblationRow>& rows);

}  // namespace ccmd
