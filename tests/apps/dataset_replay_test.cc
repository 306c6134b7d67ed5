// The programs on the real excerpts in ../shared/datasets with the shipped configs (skipped
// when absent): the agent alone and a two-agent split replay on ICL-NUIM, whose negative fy
// must travel from the config through agent, handshake, server and evaluation.

#include <gtest/gtest.h>

#include <sstream>
#include <string>
#include <vector>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "tests/apps/replay_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

const char kIcl[] = "iclnuim_office_traj0_0000_0449";

std::string Config(const std::string& name) { return std::string(CCMD_CONFIG_DIR) + "/" + name; }

// Frames [0, count) of a TUM-layout folder as a new folder: the lists cut, the images linked.
void MakeExcerpt(const std::string& from, const std::string& to, int count) {
  ASSERT_TRUE(MakeDirectories(to).ok());
  for (const char* list : {"rgb.txt", "depth.txt", "groundtruth.txt"}) {
    auto text = ReadFileToString(JoinPath(from, list));
    ASSERT_TRUE(text.ok()) << list;
    std::istringstream in(*text);
    std::string line, out;
    int kept = 0;
    while (std::getline(in, line)) {
      const bool comment = line.empty() || line[0] == '#';
      if (!comment && kept++ >= count) break;
      out += line + "\n";
    }
    ASSERT_TRUE(WriteFileAtomic(JoinPath(to, list), out).ok());
  }
  for (const char* images : {"rgb", "depth"}) {
    ASSERT_EQ(testing::RunCommand("ln -s " + JoinPath(from, images) + " " + JoinPath(to, images)),
              0);
  }
}

// The agent alone on 150 frames (5 s) of ICL-NUIM with configs/icl_nuim.yaml. The agent's
// accuracy over the 450 frames is about 2 cm; the first third of the path (0.7 m) should not
// be worse. A mirrored camera (fy > 0) gives decimetres.
TEST(DatasetReplayTest, AgentTracksIclNuimWithTheShippedConfig) {
  CCMD_REQUIRE_DATASET(dataset, kIcl);
  testing::TempDir dir;
  std::string out;
  ASSERT_EQ(
      testing::RunCommand(testing::ProgramPath("ccmd_agent") + " --source tum:" + dataset +
                              " --config " + Config("icl_nuim.yaml") +
                              " --offline --max-frames 150 --trajectory " + dir.File("traj.txt"),
                          &out),
      0)
      << out;
  auto trajectory = ReadTumTrajectory(dir.File("traj.txt"));
  auto gt = ReadTumTrajectory(JoinPath(dataset, "groundtruth.txt"));
  ASSERT_TRUE(trajectory.ok() && gt.ok());
  EXPECT_EQ(trajectory->size(), 150u);
  auto ate = ComputeAte(*gt, *trajectory);
  ASSERT_TRUE(ate.ok()) << ate.status().ToString();
  EXPECT_LT(ate->error.rmse, 0.02);
}

// Two agents on 180 frames of ICL-NUIM: the handshake takes the negative fy, the maps fuse,
// and the report's figures come from the primary map in the ground truth's frame. Bounds: the
// issue's target for the fused trajectory (2 cm); the map within 3 cm on average (that pose
// error, plus ICL's depth noise of a few millimetres and the 1 cm voxels; a mirrored map is off
// by decimetres).
TEST(DatasetReplayTest, TwoAgentsFuseOnIclNuim) {
  CCMD_REQUIRE_DATASET(dataset, kIcl);
  testing::TempDir dir;
  MakeExcerpt(dataset, dir.File("icl"), 180);
  std::string out;
  auto results =
      testing::RunReplay(dir.File("icl"), 2, Config("icl_nuim.yaml"), dir.File("run"), &out);
  ASSERT_TRUE(results.ok()) << results.status().ToString() << "\n" << out;
  testing::ExpectFusedWithin(*results, 0.02, 0.03, out);
}

}  // namespace
}  // namespace ccmd
