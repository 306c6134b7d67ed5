#include "libccmd/sensors/source_factory.h"

#include "libccmd/io/config.h"
#include "libccmd/sensors/dataset_source.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/string_util.h"

namespace ccmd {
namespace {

StatusOr<std::optional<FrameRange>> SegmentRange(int frames, const SourceOptions& options) {
  if (!options.segment) return std::optional<FrameRange>();
  CCMD_ASSIGN_OR_RETURN(const auto segments,
                        SplitWithOverlap(frames, options.segment->second, options.segment_overlap));
  return std::optional<FrameRange>(segments[options.segment->first - 1]);
}

}  // namespace

StatusOr<std::unique_ptr<RgbdSource>> OpenSource(const std::string& spec,
                                                 const SourceOptions& options) {
  const auto colon = spec.find(':');
  const std::string kind = spec.substr(0, colon);
  const std::string argument = colon == std::string::npos ? "" : spec.substr(colon + 1);

  if (kind == "tum" || kind == "dataset") {
    if (argument.empty()) return InvalidArgument("tum: needs a folder, e.g. tum:/data/fr1_desk");
    std::optional<PinholeCamera> camera;
    std::string config = options.camera_config;
    if (config.empty() && !FileExists(JoinPath(argument, "camera.yaml"))) {
      const std::string guess = GuessCameraConfigName(argument);
      if (!guess.empty() && !options.configs_dir.empty()) {
        config = JoinPath(options.configs_dir, guess);
        CCMD_LOG(INFO) << "camera config not given; using " << config << " for " << argument;
      }
    }
    if (!config.empty()) {
      CCMD_ASSIGN_OR_RETURN(camera, LoadCameraConfig(config));
    }
    // Open once to count frames, then with the segment range.
    CCMD_ASSIGN_OR_RETURN(auto whole, DatasetSource::Open(argument, camera));
    CCMD_ASSIGN_OR_RETURN(const auto range, SegmentRange(whole->FrameCount(), options));
    if (!range) return std::unique_ptr<RgbdSource>(std::move(whole));
    CCMD_ASSIGN_OR_RETURN(auto part, DatasetSource::Open(argument, camera, range));
    return std::unique_ptr<RgbdSource>(std::move(part));
  }
  if (kind == "synth") {
    CCMD_ASSIGN_OR_RETURN(const SyntheticSequenceOptions synth, ParseSyntheticSpec(argument));
    CCMD_ASSIGN_OR_RETURN(const auto range, SegmentRange(synth.frames, options));
    return std::unique_ptr<RgbdSource>(new SyntheticSource(synth, range));
  }
  return InvalidArgument("unknown source '" + spec + "' (expected tum:DIR or synth[:options])");
}

}  // namespace ccmd
