#pragma once

// Records frames in the TUM RGB-D layout, so any live run can be replayed (tum:DIR) and
// evaluated later:
//   rgb/<t>.png     8-bit colour, exactly as delivered (PNG is lossless)
//   depth/<t>.png   16-bit depth in the camera's DepthMapFactor units per metre
//   rgb.txt, depth.txt   "timestamp path" lines with TUM's comment header
//   camera.yaml     the camera (WriteCameraConfig), read back by TumSequence, and the
//                   sensor's keys given in the options (its depth noise)
// TumSequence reads the folder back frame for frame: same timestamps, same colour, same
// millimetres (exact whenever DepthMapFactor >= 1000, i.e. file units of 1 mm or finer).
//
// The lists are appended and flushed after each frame's images are written, so a run that
// is interrupted (Ctrl-C, crash, power) leaves a readable recording of every frame listed.
//
// Encoding the two PNGs of a 640x480 frame costs about a frame period at 30 fps at
// compression level 1 (half of one at level 0); with `queue_frames` > 0, writer threads do
// it and Write only copies the frame into a bounded queue. Lines are appended as frames
// complete, so with several writers the lists may be out of order; TumSequence sorts them.

#include <atomic>
#include <cstdio>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/bounded_queue.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct TumRecorderOptions {
  int png_compression = 1;      // 0..9: live recording favours speed over size
  bool overwrite = false;       // allow a folder that already holds a recording (lists restart)
  int queue_frames = 0;         // 0: write in Write(); N > 0: writer threads behind N frames
  int writer_threads = 1;       // with a queue
  bool drop_when_full = false;  // with a queue: drop (and count) rather than wait when full
  // Config lines appended to camera.yaml: the sensor's own keys (DepthNoise.*) of the config
  // the camera was opened with, so that the recording replays as that config tracked it.
  std::string config_keys;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class TumRecorder {
 public:
  // Creates the folders and camera.yaml. The camera's size must be the depth size of the
  // frames; its depth_map_factor sets the depth file units.
  static StatusOr<std::unique_ptr<TumRecorder>> Create(const std::string& folder,
                                                       const PinholeCamera& camera,
                                                       const TumRecorderOptions& options = {});
  ~TumRecorder();
  TumRecorder(const TumRecorder&) = delete;
  TumRecorder& operator=(const TumRecorder&) = delete;

  // Records one frame. Timestamps must increase (they name the files). Errors of the
  // writer thread are returned by the next Write or by Close.
  Status Write(const RgbdFrame& frame);

  // groundtruth.txt, when the source knows it (synthetic sequences).
  Status WriteGroundTruth(const Trajectory& trajectory);

  // Writes what is queued and closes the lists. Idempotent; the destructor calls it.
  Status Close();

  const std::string& folder() const { return folder_; }
  long frames_written() const { return frames_written_.load(); }
  long frames_dropped() const { return frames_dropped_.load(); }
  // Depth pixels too far for 16-bit file units (recorded as 0 = no depth).
  long clipped_depth_pixels() const { return clipped_.load(); }

 private:
  TumRecorder() = default;
  Status Check(const RgbdFrame& frame);
  Status WriteNow(const RgbdFrame& frame);
  void WriterLoop();
  void SetError(const Status& status);
  Status TakeError();

  std::string folder_;
  PinholeCamera camera_;
  TumRecorderOptions options_;
  std::FILE* rgb_list_ = nullptr;
  std::FILE* depth_list_ = nullptr;
  bool have_last_ = false;
  double last_timestamp_ = 0;
  std::string last_name_;
  bool closed_ = false;

  std::unique_ptr<BoundedQueue<RgbdFrame>> queue_;
  std::vector<std::thread> writers_;
  std::mutex list_mutex_;  // the two lists are appended together
  std::mutex error_mutex_;
  Status error_;
  std::atomic<long> frames_written_{0};
  std::atomic<long> frames_dropped_{0};
  std::atomic<long> clipped_{0};
};

// File name stem for a timestamp: "1305031102.175304" (six decimals, as TUM names files).
std::string TumTimestampName(double timestamp);

}  // namespace ccmd
