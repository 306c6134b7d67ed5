#include "libccmd/sensors/dataset_source.h"

#include <algorithm>

#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

// Unreadable frames in a row before a recording counts as unreadable: as for a camera, a few
// seconds' worth (sensors/v4l2_source.cc).
constexpr double kMaxDroppedInARowSeconds = 3;

}  // namespace

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

// A frame whose files cannot be read (missing, truncated, another format) is dropped, as a
// camera drops a damaged frame: the frames before and after it are still the recording.
Status DatasetSource::Read(RgbdFrame* frame) {
  const int max_in_a_row =
      static_cast<int>(kMaxDroppedInARowSeconds * std::max(1.0, sequence_.camera().fps));
  for (int in_a_row = 0;;) {
    if (next_ > range_.last) {
      if (delivered_ > 0 || dropped_ == 0) return EndOfStream();
      return Corrupt("none of the " + std::to_string(range_.size()) + " frames of " +
                     sequence_.folder() + " could be read; the last: " + last_error_);
    }
    const int i = next_++;
    auto loaded = sequence_.LoadFrame(static_cast<std::size_t>(i));
    if (loaded.ok()) {
      *frame = std::move(loaded).value();
      ++delivered_;
      return Status::Ok();
    }
    ++dropped_;
    last_error_ = loaded.status().message();
    CCMD_LOG(WARNING) << "dropping frame " << i << ": " << last_error_;
    if (++in_a_row >= max_in_a_row) {
      return Corrupt("frames " + std::to_string(i - in_a_row + 1) + "-" + std::to_string(i) +
                     " of " + sequence_.folder() + " (" + std::to_string(in_a_row) +
                     " in a row) could not be read; the last: " + last_error_);
    }
  }
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
