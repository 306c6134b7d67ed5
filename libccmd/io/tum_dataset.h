#pragma once

// Reader for RGB-D sequences in the TUM RGB-D layout:
//   rgb.txt, depth.txt   "timestamp path" per line (paths relative to the folder, .png or
//                        .jpg, taken as written), '#' comments
//   groundtruth.txt      TUM trajectory of the colour camera (optional)
//   camera.yaml          optional camera config (ORB-SLAM YAML) written by ccmd_synth
// Colour and depth are associated as TUM's associate.py does: candidate pairs closer than
// a tolerance (default 20 ms), taken greedily from the closest, each file used once.
// Folders that only have an associations.txt ("t path t path", as ORB-SLAM's examples and
// ICL-NUIM's TUM-compatible release ship them; which column is depth is told by the path)
// are read from it. ICL-NUIM's release numbers its frames where timestamps go (0, 1, 2, ...,
// in its ground truth too): such consecutive whole numbers are read as frames at the camera's
// rate (index / fps seconds). Without a groundtruth.txt, the one *.gt.freiburg file of the
// folder (ICL-NUIM's) is the ground truth.
// A 7-Scenes sequence folder as its archives unpack (seq-01/frame-000000.color.png,
// .depth.png in millimetres with 65535 for no depth, .pose.txt a 4x4 camera-to-world
// matrix) is read as it is: every frame-NNNNNN.color.png (or .jpg) in the order of its
// number, which need not start at 0 (part of a sequence copied out keeps its numbers),
// timestamps 1 + number/30 s (7-Scenes has none; the same as the project's converted
// copies), depth in millimetres whatever the camera's DepthMapFactor, the poses as the
// ground truth.

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct TimedFile {
  double timestamp = 0;
  std::string path;  // as written in the list
};

// Reads a "timestamp path" list; the result is sorted by timestamp.
StatusOr<std::vector<TimedFile>> ReadTimedFileList(const std::string& path);

// Greedy nearest-timestamp association (TUM associate.py): returns (index in a, index in b)
// pairs with |a - (b + offset)| < max_difference, sorted by a's index.
std::vector<std::pair<std::size_t, std::size_t>> AssociateTimestamps(const std::vector<double>& a,
                                                                     const std::vector<double>& b,
                                                                     double max_difference,
                                                                     double offset = 0.0);

struct TumFrameInfo {
  double timestamp = 0;  // the colour image's time, which names the frame
  double depth_timestamp = 0;
  std::string rgb_path;  // absolute or relative to the current folder
  std::string depth_path;
  std::optional<Pose> T_world_cam_gt;  // interpolated ground truth, if available
};

struct TumOptions {
  double max_time_difference = 0.02;  // seconds, colour-depth association
  double groundtruth_max_gap = 0.05;  // seconds between the gt samples around a frame
  // Depth file units per metre; 0 = take it from the camera (config or camera.yaml).
  double depth_map_factor = 0.0;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class TumSequence {
 public:
  // The 7-Scenes frame-per-file layout (see above): some frame-NNNNNN.color.png or .jpg with
  // its frame-NNNNNN.depth.png.
  static bool IsSevenScenesFolder(const std::string& folder);

  // `camera` comes from a config file; without one, the folder's camera.yaml is used, and
  // without that, the caller must pass a camera (see GuessCameraConfigName()).
  static StatusOr<TumSequence> Open(const std::string& folder,
                                    const std::optional<PinholeCamera>& camera,
                                    const TumOptions& options = {});

  std::size_t size() const { return frames_.size(); }
  const TumFrameInfo& frame(std::size_t i) const { return frames_[i]; }
  const std::string& folder() const { return folder_; }
  const PinholeCamera& camera() const { return camera_; }

  // The raw ground truth (may be empty), and the ground truth at frame timestamps.
  const Trajectory& groundtruth() const { return groundtruth_; }
  Trajectory GroundTruthAtFrames() const;

  // Loads colour (BGR) and depth (converted to uint16 mm, 0 where there is none). Fails with a
  // clear message on a missing, unreadable or wrongly typed image.
  StatusOr<RgbdFrame> LoadFrame(std::size_t i) const;

 private:
  std::string folder_;
  PinholeCamera camera_;
  double depth_map_factor_ = 5000.0;
  std::uint16_t no_depth_code_ = 0;  // a file value that means no depth, besides 0
  std::vector<TumFrameInfo> frames_;
  Trajectory groundtruth_;
};

// Converts a depth image in file units (depth_map_factor per metre) to uint16 millimetres.
cv::Mat DepthToMillimetres(const cv::Mat& raw, double depth_map_factor);

// A 3-channel image with its first and third channels exchanged (a new image): how colour
// files of a camera with Camera.RGB: 0 are read, and how ccmd_synth writes them.
cv::Mat SwapRedBlue(const cv::Mat& image);

// Name of the shipped config that matches a dataset folder: by its name
// ("rgbd_dataset_freiburg1_desk" -> "tum_fr1.yaml"), or by its layout (a 7-Scenes sequence ->
// "7scenes.yaml"); "" when neither says anything.
std::string GuessCameraConfigName(const std::string& folder);

}  // namespace ccmd
