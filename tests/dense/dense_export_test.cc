// PLY export, snapshots, and reading while another thread writes.

#include <gtest/gtest.h>

#include <dirent.h>

#include <algorithm>
#include <atomic>
#include <map>
#include <set>
#include <thread>

#include "libccmd/dense/dense_map.h"
#include "libccmd/dense/label.h"
#include "libccmd/dense/snapshot.h"
#include "libccmd/util/file_util.h"
#include "tests/dense/dense_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using dense_testing::MakeMap;
using dense_testing::PlaneKeyframe;
using dense_testing::SameCloud;
using dense_testing::StripPose;
using dense_testing::TestOptions;

std::unique_ptr<DenseMap> TwoAgents() {
  auto map = MakeMap(TestOptions(3));
  for (std::uint32_t id = 0; id < 5; ++id) {
    EXPECT_TRUE(map->AddKeyframe(PlaneKeyframe(AgentId(1), id, StripPose(id), 31)).ok());
    EXPECT_TRUE(map->AddKeyframe(PlaneKeyframe(AgentId(2), id, StripPose(id + 2), 32)).ok());
  }
  return map;
}

std::vector<std::string> FilesIn(const std::string& folder) {
  std::vector<std::string> names;
  DIR* dir = opendir(folder.c_str());
  if (dir == nullptr) return names;
  while (const dirent* e = readdir(dir)) {
    const std::string name = e->d_name;
    if (name != "." && name != "..") names.push_back(name);
  }
  closedir(dir);
  std::sort(names.begin(), names.end());
  return names;
}

TEST(DenseExportTest, PlyRoundTripsWithColoursAndLabels) {
  testing::TempDir dir;
  auto map = TwoAgents();
  for (const DenseFilter filter :
       {DenseFilter::kNone, DenseFilter::kWindow, DenseFilter::kGlobal}) {
    const std::string path = dir.File("map.ply");
    ASSERT_TRUE(map->ExportPly(path, DenseSelection::Global(), filter).ok());
    auto read = ReadPly(path);
    ASSERT_TRUE(read.ok()) << read.status().ToString();
    EXPECT_FALSE(read->HasNormals());
    EXPECT_TRUE(SameCloud(*read, *map->Extract(DenseSelection::Global(), filter)));
    const std::string data = *ReadFileToString(path);
    EXPECT_NE(data.find("property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
                        "property uchar green\nproperty uchar blue\nproperty uint label\n"),
              std::string::npos);
  }
  // Per agent: only that agent's labels.
  ASSERT_TRUE(map->ExportPly(dir.File("a2.ply"), DenseSelection::Agent(AgentId(2))).ok());
  const PointCloud a2 = *ReadPly(dir.File("a2.ply"));
  ASSERT_GT(a2.size(), 0u);
  for (const std::uint32_t label : a2.labels) EXPECT_EQ(DecodeLabel(label).agent, AgentId(2));
  EXPECT_EQ(map->ExportPly(dir.File("x.ply"), DenseSelection::Agent(AgentId(3))).code(),
            StatusCode::kNotFound);
  EXPECT_FALSE(FileExists(dir.File("x.ply")));
}

// The streamed export (at shutdown) is written as it is made, without the extracted cloud;
// what it writes must be that cloud point for point, as the copying export's is, with keyframes
// compacted out of the window, overlapping keyframes of two agents competing for voxels, and one of
// them moved after it was stored.
TEST(DenseExportTest, TheStreamedExportIsTheExtractedCloud) {
  testing::TempDir dir;
  DenseMapOptions options = TestOptions(2);
  options.compact_keyframes = true;
  auto map = MakeMap(options);
  for (std::uint32_t id = 0; id < 8; ++id) {
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(AgentId(1), id, StripPose(id), 31)).ok());
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(AgentId(2), id, StripPose(id + 1), 32)).ok());
  }
  ASSERT_GT(map->Stats().compact_keyframes, 0u);
  // A compacted keyframe turned and moved: its stored points, one per voxel before, can now
  // share voxels, where the first of them is the one kept.
  Pose moved = StripPose(3);
  moved.linear() = moved.linear() * RotationFromAngleAxis({0.15, -0.2, 0.1});
  moved.translation() += Eigen::Vector3d(0.013, -0.021, 0.007);
  ASSERT_TRUE(map->UpdateKeyframePose(GlobalKeyframeId{AgentId(2), KeyframeId(3)}, moved).ok());
  for (const DenseFilter filter :
       {DenseFilter::kNone, DenseFilter::kWindow, DenseFilter::kGlobal}) {
    for (const DenseSelection& selection :
         {DenseSelection::Global(), DenseSelection::Agent(AgentId(2))}) {
      auto extracted = map->Extract(selection, filter);
      ASSERT_TRUE(extracted.ok());
      ASSERT_GT(extracted->size(), 0u);
      for (const DenseExportMode mode : {DenseExportMode::kCopy, DenseExportMode::kStreamed}) {
        const std::string path = dir.File("map.ply");
        ASSERT_TRUE(map->ExportPly(path, selection, filter, mode).ok());
        auto read = ReadPly(path);
        ASSERT_TRUE(read.ok()) << read.status().ToString();
        EXPECT_TRUE(SameCloud(*read, *extracted))
            << static_cast<int>(filter) << " " << static_cast<int>(mode);
      }
    }
  }
}

