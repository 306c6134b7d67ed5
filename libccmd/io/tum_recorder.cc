#include "libccmd/io/tum_recorder.h"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <opencv2/imgcodecs.hpp>

#include "libccmd/io/config.h"
#include "libccmd/util/file_util.h"

namespace ccmd {

Status TumRecorderOptions::Validate() const {
  if (png_compression < 0 || png_compression > 9)
    return InvalidArgument("PNG compression must be 0..9");
  if (queue_frames < 0) return InvalidArgument("queue frames must be >= 0");
  if (writer_threads < 1) return InvalidArgument("writer threads must be at least 1");
  return Status::Ok();
}

void TumRecorderOptions::Describe(OptionsWriter* out) const {
  out->Add("png_compression", png_compression);
  out->Add("overwrite", overwrite);
  out->Add("queue_frames", queue_frames);
  out->Add("writer_threads", writer_threads);
  out->Add("drop_when_full", drop_when_full);
}

std::string TumTimestampName(double timestamp) {
  char name[64];
  std::snprintf(name, sizeof(name), "%.6f", timestamp);
  return name;
}

namespace {

std::FILE* OpenList(const std::string& path, const char* what, Status* status) {
  std::FILE* file = std::fopen(path.c_str(), "w");
  if (file == nullptr) {
    *status = IoError("cannot create " + path + ": " + std::strerror(errno));
    return nullptr;
  }
  // The header TUM's own lists carry; TumSequence skips '#' lines.
  std::fprintf(file, "# %s images\n# recorded by ccmd\n# timestamp filename\n", what);
  std::fflush(file);
  return file;
}

}  // namespace

StatusOr<std::unique_ptr<TumRecorder>> TumRecorder::Create(const std::string& folder,
                                                           const PinholeCamera& camera,
                                                           const TumRecorderOptions& options) {
  CCMD_RETURN_IF_ERROR(camera.Validate().WithContext("recording camera"));
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (!(camera.depth_map_factor > 0) || camera.depth_map_factor > 65535) {
    return InvalidArgument("recording camera: DepthMapFactor " +
                           std::to_string(camera.depth_map_factor) + " out of range");
  }
  if (options.png_compression < 0 || options.png_compression > 9 || options.queue_frames < 0 ||
      options.writer_threads < 1 || options.writer_threads > 16) {
    return InvalidArgument("recorder options out of range");
  }
  if (!options.overwrite && FileExists(JoinPath(folder, "rgb.txt"))) {
    return InvalidArgument(folder + " already holds a recording (rgb.txt); choose a new folder");
  }
  CCMD_RETURN_IF_ERROR(MakeDirectories(JoinPath(folder, "rgb")));
  CCMD_RETURN_IF_ERROR(MakeDirectories(JoinPath(folder, "depth")));
  // Frames are recorded as the program sees them: colour in the usual channel order and
  // depth already registered to colour, so the file says so whatever the source's config.
  PinholeCamera written = camera;
  written.rgb = true;
  CCMD_RETURN_IF_ERROR(WriteCameraConfig(written, JoinPath(folder, "camera.yaml"), std::nullopt,
                                         options.config_keys));

  std::unique_ptr<TumRecorder> recorder(new TumRecorder());
  recorder->folder_ = folder;
  recorder->camera_ = camera;
  recorder->options_ = options;
  Status status;
  recorder->rgb_list_ = OpenList(JoinPath(folder, "rgb.txt"), "color", &status);
  if (!status.ok()) return status;
  recorder->depth_list_ = OpenList(JoinPath(folder, "depth.txt"), "depth", &status);
  if (!status.ok()) return status;
  if (options.queue_frames > 0) {
    recorder->queue_ = std::make_unique<BoundedQueue<RgbdFrame>>(options.queue_frames);
    for (int i = 0; i < options.writer_threads; ++i) {
      recorder->writers_.emplace_back([r = recorder.get()] { r->WriterLoop(); });
    }
  }
  return recorder;
}

TumRecorder::~TumRecorder() { Close().IgnoreError(); }

Status TumRecorder::Check(const RgbdFrame& frame) {
  if (frame.bgr.empty() || frame.bgr.type() != CV_8UC3) {
    return InvalidArgument("recorder: colour must be 8-bit BGR");
  }
  if (frame.depth_mm.empty() || frame.depth_mm.type() != CV_16UC1) {
    return InvalidArgument("recorder: depth must be 16-bit millimetres");
  }
  if (frame.depth_mm.cols != camera_.width || frame.depth_mm.rows != camera_.height) {
    return InvalidArgument("recorder: depth is " + std::to_string(frame.depth_mm.cols) + "x" +
                           std::to_string(frame.depth_mm.rows) + ", the camera " +
                           std::to_string(camera_.width) + "x" + std::to_string(camera_.height));
  }
  if (frame.bgr.cols < frame.depth_mm.cols || frame.bgr.rows < frame.depth_mm.rows) {
    return InvalidArgument("recorder: colour smaller than depth");
  }
  if (!std::isfinite(frame.timestamp) || !std::isfinite(frame.depth_time_offset)) {
    return InvalidArgument("recorder: timestamp not finite");
  }
  const std::string name = TumTimestampName(frame.timestamp);
  if (have_last_ && (frame.timestamp <= last_timestamp_ || name == last_name_)) {
    return InvalidArgument("recorder: timestamps must increase (" + name + " after " + last_name_ +
                           ")");
  }
  have_last_ = true;
  last_timestamp_ = frame.timestamp;
  last_name_ = name;
  return Status::Ok();
}

Status TumRecorder::WriteNow(const RgbdFrame& frame) {
  const std::string name = TumTimestampName(frame.timestamp);
  // Depth under its own time, as TUM RGB-D lists it: a sensor whose streams are not
  // synchronised plays back with the same offset.
  const std::string depth_name = TumTimestampName(frame.timestamp + frame.depth_time_offset);
  const std::string rgb_path = "rgb/" + name + ".png";
  const std::string depth_path = "depth/" + depth_name + ".png";

  // Millimetres to file units; a depth too far for 16 bits is recorded as "no depth"
  // rather than saturated to a wrong distance.
  cv::Mat depth_file;
  const double scale = camera_.depth_map_factor / 1000.0;
  if (scale == 1.0) {
    depth_file = frame.depth_mm;
  } else {
    depth_file.create(frame.depth_mm.size(), CV_16UC1);
    long clipped = 0;
    for (int y = 0; y < depth_file.rows; ++y) {
      const std::uint16_t* in = frame.depth_mm.ptr<std::uint16_t>(y);
      std::uint16_t* out = depth_file.ptr<std::uint16_t>(y);
      for (int x = 0; x < depth_file.cols; ++x) {
        const double units = std::round(in[x] * scale);
        if (units > 65535.0) {
          out[x] = 0;
          ++clipped;
        } else {
          out[x] = static_cast<std::uint16_t>(units);
        }
      }
    }
    clipped_ += clipped;
  }
  const std::vector<int> png = {cv::IMWRITE_PNG_COMPRESSION, options_.png_compression};
  try {
    if (!cv::imwrite(JoinPath(folder_, rgb_path), frame.bgr, png)) {
      return IoError("cannot write " + JoinPath(folder_, rgb_path));
    }
    if (!cv::imwrite(JoinPath(folder_, depth_path), depth_file, png)) {
      return IoError("cannot write " + JoinPath(folder_, depth_path));
    }
  } catch (const cv::Exception& e) {
    return IoError("writing frame " + name + ": " + e.msg);
  }
  // Listed only once both images are complete.
  std::lock_guard<std::mutex> lock(list_mutex_);
  if (std::fprintf(rgb_list_, "%s %s\n", name.c_str(), rgb_path.c_str()) < 0 ||
      std::fprintf(depth_list_, "%s %s\n", depth_name.c_str(), depth_path.c_str()) < 0 ||
      std::fflush(rgb_list_) != 0 || std::fflush(depth_list_) != 0) {
    return IoError("cannot append to the lists in " + folder_ + ": " + std::strerror(errno));
  }
  ++frames_written_;
  return Status::Ok();
}

void TumRecorder::SetError(const Status& status) {
  std::lock_guard<std::mutex> lock(error_mutex_);
  if (error_.ok()) error_ = status;
}

Status TumRecorder::TakeError() {
  std::lock_guard<std::mutex> lock(error_mutex_);
  return error_;
}

void TumRecorder::WriterLoop() {
  while (std::optional<RgbdFrame> frame = queue_->Pop()) {
    if (!TakeError().ok()) continue;  // after a failure, drain without writing
    const Status status = WriteNow(*frame);
    if (!status.ok()) SetError(status);
  }
}

Status TumRecorder::Write(const RgbdFrame& frame) {
  if (closed_) return InvalidArgument("recorder: closed");
  CCMD_RETURN_IF_ERROR(TakeError());
  CCMD_RETURN_IF_ERROR(Check(frame));
  if (!queue_) return WriteNow(frame);
  // A deep copy: live sources may reuse their buffers for the next frame.
  RgbdFrame copy;
  copy.index = frame.index;
  copy.timestamp = frame.timestamp;
  copy.depth_time_offset = frame.depth_time_offset;
  copy.bgr = frame.bgr.clone();
  copy.depth_mm = frame.depth_mm.clone();
  if (options_.drop_when_full) {
    if (!queue_->TryPush(std::move(copy))) ++frames_dropped_;
  } else {
    queue_->Push(std::move(copy));
  }
  return Status::Ok();
}

Status TumRecorder::WriteGroundTruth(const Trajectory& trajectory) {
  return WriteTumTrajectory(trajectory, JoinPath(folder_, "groundtruth.txt"));
}

Status TumRecorder::Close() {
  if (closed_) return TakeError();
  closed_ = true;
  if (queue_) {
    queue_->Close();  // the writers drain what is queued, then stop
    for (std::thread& writer : writers_) writer.join();
  }
  Status status = TakeError();
  for (std::FILE** list : {&rgb_list_, &depth_list_}) {
    if (*list != nullptr && std::fclose(*list) != 0 && status.ok()) {
      status = IoError("cannot close the lists in " + folder_);
    }
    *list = nullptr;
  }
  return status;
}

}  // namespace ccmd
