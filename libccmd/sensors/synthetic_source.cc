#include "libccmd/sensors/synthetic_source.h"

#include <algorithm>

#include "libccmd/util/string_util.h"

namespace ccmd {

SyntheticSource::SyntheticSource(const SyntheticSequenceOptions& options,
                                 std::optional<FrameRange> range)
    : options_(options),
      scene_([&] {
        RoomSceneOptions room = options.room;
        room.seed = options.seed;
        return SyntheticScene::MakeRoom(room);
      }()),
      camera_(SyntheticCamera(options.width, options.height)),
      path_(MakeLoopPath(options.frames, options.fps, options.path)),
      range_(range.value_or(FrameRange{0, options.frames - 1})),
      next_(range_.first) {
  camera_.fps = options.fps;
}

Status SyntheticSource::Read(RgbdFrame* frame) {
  if (next_ > range_.last) return EndOfStream();
  const RenderedFrame rendered =
      RenderFrame(scene_, camera_, path_[next_].T_world_cam, FrameRenderOptions(options_, next_));
  frame->index = next_;
  frame->timestamp = path_[next_].timestamp;
  frame->bgr = rendered.bgr;
  // Written sequences store depth at 5000 per metre and read it back rounded to mm; the
  // renderer already outputs whole millimetres, so both paths give the same values.
  frame->depth_mm = rendered.depth_mm;
  ++next_;
  return Status::Ok();
}

std::string SyntheticSource::Describe() const {
  return "synthetic room seed " + std::to_string(options_.seed) + " frames " +
         std::to_string(range_.first) + "-" + std::to_string(range_.last);
}

Trajectory SyntheticSource::GroundTruth() const {
  return Trajectory(path_.begin() + range_.first, path_.begin() + range_.last + 1);
}

StatusOr<SyntheticSequenceOptions> ParseSyntheticSpec(const std::string& spec) {
  SyntheticSequenceOptions options;
  if (Trim(spec).empty()) return options;
  for (const std::string& item : Split(spec, ',')) {
    const auto kv = Split(item, '=');
    if (kv.size() != 2) return InvalidArgument("synthetic option '" + item + "' is not key=value");
    const std::string key(Trim(kv[0]));
    auto value = ParseDouble(kv[1]);
    if (!value.ok()) return value.status().WithContext("synthetic option " + key);
    if (key == "frames")
      options.frames = static_cast<int>(*value);
    else if (key == "seed")
      options.seed = static_cast<std::uint64_t>(*value);
    else if (key == "width")
      options.width = static_cast<int>(*value);
    else if (key == "height")
      options.height = static_cast<int>(*value);
    else if (key == "noise")
      options.noise_scale = *value, options.noise = *value > 0;
    else if (key == "fps")
      options.fps = *value;
    else
      return InvalidArgument("unknown synthetic option '" + key +
                             "' (frames, seed, width, height, noise, fps)");
  }
  if (options.frames < 1 || options.width < 32 || options.height < 24 || !(options.fps > 0)) {
    return InvalidArgument("synthetic options out of range: " + spec);
  }
  return options;
}

}  // namespace ccmd