TEST(DenseExportTest, GlobalFilterLeavesOnePointPerVoxel) {
  auto map = TwoAgents();
  const PointCloud global = *map->Extract(DenseSelection::Global(), DenseFilter::kGlobal);
  const PointCloud window = *map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
  const VoxelGrid grid(0.05);
  std::set<std::uint64_t> voxels_global, voxels_window;
  for (const auto& p : global.points) voxels_global.insert(grid.Key(p));
  for (const auto& p : window.points) voxels_window.insert(grid.Key(p));
  EXPECT_EQ(voxels_global.size(), global.size());
  EXPECT_EQ(voxels_global, voxels_window);
  EXPECT_LT(global.size(), window.size());  // the agents overlap
}

TEST(DenseExportTest, SnapshotsArePeriodicFinalAndLeaveNoTemporaryFiles) {
  testing::TempDir dir;
  auto map = TwoAgents();
  SnapshotOptions options;
  options.folder = dir.File("snap");
  options.period_s = 30;
  options.per_map = true;
  options.per_agent = true;
  DenseSnapshotWriter writer(map.get(), options);
  EXPECT_TRUE(*writer.Tick(100.0));   // the first tick writes
  EXPECT_FALSE(*writer.Tick(110.0));  // within the period
  EXPECT_TRUE(*writer.Tick(130.5));
  EXPECT_EQ(writer.snapshots_written(), 2);
  ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(AgentId(1), 9, StripPose(9), 31)).ok());
  ASSERT_TRUE(writer.WriteFinal().ok());
  EXPECT_EQ(writer.snapshots_written(), 3);

  EXPECT_EQ(FilesIn(options.folder), (std::vector<std::string>{"agents", "dense_map.ply", "maps"}));
  EXPECT_EQ(FilesIn(options.folder + "/maps"),
            (std::vector<std::string>{"map_1.ply", "map_2.ply"}));
  EXPECT_EQ(FilesIn(options.folder + "/agents"),
            (std::vector<std::string>{"agent_1.ply", "agent_2.ply"}));
  // The final snapshot has the keyframe added after the periodic ones.
  EXPECT_TRUE(SameCloud(*ReadPly(writer.GlobalPath()), *map->Extract(DenseSelection::Global())));

  DenseSnapshotWriter nowhere(map.get(), SnapshotOptions{});
  EXPECT_EQ(nowhere.WriteNow().code(), StatusCode::kInvalidArgument);
}

TEST(DenseExportTest, ExportsWhileAnotherThreadWritesSeeWholeKeyframes) {
  auto map = MakeMap(TestOptions(3));
  constexpr std::uint32_t kCount = 24;
  std::vector<DenseKeyframe> keyframes;
  for (std::uint32_t id = 0; id < kCount; ++id) {
    keyframes.push_back(PlaneKeyframe(AgentId(1), id, StripPose(id), 41));
  }
  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (std::uint32_t id = 0; id < kCount; ++id) {
      EXPECT_TRUE(map->AddKeyframe(keyframes[id]).ok());
      if (id > 2) {
        EXPECT_TRUE(map->UpdateKeyframePose({AgentId(1), KeyframeId(id - 2)}, StripPose(id)).ok());
      }
    }
    done = true;
  });
  int exports = 0;
  while (!done || exports < 3) {
    auto all = map->Extract(DenseSelection::Global(), DenseFilter::kNone);
    ASSERT_TRUE(all.ok());
    // Every keyframe appears whole: as many points under its label as it has.
    std::map<std::uint32_t, std::size_t> per_label;
    for (const std::uint32_t label : all->labels) ++per_label[label];
    for (const auto& [label, count] : per_label) {
      const DenseKeyframe& k = keyframes[DecodeLabel(label).keyframe.value()];
      ASSERT_EQ(count, static_cast<std::size_t>(cv::countNonZero(k.depth_mm)));
    }
    ++exports;
  }
  writer.join();
  // The end state equals a build with the final poses.
  auto scratch = MakeMap(TestOptions(3));
  for (std::uint32_t id = 0; id < kCount; ++id) {
    DenseKeyframe k = keyframes[id];
    if (id + 2 < kCount && id + 2 > 2) k.T_world_cam = StripPose(id + 2);
    ASSERT_TRUE(scratch->AddKeyframe(k).ok());
  }
  EXPECT_TRUE(SameCloud(*map->Extract(DenseSelection::Global(), DenseFilter::kWindow),
                        *scratch->Extract(DenseSelection::Global(), DenseFilter::kWindow)));
}

}  // namespace
}  // namespace ccmd
