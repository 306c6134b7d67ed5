#pragma once

#include <optional>

#include "libccmd/io/split.h"
#include "libccmd/sensors/rgbd_source.h"
#include "libccmd/synth/sequence.h"

namespace ccmd {

// Renders a synthetic sequence on the fly (no files): the frames are identical to those
// ccmd_synth writes with the same options.
class SyntheticSource : public RgbdSource {
 public:
  SyntheticSource(const SyntheticSequenceOptions& options, std::optional<FrameRange> range = {});

  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return camera_; }
  std::string Describe() const override;
  int FrameCount() const override { return range_.size(); }
  Trajectory GroundTruth() const override;

 private:
  SyntheticSequenceOptions options_;
  SyntheticScene scene_;
  PinholeCamera camera_;
  Trajectory path_;
  FrameRange range_;
  int next_;
};

// Parses "key=value,key=value" options of a synth: source spec
// (frames, seed, width, height, noise, fps).
StatusOr<SyntheticSequenceOptions> ParseSyntheticSpec(const std::string& spec);

}  // namespace ccmd
