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

  // Drops frames whose files cannot be read (counted in DroppedFrames()); Corrupt after 3 s of
  // them in a row, or when none of the range could be read.
  Status Read(RgbdFrame* frame) override;
  const PinholeCamera& camera() const override { return sequence_.camera(); }
  std::string Describe() const override;
  int FrameCount() const override { return range_.size(); }
  Trajectory GroundTruth() const override;
  long DroppedFrames() const override { return dropped_; }

  const TumSequence& sequence() const { return sequence_; }
  const FrameRange& range() const { return range_; }

 private:
  DatasetSource(TumSequence sequence, FrameRange range)
      : sequence_(std::move(sequence)), range_(range), next_(range.first) {}
  TumSequence sequence_;
  FrameRange range_;
  int next_;
  long delivered_ = 0, dropped_ = 0;
  std::string last_error_;
};

}  // namespace ccmd
