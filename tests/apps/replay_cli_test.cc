// ccmd_replay end to end on a small synthetic sequence: a server and two agent processes over
// loopback TCP. The report's figures are checked against independent computations from the
// files the run wrote.

#include <algorithm>
#include <limits>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/string_util.h"
#include "tests/apps/replay_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(ReplayCliTest, TwoAgentsFuseAndTheReportMatchesTheFiles) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 200;
  synth.surface_spacing = 0.02;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
  std::string out;
  auto results = testing::RunReplay(dir.File("seq"), 2, "", dir.File("run"), &out);
  ASSERT_TRUE(results.ok()) << results.status().ToString() << "\n" << out;
  for (const char* key : {"ate_rmse_m", "maps_after_fusion", "recon_mean_m", "recon_hausdorff_m",
                          "atps_kBps", "akfs_kB", "akfr_hz", "agents"}) {
    ASSERT_TRUE(results->Has(key)) << key;
  }
  EXPECT_EQ(results->Get("maps_after_fusion")->number(), 1);
  ASSERT_EQ(results->Get("agents")->size(), 2u);
  for (const Json& a : results->Get("agents")->array()) {
    for (const char* key : {"ate_rmse_m", "keyframes", "bytes"}) EXPECT_TRUE(a.Has(key)) << key;
    EXPECT_GT(a.Get("keyframes")->number(), 5);
  }
  for (const char* file :
       {"run/report.md", "run/map.ply", "run/trajectory_fused.txt", "run/plots/trajectories.png",
        "run/plots/traffic.png", "run/plots/bytes_per_kind.png", "run/plots/map_top.png",
        "run/plots/map_view.png"}) {
    EXPECT_TRUE(FileExists(dir.File(file))) << file;
  }
  // Independent check: the fused ATE from the written trajectory against the ground truth.
  auto gt = ReadTumTrajectory(dir.File("seq/groundtruth.txt"));
  auto fused = ReadTumTrajectory(dir.File("run/trajectory_fused.txt"));
  ASSERT_TRUE(gt.ok() && fused.ok());
  auto ate = ComputeAte(*gt, *fused);
  ASSERT_TRUE(ate.ok());
  EXPECT_NEAR(results->Get("ate_rmse_m")->number(), ate->error.rmse, 1e-9);
  EXPECT_LT(ate->error.rmse, 0.01);
  // And the reconstruction error from the written map, aligned by the fit of the trajectory's
  // whole poses (centres and orientations), its arms as long as the median distance from the
  // map's points to their nearest keyframe.
  auto reference = ReadPly(dir.File("seq/surface.ply"));
  auto map = ReadPly(dir.File("run/map.ply"));
  ASSERT_TRUE(reference.ok() && map.ok() && map->size() > 0);
  std::vector<double> nearest;
  for (const auto& p : map->points) {
    double best = std::numeric_limits<double>::infinity();
    for (const auto& k : *fused) {
      best = std::min(best, (p.cast<double>() - k.T_world_cam.translation()).norm());
    }
    nearest.push_back(best);
  }
  std::nth_element(nearest.begin(), nearest.begin() + nearest.size() / 2, nearest.end());
  const double viewing_distance = nearest[nearest.size() / 2];
  EXPECT_GT(viewing_distance, 0.5);  // the room's walls are metres from the cameras
  // The report's is the median of an even pick of at most 20000 points.
  const double reported_distance = results->Get("recon_viewing_distance_m")->number();
  EXPECT_NEAR(reported_distance, viewing_distance, 0.02);
  AteOptions by_poses;
  by_poses.pose_alignment_below_spread_m = 1e9;
  by_poses.pose_alignment_arm_m = reported_distance;
  auto posed = ComputeAte(*gt, *fused, by_poses);
  ASSERT_TRUE(posed.ok());
  // On this loop both fits agree to a fraction of a degree.
  EXPECT_LT(Eigen::AngleAxisd(posed->alignment.R * ate->alignment.R.transpose()).angle(), 0.01);
  for (auto& p : map->points) p = (posed->alignment * p.cast<double>()).cast<float>();
  auto recon = ComputeReconstructionError(*reference, *map);
  ASSERT_TRUE(recon.ok());
  EXPECT_NEAR(results->Get("recon_mean_m")->number(), recon->mean, 1e-9);
  EXPECT_LT(recon->mean, 0.01);
  // Placed by ICP the map can be no worse, and on this exact room the keyframes' fit is
  // within a fraction of a degree of that placement.
  EXPECT_LE(results->Get("recon_mean_after_icp_m")->number(), recon->mean + 0.0005);
  EXPECT_LT(results->Get("recon_icp_turn_deg")->number(), 0.2);
  // Each agent's map error is that of the points its keyframes gave (the labels' top byte is
  // the agent's id, as the server numbered it); both agents gave points.
  auto ids = ReadJsonFile(dir.File("run/server_stats.json"));
  ASSERT_TRUE(ids.ok() && map->HasLabels());
  for (const Json& a : results->Get("agents")->array()) {
    const std::string name = a.Get("name")->string();
    const auto id = static_cast<std::uint32_t>(ids->Get("agent_ids")->Get(name)->number());
    PointCloud own;
    for (std::size_t i = 0; i < map->size(); ++i) {
      if (map->labels[i] >> 24 == id) own.points.push_back(map->points[i]);
    }
    ASSERT_GT(own.size(), 0u) << name;
    auto own_error = ComputeReconstructionError(*reference, own);
    ASSERT_TRUE(own_error.ok() && a.Has("map_mean_error_m")) << name;
    EXPECT_NEAR(a.Get("map_mean_error_m")->number(), own_error->mean, 1e-9) << name;
  }
  // Bandwidth: the agents' bytes add up to what the server counted per agent.
  auto stats = ReadJsonFile(dir.File("run/server_stats.json"));
  ASSERT_TRUE(stats.ok());
  double server_bytes = 0;
  for (const Json& a : stats->Get("transport")->Get("agents")->array()) {
    server_bytes += a.Get("messages")->Get("keyframe")->Get("bytes")->number() +
                    a.Get("messages")->Get("pose_update")->Get("bytes")->number();
  }
  double agent_bytes = 0;
  for (const char* name : {"agent1", "agent2"}) {
    auto s = ReadJsonFile(dir.File(std::string("run/agents/") + name + "_stats.json"));
    ASSERT_TRUE(s.ok());
    agent_bytes += s->Get("link")->Get("keyframe_bytes")->number() +
                   s->Get("link")->Get("pose_update_bytes")->number();
  }
  EXPECT_EQ(server_bytes, agent_bytes);
}

