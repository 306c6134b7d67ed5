#pragma once

// Periodic and final PLY snapshots of the dense map. The server calls Tick() from whichever
// thread it likes (a snapshot holds the store's lock only while copying points, see
// dense_map.h) and WriteFinal() at shutdown. Files are replaced atomically, so a crash leaves
// the previous complete snapshot, never a partial one:
//   <folder>/dense_map.ply            the global map
//   <folder>/maps/map_<id>.ply        per map, if per_map
//   <folder>/agents/agent_<id>.ply    per agent, if per_agent

#include <string>

#include "libccmd/dense/dense_map.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct SnapshotOptions {
  std::string folder;
  double period_s = 30.0;  // <= 0: only explicit and final snapshots
  bool per_map = false;
  bool per_agent = false;
  DenseFilter filter = DenseFilter::kGlobal;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Not thread-safe itself (it keeps the time of the last snapshot): use it from one thread.
class DenseSnapshotWriter {
 public:
  // `map` must outlive the writer.
  DenseSnapshotWriter(DenseMap* map, SnapshotOptions options);

  // Writes a snapshot if none was written yet or `period_s` has passed since the last one
  // (`now_s` on a monotonic clock, e.g. MonotonicSeconds()). Returns whether it wrote.
  StatusOr<bool> Tick(double now_s);
  // Whether Tick(now_s) would write.
  bool Due(double now_s) const {
    return !has_last_ || (options_.period_s > 0 && now_s - last_s_ >= options_.period_s);
  }
  // Writes a snapshot now (one on request, or the final one at shutdown, which no writer
  // waits for: it takes the export's lock longer for less memory).
  Status WriteNow(DenseExportMode mode = DenseExportMode::kCopy);
  Status WriteFinal() { return WriteNow(DenseExportMode::kStreamed); }

  int snapshots_written() const { return written_; }
  std::string GlobalPath() const;

 private:
  DenseMap* map_;
  SnapshotOptions options_;
  bool has_last_ = false;
  double last_s_ = 0;
  int written_ = 0;
};

}  // namespace ccmd
