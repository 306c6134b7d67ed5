#include "libccmd/sensors/v4l2_source.h"

#include <algorithm>
#include <cmath>
#include <set>
#include <sstream>

#include "libccmd/sensors/frame_pairing.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/string_util.h"

namespace ccmd {
namespace {

// Consecutive frames dropped without a partner (or damaged) before the source gives up:
// a few seconds' worth means the two nodes are not one camera or one clock.
constexpr int kMaxDropsInARowSeconds = 3;

std::string ModeList(const V4l2DeviceInfo& info) {
  std::set<std::string> listed;
  std::string text;
  for (const V4l2Mode& mode : info.modes) {
    const std::string item = FourccToString(mode.fourcc) + " " + std::to_string(mode.width) + "x" +
                             std::to_string(mode.height);
    if (!listed.insert(item).second) continue;
    if (!text.empty()) text += ", ";
    text += item;
    if (listed.size() >= 12) {
      text += ", ...";
      break;
    }
  }
  return text.empty() ? "nothing" : text;
}

bool Offers(const V4l2DeviceInfo& info, std::uint32_t fourcc, int width, int height) {
  return std::any_of(info.modes.begin(), info.modes.end(), [&](const V4l2Mode& m) {
    return m.fourcc == fourcc && m.width == width && m.height == height;
  });
}

}  // namespace

std::string V4l2SourceOptions::ToString() const {
  std::ostringstream out;
  out << "color=" << color_device << " depth=" << depth_device << " " << width << "x" << height
      << "@" << fps;
  if (color_width > 0) out << " color " << color_width << "x" << color_height;
  out << " color_format=" << color_format << " depth_unit=" << depth_unit_m << " m";
  if (!config.empty()) out << " config=" << config;
  return out.str();
}

StatusOr<V4l2SourceOptions> ParseV4l2Spec(const std::string& spec) {
  V4l2SourceOptions options;
  for (const std::string& item : Split(spec, ',')) {
    if (Trim(item).empty()) continue;
    const auto eq = item.find('=');
    if (eq == std::string::npos)
      return InvalidArgument("v4l2 option '" + item + "' is not key=value");
    const std::string key(Trim(item.substr(0, eq)));
    const std::string value(Trim(item.substr(eq + 1)));
    auto number = [&](double low, double high) -> StatusOr<double> {
      CCMD_ASSIGN_OR_RETURN(const double v, ParseDouble(value));
      if (!(v >= low && v <= high)) {
        return InvalidArgument("v4l2 option " + key + "=" + value + " outside [" +
                               std::to_string(low) + ", " + std::to_string(high) + "]");
      }
      return v;
    };
    if (key == "color" || key == "colour") {
      options.color_device = value;
    } else if (key == "depth") {
      options.depth_device = value;
    } else if (key == "config") {
      options.config = value;
    } else if (key == "color_format") {
      if (value != "auto" && value != "yuyv" && value != "mjpeg") {
        return InvalidArgument("v4l2 color_format must be auto, yuyv or mjpeg, not '" + value +
                               "'");
      }
      options.color_format = value;
    } else {
      StatusOr<double> v = Status::Ok();
      if (key == "width" || key == "height" || key == "color_width" || key == "color_height") {
        v = number(key.rfind("color", 0) == 0 ? 0 : 16, kMaxImageSide);
      } else if (key == "fps") {
        v = number(1, 1000);
      } else if (key == "depth_unit") {
        v = number(1e-6, 1);
      } else if (key == "timeout") {
        v = number(0.05, 600);
      } else if (key == "pair_tolerance") {
        v = number(0, 1);
      } else if (key == "buffers") {
        v = number(2, 32);
      } else {
        return InvalidArgument("unknown v4l2 option '" + key +
                               "' (color, depth, config, width, height, fps, color_width, "
                               "color_height, color_format, depth_unit, timeout, "
                               "pair_tolerance, buffers)");
      }
      if (!v.ok()) return v.status();
      if (key == "width") options.width = static_cast<int>(*v);
      if (key == "height") options.height = static_cast<int>(*v);
      if (key == "color_width") options.color_width = static_cast<int>(*v);
      if (key == "color_height") options.color_height = static_cast<int>(*v);
      if (key == "fps") options.fps = *v;
      if (key == "depth_unit") options.depth_unit_m = *v;
      if (key == "timeout") options.timeout_s = *v;
      if (key == "pair_tolerance") options.pair_tolerance_s = *v;
      if (key == "buffers") options.buffers = static_cast<int>(*v);
    }
  }
  if (options.color_device.empty() || options.depth_device.empty()) {
    return InvalidArgument(
        "v4l2 needs both nodes: v4l2:color=/dev/videoN,depth=/dev/videoM "
        "(ccmd_camera --list shows which node offers Z16 depth)");
  }
  if ((options.color_width > 0) != (options.color_height > 0)) {
    return InvalidArgument("v4l2: give both color_width and color_height, or neither");
  }
  return options;
}

StatusOr<std::uint32_t> ChooseColorFormat(const V4l2DeviceInfo& info, const std::string& wanted,
                                          int width, int height) {
  std::vector<std::uint32_t> candidates;
  if (wanted == "yuyv")
    candidates = {kFourccYuyv};
  else if (wanted == "mjpeg")
    candidates = {kFourccMjpeg};
  else
    candidates = {kFourccYuyv, kFourccMjpeg};
  for (const std::uint32_t fourcc : candidates) {
    if (Offers(info, fourcc, width, height)) return fourcc;
  }
  return Unsupported(info.path + " (" + info.card + ") offers no " +
                     (wanted == "auto" ? std::string("YUYV or MJPEG") : wanted) + " colour at " +
                     std::to_string(width) + "x" + std::to_string(height) + "; it offers " +
                     ModeList(info));
}

Status V4l2Source::StartStream(const std::string& path, std::uint32_t fourcc, int width, int height,
                               const V4l2SourceOptions& options, Stream* stream) {
  CCMD_ASSIGN_OR_RETURN(stream->format, stream->device->SetFormat(fourcc, width, height));
  CCMD_ASSIGN_OR_RETURN(const double fps, stream->device->SetFrameRate(options.fps));
  if (fps > 0 && std::fabs(fps - options.fps) > 0.5) {
    CCMD_LOG(WARNING) << path << ": asked for " << options.fps << " fps, the driver set " << fps;
  }
  if (stream->format.stride == 0 && fourcc != kFourccMjpeg) {
    stream->format.stride = width * 2;  // drivers may leave bytesperline 0 for packed formats
  }
  return stream->device->Start(options.buffers);
}

namespace {

PinholeCamera AtSize(const PinholeCamera& camera, int width, int height, const char* what) {
  if (camera.width == width && camera.height == height) return camera;
  CCMD_LOG(WARNING) << what << " intrinsics are for " << camera.width << "x" << camera.height
                    << ", the stream is " << width << "x" << height << ": scaling them";
  return camera.Resized(width, height);
}

}  // namespace

StatusOr<std::unique_ptr<V4l2Source>> V4l2Source::Open(
    const V4l2SourceOptions& options, const PinholeCamera& camera, const V4l2DeviceOpener& opener,
    const std::optional<DepthToColorCalibration>& registration) {
  std::unique_ptr<V4l2Source> source(new V4l2Source());
  source->options_ = options;
  if (source->options_.color_width <= 0) {
    source->options_.color_width = options.width;
    source->options_.color_height = options.height;
  }
  const V4l2SourceOptions& o = source->options_;
  if (registration) {
    // Frames get the colour camera's geometry at the depth stream's size.
    source->camera_ =
        AtSize(camera, o.color_width, o.color_height, "colour").Resized(o.width, o.height);
    source->registration_ = registration;
    source->registration_->depth = AtSize(registration->depth, o.width, o.height, "depth");
  } else {
    source->camera_ = AtSize(camera, o.width, o.height, "camera");
    CCMD_LOG(WARNING) << "v4l2: no Depth block in the camera config, so depth is not "
                         "registered to colour (two imagers: see docs/cameras.md)";
  }
  source->camera_.fps = o.fps;
  source->tolerance_ = o.pair_tolerance_s > 0 ? o.pair_tolerance_s : DefaultPairTolerance(o.fps);

  Stream& depth = source->depth_;
  depth.role = "depth";
  depth.path = o.depth_device;
  CCMD_ASSIGN_OR_RETURN(depth.device, opener(o.depth_device));
  CCMD_ASSIGN_OR_RETURN(const V4l2DeviceInfo depth_info, depth.device->Query());
  if (!depth_info.streaming_capture) {
    return Unsupported(o.depth_device + " (" + depth_info.card +
                       ") is not a streaming video capture node");
  }
  if (!Offers(depth_info, kFourccZ16, o.width, o.height)) {
    return Unsupported(o.depth_device + " (" + depth_info.card + ") offers no Z16 depth at " +
                       std::to_string(o.width) + "x" + std::to_string(o.height) + "; it offers " +
                       ModeList(depth_info) +
                       ". On a RealSense the depth node is the one that lists 'Z16 '.");
  }

  Stream& color = source->color_;
  color.role = "colour";
  color.path = o.color_device;
  CCMD_ASSIGN_OR_RETURN(color.device, opener(o.color_device));
  CCMD_ASSIGN_OR_RETURN(const V4l2DeviceInfo color_info, color.device->Query());
  if (!color_info.streaming_capture) {
    return Unsupported(o.color_device + " (" + color_info.card +
                       ") is not a streaming video capture node");
  }
  CCMD_ASSIGN_OR_RETURN(
      const std::uint32_t color_fourcc,
      ChooseColorFormat(color_info, o.color_format, o.color_width, o.color_height));

  CCMD_RETURN_IF_ERROR(StartStream(o.depth_device, kFourccZ16, o.width, o.height, o, &depth));
  CCMD_RETURN_IF_ERROR(
      StartStream(o.color_device, color_fourcc, o.color_width, o.color_height, o, &color));
  CCMD_LOG(INFO) << "v4l2: " << source->Describe();
  return source;
}

V4l2Source::~V4l2Source() {
  // Give back held buffers before the devices stop (harmless if they are gone).
  for (Stream* s : {&color_, &depth_}) {
    if (s->device) {
      if (s->held) s->device->Requeue(s->buffer.index).IgnoreError();
      s->device->Close();
    }
  }
}

Status V4l2Source::Fail(Status status) {
  failed_ = status;
  return status;
}

Status V4l2Source::Fetch(Stream* stream) {
  // Frames the driver flags as damaged are given back at once; a device that only
  // produces those for a few seconds is treated as lost.
  const int max_damaged = static_cast<int>(kMaxDropsInARowSeconds * std::max(1.0, options_.fps));
  for (int damaged = 0;; ++damaged) {
    StatusOr<V4l2Buffer> buffer = stream->device->Dequeue(options_.timeout_s);
    if (!buffer.ok()) {
      return Fail(buffer.status().WithContext("v4l2 " + stream->role + " " + stream->path));
    }
    if (stream->seen_sequence && buffer->sequence > stream->last_sequence + 1) {
      stats_.driver_gaps += buffer->sequence - stream->last_sequence - 1;
    }
    stream->seen_sequence = true;
    stream->last_sequence = buffer->sequence;
    if (!buffer->error) {
      stream->buffer = *buffer;
      stream->held = true;
      return Status::Ok();
    }
    ++stats_.damaged_dropped;
    CCMD_RETURN_IF_ERROR(Fail(stream->device->Requeue(buffer->index)));
    if (damaged >= max_damaged) {
      return Fail(Unavailable("v4l2 " + stream->role + " " + stream->path +
                              ": only damaged frames for " +
                              std::to_string(kMaxDropsInARowSeconds) + " s"));
    }
  }
}

Status V4l2Source::Release(Stream* stream) {
  if (!stream->held) return Status::Ok();
  stream->held = false;
  const Status status = stream->device->Requeue(stream->buffer.index);
  if (!status.ok()) return Fail(status.WithContext("v4l2 " + stream->role + " " + stream->path));
  return status;
}

Status V4l2Source::ConvertColor(const V4l2Buffer& buffer, cv::Mat* bgr) {
  const V4l2Format& f = color_.format;
  if (f.fourcc == kFourccMjpeg) {
    return mjpeg_.Decode(buffer.data, buffer.bytes_used, f.width, f.height, bgr);
  }
  return ConvertYuyvToBgr(buffer.data, buffer.bytes_used, {f.width, f.height, f.stride}, bgr);
}

Status V4l2Source::ConvertDepth(const V4l2Buffer& buffer, cv::Mat* depth_mm) {
  const V4l2Format& f = depth_.format;
  return ConvertZ16ToMillimetres(buffer.data, buffer.bytes_used, {f.width, f.height, f.stride},
                                 options_.depth_unit_m, depth_mm);
}

Status V4l2Source::Read(RgbdFrame* frame) {
  if (!failed_.ok()) return failed_;
  const int max_drops = static_cast<int>(kMaxDropsInARowSeconds * std::max(1.0, options_.fps) * 2);
  for (int drops = 0;; ++drops) {
    if (drops > max_drops) {
      std::ostringstream message;
      message.precision(6);
      message << std::fixed << "v4l2: colour and depth timestamps never came within "
              << tolerance_ * 1e3 << " ms of each other (last colour " << color_.buffer.timestamp
              << " s, depth " << depth_.buffer.timestamp << " s): are " << color_.path << " and "
              << depth_.path << " one camera?";
      return Fail(Unsupported(message.str()));
    }
    if (!color_.held) CCMD_RETURN_IF_ERROR(Fetch(&color_));
    if (!depth_.held) CCMD_RETURN_IF_ERROR(Fetch(&depth_));
    const PairStep step =
        NextPairStep(color_.buffer.timestamp, depth_.buffer.timestamp, tolerance_);
    if (step == PairStep::kAdvanceColor) {
      ++stats_.unpaired_dropped;
      CCMD_RETURN_IF_ERROR(Release(&color_));
      continue;
    }
    if (step == PairStep::kAdvanceDepth) {
      ++stats_.unpaired_dropped;
      CCMD_RETURN_IF_ERROR(Release(&depth_));
      continue;
    }
    // A pair: convert while the buffers are still ours, then give both back.
    cv::Mat bgr, depth_mm;
    const Status color_status = ConvertColor(color_.buffer, &bgr);
    const Status depth_status = ConvertDepth(depth_.buffer, &depth_mm);
    const double color_time = color_.buffer.timestamp, depth_time = depth_.buffer.timestamp;
    CCMD_RETURN_IF_ERROR(Release(&color_));
    CCMD_RETURN_IF_ERROR(Release(&depth_));
    if (!color_status.ok() || !depth_status.ok()) {
      // A damaged frame (truncated MJPEG, short Z16 buffer) is dropped, not fatal.
      ++stats_.damaged_dropped;
      CCMD_LOG(DEBUG) << "v4l2: dropping a damaged pair: "
                      << (color_status.ok() ? depth_status : color_status).ToString();
      continue;
    }
    frame->index = next_index_++;
    frame->timestamp = color_time;
    frame->depth_time_offset = depth_time - color_time;
    frame->bgr = ResizeColorToDepth(bgr, depth_mm.size());
    frame->depth_mm = registration_ ? RegisterDepthToColor(depth_mm, registration_->depth, camera_,
                                                           registration_->T_color_depth)
                                    : depth_mm;
    ++stats_.frames;
    return Status::Ok();
  }
}

std::string V4l2Source::Describe() const {
  std::ostringstream out;
  out << "v4l2 colour " << color_.path << " (" << FourccToString(color_.format.fourcc) << " "
      << color_.format.width << "x" << color_.format.height << ") depth " << depth_.path << " (Z16 "
      << depth_.format.width << "x" << depth_.format.height << ") " << options_.fps << " fps"
      << (registration_ ? ", depth registered to colour" : ", depth not registered");
  return out.str();
}

}  // namespace ccmd
