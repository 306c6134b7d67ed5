#include "libccmd/sensors/dataset_source.h"

namespace ccmd {

StatusOr<std::unique_ptr<DatasetSource>> DatasetSource::Open(
    const std::string& folder, const std::optional<PinholeCamera>& camera,
    std::optional<FrameRange> range, const TumOptions& options) {
  CCMD_ASSIGN_OR_RETURN(TumSequence sequence, TumSequence::Open(folder, camera, options));
  const int n = static_cast<int>(sequence.size());
  const FrameRange r = range.value_or(FrameRange{0, n - 1});
  if (r.first < 0 || r.last >= n || r.first > r.last) {
    return OutOfRange("frame range " + std::to_string(r.first) + "-" + std::to_string(r.last) +
                      " outside the " + std::to_string(n) + " frames of " + folder);
  }
  return std::unique_ptr<DatasetSource>(new DatasetSource(std::move(sequence), r));
}

Status DatasetSource::Read(RgbdFrame* frame) {
  if (next_ > range_.last) return EndOfStream();
  auto loaded = sequence_.LoadFrame(static_cast<std::size_t>(next_));
  if (!loaded.ok()) return loaded.status();
  *frame = std::move(loaded).value();
  ++next_;
  return Status::Ok();
}

std::string DatasetSource::Describe() const {
  return "dataset " + sequence_.folder() + " frames " + std::to_string(range_.first) + "-" +
         std::to_string(range_.last);
}

Trajectory DatasetSource::GroundTruth() const {
  Trajectory gt;
  for (int i = range_.first; i <= range_.last; ++i) {
    const TumFrameInfo& info = sequence_.frame(static_cast<std::size_t>(i));
    if (info.T_world_cam_gt) gt.push_back({info.timestamp, *info.T_world_cam_gt});
  }
  return gt;
}

}  // namespace ccmd
