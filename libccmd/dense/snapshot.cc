#include "libccmd/dense/snapshot.h"

#include <utility>

#include "libccmd/util/file_util.h"

namespace ccmd {

Status SnapshotOptions::Validate() const {
  if (folder.empty()) return InvalidArgument("snapshots need a folder");
  if (!std::isfinite(period_s)) return InvalidArgument("snapshot period must be finite");
  return Status::Ok();
}

void SnapshotOptions::Describe(OptionsWriter* out) const {
  out->Add("folder", folder);
  out->Add("period_s", period_s);
  out->Add("per_map", per_map);
  out->Add("per_agent", per_agent);
  out->Add("filter", filter == DenseFilter::kGlobal ? "global" : "other");
}

DenseSnapshotWriter::DenseSnapshotWriter(DenseMap* map, SnapshotOptions options)
    : map_(map), options_(std::move(options)) {}

std::string DenseSnapshotWriter::GlobalPath() const {
  return JoinPath(options_.folder, "dense_map.ply");
}

StatusOr<bool> DenseSnapshotWriter::Tick(double now_s) {
  if (!Due(now_s)) return false;
  has_last_ = true;
  last_s_ = now_s;  // also after a failure: a full disk is not retried in a tight loop
  CCMD_RETURN_IF_ERROR(WriteNow());
  return true;
}

Status DenseSnapshotWriter::WriteNow(DenseExportMode mode) {
  if (options_.folder.empty()) return InvalidArgument("snapshot folder is not set");
  CCMD_RETURN_IF_ERROR(MakeDirectories(options_.folder));
  CCMD_RETURN_IF_ERROR(
      map_->ExportPly(GlobalPath(), DenseSelection::Global(), options_.filter, mode));
  if (options_.per_map) {
    const std::string folder = JoinPath(options_.folder, "maps");
    CCMD_RETURN_IF_ERROR(MakeDirectories(folder));
    for (const MapId map : map_->Maps()) {
      const std::string path = JoinPath(folder, "map_" + std::to_string(map.value()) + ".ply");
      const Status s = map_->ExportPly(path, DenseSelection::Map(map), options_.filter, mode);
      // A map merged away between listing and export is not an error.
      if (!s.ok() && s.code() != StatusCode::kNotFound) return s;
    }
  }
  if (options_.per_agent) {
    const std::string folder = JoinPath(options_.folder, "agents");
    CCMD_RETURN_IF_ERROR(MakeDirectories(folder));
    for (const AgentId agent : map_->Agents()) {
      const std::string path = JoinPath(folder, "agent_" + std::to_string(agent.value()) + ".ply");
      CCMD_RETURN_IF_ERROR(
          map_->ExportPly(path, DenseSelection::Agent(agent), options_.filter, mode));
    }
  }
  ++written_;
  return Status::Ok();
}

}  // namespace ccmd
