#pragma once

// The one interface every frame producer implements: dataset replay, synthetic rendering,
// and live cameras (OpenNI2, V4L2). The agent's front-end only sees this.

#include <memory>
#include <string>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/status.h"

namespace ccmd {

class RgbdSource {
 public:
  virtual ~RgbdSource() = default;

  // Reads the next frame. Returns EndOfStream after the last frame, Unavailable for a
  // transient failure the caller may retry (e.g. a camera unplugged), other errors otherwise.
  // A damaged frame (a truncated image, a short buffer) is dropped, not returned as an error.
  virtual Status Read(RgbdFrame* frame) = 0;

  // Frames dropped so far as damaged or unreadable (a camera's also those left without a
  // partner from the other stream).
  virtual long DroppedFrames() const { return 0; }

  // Intrinsics of the depth image (colour is registered to it, possibly at a higher size).
  virtual const PinholeCamera& camera() const = 0;

  // "tum:/data/rgbd_dataset_freiburg1_desk frames 0-214", for logs.
  virtual std::string Describe() const = 0;

  // Number of frames this source will deliver, or -1 for a live source.
  virtual int FrameCount() const { return -1; }

  // True for cameras: frames come at the device's pace and cannot be replayed.
  virtual bool IsLive() const { return false; }

  // Ground truth at the frames of this source (empty when unknown).
  virtual Trajectory GroundTruth() const { return {}; }

  // The camera whose poses trajectories of this source's frames give, in the colour camera's
  // frame (the config's Trajectory.camera, config.h): identity for the colour camera.
  virtual Pose T_color_trajectory() const { return Pose::Identity(); }
};

}  // namespace ccmd
