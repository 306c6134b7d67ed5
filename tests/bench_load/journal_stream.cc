#include "tests/bench_load/journal_stream.h"

#include <dirent.h>

#include <algorithm>
#include <cmath>

#include "libccmd/codec/wire_pose.h"
#include "libccmd/net/journal.h"
#include "libccmd/tracking/keyframe_message.h"

namespace ccmd::load {
namespace {

std::vector<std::string> JournalFiles(const std::string& folder) {
  std::vector<std::string> files;
  if (DIR* dir = ::opendir(folder.c_str())) {
    while (const dirent* e = ::readdir(dir)) {
      AgentId id;
      if (ParseJournalFileName(e->d_name, &id)) files.push_back(folder + "/" + e->d_name);
    }
    ::closedir(dir);
  }
  std::sort(files.begin(), files.end());
  return files;
}

StatusOr<JournalStream> ReadStream(const std::string& path) {
  JournalStream stream;
  JournalVisitor visitor;
  visitor.on_info = [&](const JournalAgentInfo& info) {
    stream.name = info.name;
    stream.camera = info.camera;
    return Status::Ok();
  };
  visitor.on_record = [&](const JournalRecord& record) -> Status {
    StreamMessage m;
    if (record.type == static_cast<std::uint8_t>(MessageType::kKeyframe)) {
      CCMD_ASSIGN_OR_RETURN(KeyframeMessage keyframe, ParseKeyframe(record.message));
      stream.keyframes++;
      stream.keyframe_bytes += record.message.size();
      stream.keyframe_ids = std::max(stream.keyframe_ids, keyframe.id.value() + 1);
      for (const NewMapPoint& p : keyframe.new_map_points) {
        stream.map_point_ids = std::max(stream.map_point_ids, p.id.value() + 1);
      }
      m.keyframe = std::make_shared<const KeyframeMessage>(std::move(keyframe));
    } else if (record.type == static_cast<std::uint8_t>(MessageType::kPoseUpdate)) {
      CCMD_ASSIGN_OR_RETURN(PoseUpdateMessage update, ParsePoseUpdate(record.message));
      m.pose_update = std::make_shared<const PoseUpdateMessage>(std::move(update));
    } else {
      return Status::Ok();  // a kind this tool does not replay
    }
    stream.messages.push_back(std::move(m));
    return Status::Ok();
  };
  CCMD_ASSIGN_OR_RETURN(const JournalScan scan, ScanJournalFile(path, visitor));
  if (!scan.has_info) return InvalidArgument(path + ": no agent description (empty journal)");
  if (stream.keyframes == 0) return InvalidArgument(path + ": no keyframes");
  return stream;
}

WirePose Moved(const Pose& T_offset, const WirePose& pose) {
  return PoseToWire(T_offset * PoseFromWire(pose));
}

}  // namespace

StatusOr<std::vector<JournalStream>> ReadJournalStreams(const std::string& folder) {
  const std::vector<std::string> files = JournalFiles(folder);
  if (files.empty()) return NotFound("no agent_*.journal files in " + folder);
  std::vector<JournalStream> streams;
  for (const std::string& path : files) {
    CCMD_ASSIGN_OR_RETURN(JournalStream stream, ReadStream(path));
    streams.push_back(std::move(stream));
  }
  return streams;
}

KeyframeMessage LapKeyframe(const JournalStream& stream, const KeyframeMessage& recorded,
                            std::uint32_t lap, const Pose& T_offset_recorded) {
  const std::uint32_t k = lap * stream.keyframe_ids, p = lap * stream.map_point_ids;
  KeyframeMessage m = recorded;
  m.id = KeyframeId(m.id.value() + k);
  if (m.parent) m.parent = KeyframeId(m.parent->value() + k);
  m.T_world_cam = Moved(T_offset_recorded, m.T_world_cam);
  for (WireKeypoint& kp : m.keypoints) {
    if (kp.map_point) kp.map_point = MapPointId(kp.map_point->value() + p);
  }
  for (NewMapPoint& point : m.new_map_points) point.id = MapPointId(point.id.value() + p);
  for (CovisibilityLink& link : m.covisibility)
    link.keyframe = KeyframeId(link.keyframe.value() + k);
  // Relative poses between the agent's keyframes do not depend on its frame.
  for (DepthLink& link : m.depth_links) link.keyframe = KeyframeId(link.keyframe.value() + k);
  return m;
}

PoseUpdateMessage LapPoseUpdate(const JournalStream& stream, const PoseUpdateMessage& recorded,
                                std::uint32_t lap, const Pose& T_offset_recorded) {
  PoseUpdateMessage m = recorded;
  for (PoseUpdateEntry& e : m.entries) {
    e.keyframe = KeyframeId(e.keyframe.value() + lap * stream.keyframe_ids);
    e.T_world_cam = Moved(T_offset_recorded, e.T_world_cam);
  }
  return m;
}

Pose AgentOffset(int index) {
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(0.7 * index, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(2.0 * index, -1.5 * index, 0.3 * index);
  return T;
}

}  // namespace ccmd::load
