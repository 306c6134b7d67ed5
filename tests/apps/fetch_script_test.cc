// datasets/fetch_icl_nuim.sh on a local copy of the release's layout (CCMD_ICL_NUIM_URL points
// it at a folder of this test's): the office room's archive and ground truth become a TUM
// folder with frames and poses matched by index at 30 Hz, named so that the programs choose
// configs/icl_nuim.yaml for it; a scene it does not know is refused.

#include <gtest/gtest.h>

#include <fstream>
#include <sstream>

#include "libccmd/io/trajectory.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/subprocess.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

void Write(const std::string& path, const std::string& text) { std::ofstream(path) << text; }

// Runs the script with the release's site replaced by `site` (file://).
ProcessResult Fetch(const testing::TempDir& dir, const std::string& site,
                    const std::vector<std::string>& args) {
  std::vector<std::string> argv = {"/usr/bin/env", "CCMD_ICL_NUIM_URL=file://" + site, "bash",
                                   std::string(CCMD_DATASETS_DIR) + "/fetch_icl_nuim.sh"};
  argv.insert(argv.end(), args.begin(), args.end());
  auto p = Subprocess::Start(argv, dir.File("fetch.out"), dir.File("fetch.err"));
  EXPECT_TRUE(p.ok());
  return p.ok() ? p->Wait() : ProcessResult{};
}

// An archive laid out as the release's: frames by index, associations.txt with depth first,
// the ground truth (timestamps = frame indices) in the archive or beside it.
void MakeRelease(const testing::TempDir& dir, const std::string& archive, const std::string& gt,
                 bool gt_inside) {
  const std::string root = dir.File("release/" + archive);
  ASSERT_TRUE(MakeDirectories(root + "/rgb").ok());
  ASSERT_TRUE(MakeDirectories(root + "/depth").ok());
  ASSERT_TRUE(MakeDirectories(dir.File("site/VaFRIC")).ok());
  std::ostringstream associations, poses;
  for (int i = 0; i < 4; ++i) {
    Write(root + "/rgb/" + std::to_string(i) + ".png", "x");
    Write(root + "/depth/" + std::to_string(i) + ".png", "x");
    associations << i << " depth/" << i << ".png " << i << " rgb/" << i << ".png\n";
    if (i > 0) poses << i << " " << 0.1 * i << " 0 -2.5 0 0 0 1\n";  // frame 0 has none
  }
  Write(root + "/associations.txt", associations.str());
  Write(gt_inside ? root + "/" + gt : dir.File("site/VaFRIC/" + gt), poses.str());
  auto tar = Subprocess::Start(
      {"/usr/bin/tar", "-czf", dir.File("site/" + archive + ".tar.gz"), "-C", root, "."}, "", "");
  ASSERT_TRUE(tar.ok());
  ASSERT_EQ(tar->Wait().exit_code, 0);
}

TEST(FetchScriptTest, TheOfficeRoomBecomesATumFolderMatchedByIndex) {
  testing::TempDir dir;
  ASSERT_NO_FATAL_FAILURE(MakeRelease(dir, "traj0_frei_png", "traj0.gt.freiburg", true));
  const ProcessResult r =
      Fetch(dir, dir.File("site"), {"--dest", dir.File("out"), "--scene", "office", "0"});
  ASSERT_EQ(r.exit_code, 0) << *ReadFileToString(dir.File("fetch.err"));
  const std::string folder = dir.File("out/office_room_traj0_frei_png");
  EXPECT_EQ(GuessCameraConfigName(folder), "icl_nuim.yaml");
  EXPECT_EQ(*ReadFileToString(folder + "/rgb.txt"),
            "0.000000 rgb/0.png\n0.033333 rgb/1.png\n0.066667 rgb/2.png\n0.100000 rgb/3.png\n");
  EXPECT_EQ(*ReadFileToString(folder + "/depth.txt"),
            "0.000000 depth/0.png\n0.033333 depth/1.png\n0.066667 depth/2.png\n"
            "0.100000 depth/3.png\n");
  auto gt = ReadTumTrajectory(folder + "/groundtruth.txt");
  ASSERT_TRUE(gt.ok());
  ASSERT_EQ(gt->size(), 3u);
  EXPECT_NEAR(gt->front().timestamp, 1.0 / 30, 1e-6);
  EXPECT_NEAR(gt->back().T_world_cam.translation().x(), 0.3, 1e-9);  // frame 3's pose
  EXPECT_FALSE(FileExists(dir.File("out/traj0_frei_png.tar.gz")));   // the archive is gone
}

TEST(FetchScriptTest, ALivingRoomGroundTruthPublishedBesideTheArchiveIsFetched) {
  testing::TempDir dir;
  ASSERT_NO_FATAL_FAILURE(
      MakeRelease(dir, "living_room_traj2_frei_png", "livingRoom2.gt.freiburg", false));
  const ProcessResult r = Fetch(dir, dir.File("site"), {"--dest", dir.File("out"), "2"});
  ASSERT_EQ(r.exit_code, 0) << *ReadFileToString(dir.File("fetch.err"));
  auto gt = ReadTumTrajectory(dir.File("out/living_room_traj2_frei_png/groundtruth.txt"));
  ASSERT_TRUE(gt.ok());
  EXPECT_EQ(gt->size(), 3u);
}

TEST(FetchScriptTest, AnUnknownSceneIsRefused) {
  testing::TempDir dir;
  const ProcessResult r =
      Fetch(dir, dir.File("site"), {"--dest", dir.File("out"), "--scene", "kitchen", "0"});
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(ReadFileToString(dir.File("fetch.err"))->find("unknown scene kitchen"),
            std::string::npos);
}

}  // namespace
}  // namespace ccmd
