#pragma once

#include <optional>

#include "libccmd/io/split.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/rgbd_source.h"

namespace ccmd {

// Replays a TUM-layout folder (TUM RGB-D, ICL-NUIM TUM release, a 7-Scenes sequence, or a
// ccmd_synth sequence), optionally only a range of its frames (split replay).
class DatasetSource : public RgbdSource {
 public:
  static StatusOr<std::unique_ptr<DatasetSource>> Open(const std::string& folder,
                                                       const std::optional<PinholeCamera>& camera,
                                                       std::optional<FrameRange> range = {},
                                                       const TumOptions& options = {});

  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return sequence_.camera(); }
  std::string Describe() const override;
  int FrameCount() const override { return range_.size(); }
  Trajectory GroundTruth() const override;

  const TumSequence& sequence() const { return sequence_; }
  const FrameRange& range() const { return range_; }

 private:
  DatasetSource(TumSequence sequence, FrameRange range)
      : sequence_(std::move(sequence)), range_(range), next_(range.first) {}
  TumSequence sequence_;
  FrameRange range_;
  int next_;
};

}  // namespace ccmd