// A short excerpt of a slow camera split in two agents (as 50 frames of TUM fr2/desk): each
// agent makes a keyframe or two, and the maps may not fuse. Whatever the server did, a primary
// map with keyframes gets a fused ATE and a reconstruction error, and its agents are named.
TEST(ReplayCliTest, ShortSlowSplitStillReportsThePrimaryMap) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 30;
  synth.surface_spacing = 0.02;
  synth.path.loop_period_s = 400;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
  std::string out;
  auto results = testing::RunReplay(dir.File("seq"), 2, "", dir.File("run"), &out);
  ASSERT_TRUE(results.ok()) << results.status().ToString() << "\n" << out;
  ASSERT_GE(results->Get("fused_keyframes") ? results->Get("fused_keyframes")->number() : 0, 1)
      << out;
  ASSERT_TRUE(results->Has("ate_rmse_m")) << out;
  ASSERT_TRUE(results->Has("recon_mean_m")) << out;
  EXPECT_LT(results->Get("ate_rmse_m")->number(), 0.01);
  EXPECT_LT(results->Get("recon_mean_m")->number(), 0.01);
  const double maps = results->Get("maps_after_fusion")->number();
  EXPECT_EQ(results->Get("primary_map_agents")->size(), maps == 1 ? 2u : 1u);
  if (maps > 1) {
    EXPECT_NE(out.find("not every map fused"), std::string::npos) << out;
    auto report = ReadFileToString(dir.File("run/report.md"));
    ASSERT_TRUE(report.ok());
    EXPECT_NE(report->find("Not every map fused"), std::string::npos);
  }
}

// A recording with a gap (frames 70-139 of a loop left out) throws the agent where its map
// cannot relocalise it: it starts a new segment at its last pose, its own trajectory is off by
// the gap from then on (about 0.9 m), and the server joins the segments when the camera comes
// round to the start again. The map ends up as one. On an idle machine it is as accurate as a
// run without the gap (1-2 mm fused ATE, 3.5 mm reconstruction); with the test suite running
// beside it, 2 runs of about 30 gave 11 and 23 mm (the cause not isolated), so the bounds here
// are those of a segment that was placed, not the accuracy figures (docs/backend.md).
TEST(ReplayCliTest, AnAgentThatRestartsIsJoinedByTheServersLoop) {
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 280;
  synth.surface_spacing = 0.02;
  synth.path.loop_period_s = 8;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
  for (const char* list : {"seq/rgb.txt", "seq/depth.txt"}) {
    auto text = ReadFileToString(dir.File(list));
    ASSERT_TRUE(text.ok());
    std::string kept;
    int frame = 0;
    for (const std::string& line : Split(*text, '\n')) {
      if (line.empty()) continue;
      if (line[0] != '#' && (frame++ / 70) == 1) continue;
      kept += line + "\n";
    }
    ASSERT_TRUE(WriteFileAtomic(dir.File(list), kept).ok());
  }
  std::string out;
  auto results = testing::RunReplay(dir.File("seq"), 1, "", dir.File("run"), &out);
  ASSERT_TRUE(results.ok()) << results.status().ToString() << "\n" << out;
  EXPECT_GE(results->Get("loops")->number(), 1);
  const Json& agent = results->Get("agents")->array().front();
  EXPECT_EQ(agent.Get("restarts")->number(), 1) << out;
  EXPECT_EQ(results->Get("segments_placed")->number(), 1) << out;
  EXPECT_EQ(results->Get("segments_unplaced")->number(), 0) << out;
  EXPECT_GT(agent.Get("agent_frames_ate_rmse_m")->number(), 0.1) << "no gap to close";
  testing::ExpectFusedWithin(*results, 0.04, 0.03, out);
}

TEST(ReplayCliTest, RefusesAFolderThatHoldsARun) {
  testing::TempDir dir;
  ASSERT_TRUE(MakeDirectories(dir.File("run/journal")).ok());
  SyntheticSequenceOptions synth;
  synth.frames = 20;
  synth.width = 160;
  synth.height = 120;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
  std::string out;
  EXPECT_NE(testing::RunCommand(testing::ProgramPath("ccmd_replay") + " --dataset " +
                                    dir.File("seq") + " --agents 2 --out " + dir.File("run"),
                                &out),
            0);
  EXPECT_NE(out.find("already holds a run"), std::string::npos) << out;
}

}  // namespace
}  // namespace ccmd
