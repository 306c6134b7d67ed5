#pragma once

// Synthetic RGB-D sequences: a camera path through a SyntheticScene room, rendered frame by
// frame and written in the TUM RGB-D layout with exact ground truth.

#include <cstdint>
#include <functional>
#include <optional>
#include <string>

#include "libccmd/geometry/camera.h"
#include "libccmd/io/config.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/synth/renderer.h"
#include "libccmd/synth/scene.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

// A hand-held-like path: an ellipse around the room centre, looking outwards and ahead,
// with slow pitch, roll and height oscillations. One loop takes `loop_period_s`, so a
// sequence longer than that revisits its start (loop closures exist), and any two segments
// that share frames share views.
struct LoopPathOptions {
  double radius_x = 1.2;
  double radius_y = 1.0;
  double height = 1.35;
  double height_amplitude = 0.12;
  double loop_period_s = 16.0;
  double yaw_ahead_deg = 35.0;  // looking this far ahead of the outward direction
  double pitch_deg = -14.0;     // negative looks down
  double pitch_amplitude_deg = 8.0;
  double roll_amplitude_deg = 4.0;
  double start_time = 1.0;  // timestamp of frame 0

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

Trajectory MakeLoopPath(int num_frames, double fps, const LoopPathOptions& options = {});
// The path's pose `t` seconds after its start (MakeLoopPath samples it at the frame times).
Pose LoopPathPose(double t, const LoopPathOptions& options = {});

// The camera of synthetic sequences at a resolution (fx = fy = 525 at 640x480, scaled).
PinholeCamera SyntheticCamera(int width = 640, int height = 480);

struct SyntheticSequenceOptions {
  int frames = 600;
  int width = 640;
  int height = 480;
  double fps = 30.0;
  // Render through this camera instead of SyntheticCamera(width, height): its size, focal
  // lengths (either sign), distortion, frame rate, depth scale and colour order, as that
  // camera would record (width, height and fps above are then ignored).
  std::optional<PinholeCamera> camera;
  // A separate depth imager (a config's Depth block): depth images are rendered from it, at
  // its size and pose relative to the colour camera, and readers register them to colour.
  std::optional<DepthToColorCalibration> depth_camera;
  // The ground truth gives the depth imager's poses instead of the colour camera's, as a
  // recording posed by tracking its depth does (7-Scenes; the config's Trajectory.camera:
  // "depth", which camera.yaml then carries). Needs depth_camera.
  bool ground_truth_of_depth_camera = false;
  std::uint64_t seed = 1;
  bool noise = true;
  // The depth sensor's noise sigma(z) = depth_sigma_0 + depth_sigma_2 z^2 (metres, before
  // noise_scale): by default the renderer's structured-light model; a camera config's
  // DepthNoise keys give the camera's own (ccmd_synth --config), and camera.yaml then keeps them.
  double depth_sigma_0 = DepthSensorModel().sigma_0;
  double depth_sigma_2 = DepthSensorModel().sigma_2;
  // How the agents weigh each frame's depth for this sensor (Tracking.frameDepthWeight, a
  // config's choice for its sensor: ccmd_synth --config takes it); camera.yaml keeps it when set.
  double frame_depth_weight = 0.0;
  double noise_scale = 1.0;       // multiplies depth sigma and colour noise
  double surface_spacing = 0.01;  // ground-truth surface sampling (metres)
  // Motion blur: each colour image is the mean of the views over this exposure (seconds,
  // centred on the frame's time, at most a frame interval); depth and the ground truth are
  // those of the frame's time. 0: sharp images.
  double exposure_s = 0;
  // Depth taken this long after the colour image (seconds, under half a frame interval), as
  // by a sensor whose two streams are not synchronised (a Kinect v1: TUM RGB-D's depth comes
  // 10-15 ms after its colour): the depth image is the view at that time, depth.txt gives that
  // time, and the ground truth stays the colour image's.
  double depth_lag_s = 0;
  // Rolling shutter: the colour image's rows are read out one after another over this time
  // (seconds, first row to last, at most a frame interval), each row the view at its own time;
  // the frame's time and its ground truth are the middle row's. Depth stays a global shutter's
  // (one view at the frame's time, or depth_lag_s after it). 0: a global shutter.
  double rolling_shutter_s = 0;
  int threads = 0;        // 0: all cores
  RoomSceneOptions room;  // room.seed is overridden by seed
  LoopPathOptions path;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct SyntheticSequenceSummary {
  int frames = 0;
  std::size_t surface_points = 0;
  double seconds = 0;
  double render_ms_per_frame = 0;
};

// The camera a sequence with these options is rendered through.
PinholeCamera SequenceCamera(const SyntheticSequenceOptions& options);

// Writes rgb/ and depth/ (16-bit PNG at the camera's DepthMapFactor, 5000 per metre by
// default), rgb.txt, depth.txt, groundtruth.txt (the colour camera's poses), camera.yaml,
// surface.ply (the ground-truth surface seen by the sequence, with normals) and sequence.txt
// (the options used). `progress(done, total)` is called from the writer thread.
StatusOr<SyntheticSequenceSummary> WriteSyntheticSequence(
    const std::string& folder, const SyntheticSequenceOptions& options,
    const std::function<void(int, int)>& progress = nullptr);

// Render options for frame `index` of a sequence with these options (seeded per frame, so
// frames can be rendered in any order or in parallel and still be identical).
RenderOptions FrameRenderOptions(const SyntheticSequenceOptions& options, int index);

}  // namespace ccmd
