// The sampling-rate / selection table added to a replay's report and results.

#include "libccmd/system/replay_report.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <limits>
#include <optional>

#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/io/config.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/system/replay_markdown.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

Json RunResults(double colour, double depth, double points, double rgbd_keyframes,
                double keyframes) {
  Json j;
  j["colour_bytes"] = colour;
  j["depth_bytes"] = depth;
  j["map_points"] = points;
  j["rgbd_keyframes"] = rgbd_keyframes;
  j["keyframes_sent"] = keyframes;
  j["recon_mean_m"] = 0.005;
  j["ate_rmse_m"] = 0.003;
  j["maps_after_fusion"] = 1;
  return j;
}

double MedianOf(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// Two references back-projected from disjoint frames of ICL-NUIM (rendered, exact depth and
// poses) describe the same surfaces: measured to the fitted planes they agree to about a
// millimetre, where the nearest 1 cm sample alone is about 4 mm away. That floor sat under
// every reconstruction figure before the reference had normals.
TEST(ReplayReportTest, ReferenceCloudsFromOtherFramesAgreeToTheirPlanes) {
  CCMD_REQUIRE_DATASET(folder, "iclnuim_office_traj0_0000_0449");
  auto camera = LoadCameraConfig(std::string(CCMD_CONFIG_DIR) + "/icl_nuim.yaml");
  ASSERT_TRUE(camera.ok()) << camera.status().ToString();
  auto dataset = TumSequence::Open(folder, *camera);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ReferenceOptions options;
  // Every 10th frame alone, so that the two take no frame in common.
  options.max_move_m = options.max_turn_deg = std::numeric_limits<double>::infinity();
  auto first = LoadOrBuildReference(*dataset, options, nullptr);
  options.first = 5;
  auto second = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(first.ok() && second.ok());
  ASSERT_TRUE(first->HasNormals());
  auto error = ComputeReconstructionError(*first, *second);
  ASSERT_TRUE(error.ok());
  EXPECT_TRUE(error->point_to_plane);
  EXPECT_GT(error->mean_point_to_point, 0.003);
  EXPECT_LT(error->mean, 0.002);
}

// A reference built at half resolution from exact depth and poses lies on the true surface:
// each of its depths is the one at its pixel's centre. Taking a block's top-left pixel (half a
// pixel off the resized camera's ray) put half its points 1.6 mm or more off the surface on
// this room, whose floor and cabinets the 320x240 camera sees obliquely (now 0.3 mm).
TEST(ReplayReportTest, AHalfResolutionReferenceLiesOnTheSurface) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 4;
  o.width = 320;
  o.height = 240;
  o.noise = false;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  auto surface = ReadPly(dir.File("surface.ply"));
  ASSERT_TRUE(surface.ok()) << surface.status().ToString();
  ASSERT_EQ(std::rename(dir.File("surface.ply").c_str(), dir.File("truth.ply").c_str()), 0);
  auto dataset = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ReferenceOptions options;
  options.stride = 1;
  ASSERT_EQ(options.downsample, 2);
  auto reference = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(reference.ok()) << reference.status().ToString();
  auto error = ComputeReconstructionError(*reference, AsReferenceSurface(*std::move(surface)));
  ASSERT_TRUE(error.ok());
  // The median: surfaces the renderer saw only at grazing angles are missing from the
  // truth, and their points dominate the mean.
  EXPECT_LT(error->median, 0.0006);
}

// With a Depth block the ground-truth reference is built from registered depth, as the agents
// see it: registration by a pure offset t moves every point by t in the camera frame.
TEST(ReplayReportTest, ReferenceCloudUsesTheDepthRegistration) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 1;
  o.width = 160;
  o.height = 120;
  o.noise = false;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  ASSERT_EQ(std::remove(dir.File("surface.ply").c_str()),
            0);  // build the reference from ground truth
  auto dataset = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ReferenceOptions options;
  options.downsample = 1;
  options.voxel_m = 0.005;
  auto plain = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.status().ToString();

  DepthToColorCalibration calibration;
  calibration.depth = dataset->camera();
  const Eigen::Vector3d t(0.04, 0, 0);
  calibration.T_color_depth.translation() = t;
  options.registration = calibration;
  auto registered = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(registered.ok()) << registered.status().ToString();
  ASSERT_GT(registered->size(), plain->size() / 2);

  const Pose T_world_cam = *dataset->frame(0).T_world_cam_gt;
  PointCloud moved_back = *registered;
  for (Eigen::Vector3f& p : moved_back.points) p -= (T_world_cam.linear() * t).cast<float>();
  EXPECT_LT(MedianOf(NearestDistances(moved_back, *plain)), 0.004);
  EXPECT_GT(MedianOf(NearestDistances(*registered, *plain)), 0.02);

  // Ground truth of the depth camera (7-Scenes; the config's Trajectory.camera): the registered
  // depth goes to ground truth * T_color_depth^-1, where the colour camera was, and the cloud is
  // the depth camera's own view at the ground-truth pose, as the unregistered depth gives it.
  options.T_color_trajectory = calibration.T_color_depth;
  auto depth_posed = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(depth_posed.ok()) << depth_posed.status().ToString();
  EXPECT_LT(MedianOf(NearestDistances(*depth_posed, *plain)), 0.004);
  options.T_color_trajectory = Pose::Identity();

  calibration.depth = dataset->camera().Resized(80, 60);
  options.registration = calibration;
  EXPECT_EQ(LoadOrBuildReference(*dataset, options, nullptr).status().code(),
            StatusCode::kInvalidArgument);
}

// A sensor whose depth comes after its colour, with the agents moving it to the colour image's
// time: each depth image is placed where the ground truth puts the camera at the depth's own time.
// Turning at 72 degrees a second, 1/90 s moves the view by 0.8 degrees, about 3 cm on the walls, so
// the depth placed at the colour image's pose would miss the reference the same frames give without
// the lag.
TEST(ReplayReportTest, ReferenceCloudPlacesLateDepthAtItsOwnTime) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 3;  // the last depth has no ground truth after it and is left out
  o.width = 160;
  o.height = 120;
  o.noise = false;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  o.path.loop_period_s = 5;
  SyntheticSequenceOptions late = o;
  late.depth_lag_s = 1.0 / 90;
  ReferenceOptions options;
  options.downsample = 1;
  options.voxel_m = 0.005;
  options.depth_at_own_time = true;  // as camera.yaml of a rendered sequence says
  std::vector<PointCloud> clouds;
  for (const auto& [name, sequence_options] : {std::pair{"on_time", o}, std::pair{"late", late}}) {
    ASSERT_TRUE(WriteSyntheticSequence(dir.File(name), sequence_options).ok());
    ASSERT_EQ(std::remove(dir.File(std::string(name) + "/surface.ply").c_str()), 0);
    auto dataset = TumSequence::Open(dir.File(name), std::nullopt);
    ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
    options.first = 0;
    options.stride = 1;
    auto cloud = LoadOrBuildReference(*dataset, options, nullptr);
    ASSERT_TRUE(cloud.ok()) << cloud.status().ToString();
    clouds.push_back(*cloud);
  }
  ASSERT_GT(clouds[1].size(), clouds[0].size() / 3);
  EXPECT_LT(MedianOf(NearestDistances(clouds[1], clouds[0])), 0.004);
}

// A reference covers what the recording saw however far apart its frames are: one taken
// every 10th frame of a camera going round the room in 12 frames (every 10th frame of a
// recording, say) would see two of its views and leave the map's points elsewhere measured to
// far-off samples. Frames are taken by the camera's way, so nearly all of what every frame
// sees is in it; on a slow camera they are as few as before.
TEST(ReplayReportTest, ReferenceTakesFramesByTheCamerasWay) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 12;
  o.width = 160;
  o.height = 120;
  o.noise = false;
  o.path.loop_period_s = 0.4;  // 30 degrees a frame at 30 Hz
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("fast"), o).ok());
  ASSERT_EQ(std::remove(dir.File("fast/surface.ply").c_str()), 0);
  auto fast = TumSequence::Open(dir.File("fast"), std::nullopt);
  ASSERT_TRUE(fast.ok()) << fast.status().ToString();
  ReferenceOptions options;
  std::string source;
  auto reference = LoadOrBuildReference(*fast, options, &source);
  ASSERT_TRUE(reference.ok()) << reference.status().ToString();
  EXPECT_NE(source.find("from 12 ground-truth frames"), std::string::npos) << source;
  options.stride = 1;
  auto every_frame = LoadOrBuildReference(*fast, options, nullptr);
  ASSERT_TRUE(every_frame.ok()) << every_frame.status().ToString();
  auto coverage = ComputeReconstructionError(*every_frame, *reference);
  ASSERT_TRUE(coverage.ok());
  EXPECT_GT(coverage->completeness, 0.99);

  o.frames = 30;
  o.path.loop_period_s = 400;  // 1 mm and under a degree a frame
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("slow"), o).ok());
  ASSERT_EQ(std::remove(dir.File("slow/surface.ply").c_str()), 0);
  auto slow = TumSequence::Open(dir.File("slow"), std::nullopt);
  ASSERT_TRUE(slow.ok()) << slow.status().ToString();
  options.stride = 10;
  ASSERT_TRUE(LoadOrBuildReference(*slow, options, &source).ok());
  EXPECT_NE(source.find("from 3 ground-truth frames"), std::string::npos) << source;
}

// The files a server leaves when two agents did not fuse (a short excerpt of a slow camera, as
// TUM fr2/desk in 50 frames): the primary map is agent2's with two keyframes close together,
// agent1 kept a map of its own with one. The primary map's frame is not the ground truth's.
// `stats` is its server_stats.json; the evaluation's results go to `results`.
void EvaluateTwoAgentRun(const testing::TempDir& dir, const Json& stats,
                         std::optional<StatusOr<Json>>* results) {
  SyntheticSequenceOptions o;
  o.frames = 8;
  o.width = 160;
  o.height = 120;
  o.noise = false;
  o.surface_spacing = 0.02;
  o.path.loop_period_s = 400;  // nearly still: keyframes 4 mm apart
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), o).ok());
  auto dataset = TumSequence::Open(dir.File("seq"), std::nullopt);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  const std::string run = dir.File("run");
  ASSERT_TRUE(MakeDirectories(JoinPath(run, "agents")).ok());

  // Map frames: the primary map's origin is agent2's first keyframe (frame 4), agent1's its
  // frame 0, as an agent's map starts where the agent does.
  auto in_frame_of = [&](int origin, std::vector<int> frames) {
    const Pose T_map_world = dataset->frame(origin).T_world_cam_gt->inverse();
    Trajectory t;
    for (int f : frames)
      t.push_back({dataset->frame(f).timestamp, T_map_world * *dataset->frame(f).T_world_cam_gt});
    return t;
  };
  const Trajectory primary = in_frame_of(4, {4, 7});
  ASSERT_TRUE(WriteTumTrajectory(primary, JoinPath(run, "trajectory_fused.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(primary, JoinPath(run, "trajectory_agent2.txt")).ok());
  ASSERT_TRUE(WriteTumTrajectory(in_frame_of(0, {0}), JoinPath(run, "trajectory_agent1.txt")).ok());
  // The primary map's dense points: frame 5's exact depth, in the primary map's frame.
  auto frame = dataset->LoadFrame(5);
  ASSERT_TRUE(frame.ok());
  const Pose T_map_cam =
      dataset->frame(4).T_world_cam_gt->inverse() * *dataset->frame(5).T_world_cam_gt;
  PointCloud map;
  for (int v = 0; v < frame->depth_mm.rows; v += 2) {
    for (int u = 0; u < frame->depth_mm.cols; u += 2) {
      const double z = frame->depth_mm.at<std::uint16_t>(v, u) * 1e-3;
      if (z > 0)
        map.points.push_back((T_map_cam * dataset->camera().BackProject(u, v, z)).cast<float>());
    }
  }
  ASSERT_TRUE(WritePly(map, JoinPath(run, "map.ply")).ok());
  ASSERT_TRUE(WriteJsonFile(stats, JoinPath(run, "server_stats.json")).ok());
  // agent1's camera read twice as noisy as its config's model, agent2's as its model.
  for (const auto& [name, ratio] : {std::pair{"agent1", 2.04}, std::pair{"agent2", 0.98}}) {
    Json agent_stats;
    agent_stats["frames"] = 4;
    agent_stats["depth_noise_ratio"] = ratio;
    ASSERT_TRUE(
        WriteJsonFile(agent_stats, JoinPath(run, std::string("agents/") + name + "_stats.json"))
            .ok());
  }
  ReplayRunInfo info;
  info.agents = 2;
  info.segments = {{0, 4}, {4, 7}};
  results->emplace(EvaluateReplay(run, *dataset, info, ReferenceOptions()));
}

// The server's word on its maps: how many, map 1 primary, and which map each agent is in.
Json MapStats(int maps, int map_of_agent1, int map_of_agent2) {
  Json stats;
  stats["backend"]["maps"] = maps;
  stats["primary_map"] = 1;
  stats["agent_maps"]["agent1"] = map_of_agent1;
  stats["agent_maps"]["agent2"] = map_of_agent2;
  return stats;
}

TEST(ReplayReportTest, UnfusedRunStillReportsThePrimaryMapAndNamesItsAgents) {
  testing::TempDir dir;
  const Json stats = MapStats(2, 2, 1);
  std::optional<StatusOr<Json>> evaluated;
  EvaluateTwoAgentRun(dir, stats, &evaluated);
  ASSERT_TRUE(evaluated.has_value());
  StatusOr<Json>& results = *evaluated;
  const std::string run = dir.File("run");
  ASSERT_TRUE(results.ok()) << results.status().ToString();
  // Two keyframes 4 mm apart cannot fix a rotation by their positions: aligned by their poses,
  // the exact trajectory comes out exact, and the map within the depth's whole millimetres and
  // the reference's 2 cm sampling at surface edges; a map tilted by a degree would be off by
  // centimetres at these 1-3 m.
  ASSERT_TRUE(results->Has("ate_rmse_m"));
  EXPECT_LT(results->Get("ate_rmse_m")->number(), 1e-6);
  EXPECT_EQ(results->Get("ate_aligned_by")->string(), "poses");
  ASSERT_TRUE(results->Has("recon_mean_m"));
  EXPECT_LT(results->Get("recon_mean_m")->number(), 0.003);
  EXPECT_FALSE(results->Get("all_maps_fused")->boolean(true));
  ASSERT_EQ(results->Get("primary_map_agents")->size(), 1u);
  EXPECT_EQ(results->Get("primary_map_agents")->array()[0].string(), "agent2");
  const Json& agent1 = results->Get("agents")->array()[0];
  EXPECT_FALSE(agent1.Get("in_primary_map")->boolean(true));
  ASSERT_TRUE(agent1.Has("ate_rmse_m"));  // one keyframe in its own map: still a figure
  EXPECT_TRUE(results->Get("agents")->array()[1].Get("in_primary_map")->boolean());
  auto report = ReadFileToString(JoinPath(run, "report.md"));
  ASSERT_TRUE(report.ok());
  EXPECT_NE(report->find("Not every map fused"), std::string::npos) << *report;
  EXPECT_NE(report->find("which holds agent2; agent1 kept its own map:"), std::string::npos)
      << *report;
  EXPECT_NE(report->find("| agent1 | 0-4 | own |"), std::string::npos) << *report;
  // The agents' depth-noise check: the noisy camera is named, the other not.
  EXPECT_NE(report->find("agent1's depth measured 2.0 times as noisy as its config's"),
            std::string::npos)
      << *report;
  EXPECT_EQ(report->find("agent2's depth measured"), std::string::npos) << *report;
}

// One map, but agent1's keyframes all wait unplaced in it (its map fused with the primary one
// through a restarted segment no loop placed): it is in none of the primary map's outputs, and
// the report must not say that every map fused.
TEST(ReplayReportTest, AnAgentWaitingUnplacedInThePrimaryMapIsNotCountedAsFused) {
  testing::TempDir dir;
  Json stats = MapStats(1, 1, 1);
  stats["agent_placed_keyframes"]["agent1"] = 0;
  stats["agent_placed_keyframes"]["agent2"] = 2;
  std::optional<StatusOr<Json>> evaluated;
  EvaluateTwoAgentRun(dir, stats, &evaluated);
  ASSERT_TRUE(evaluated.has_value());
  const StatusOr<Json>& results = *evaluated;
  ASSERT_TRUE(results.ok()) << results.status().ToString();
  EXPECT_FALSE(results->Get("all_maps_fused")->boolean(true));
  ASSERT_EQ(results->Get("primary_map_agents")->size(), 1u);
  EXPECT_EQ(results->Get("primary_map_agents")->array()[0].string(), "agent2");
  EXPECT_FALSE(results->Get("agents")->array()[0].Get("in_primary_map")->boolean(true));
  auto report = ReadFileToString(JoinPath(dir.File("run"), "report.md"));
  ASSERT_TRUE(report.ok());
  EXPECT_NE(report->find("the keyframes of agent1 wait unplaced"), std::string::npos) << *report;
  EXPECT_EQ(report->find(" kept "), std::string::npos) << *report;
  EXPECT_NE(report->find("| agent1 | 0-4 | unplaced |"), std::string::npos) << *report;
}

// report.md says nothing results.json does not hold: written again from the results file
// alone, its sections up to CPU come out as the evaluation wrote them.
TEST(ReplayReportTest, ReportIsWrittenFromTheResultsFileAlone) {
  testing::TempDir dir;
  std::optional<StatusOr<Json>> evaluated;
  EvaluateTwoAgentRun(dir, MapStats(2, 2, 1), &evaluated);
  ASSERT_TRUE(evaluated.has_value() && evaluated->ok());
  auto saved = ReadJsonFile(JoinPath(dir.File("run"), "results.json"));
  ASSERT_TRUE(saved.ok()) << saved.status().ToString();
  ReplayRunInfo info;
  info.agents = 2;
  info.segments = {{0, 4}, {4, 7}};
  const std::string again = ReplayMarkdown(*saved, info, 8, /*map_plots=*/true);
  auto report = ReadFileToString(JoinPath(dir.File("run"), "report.md"));
  ASSERT_TRUE(report.ok());
  ASSERT_GT(again.size(), 500u);
  EXPECT_EQ(report->substr(0, again.size()), again);
  EXPECT_NE(again.find("| agent1 | 0-4 | own |"), std::string::npos) << again;
  EXPECT_NE(again.find("which holds agent2; agent1 kept"), std::string::npos) << again;
}

TEST(ReplayReportTest, AblationTableAddsRowsWithRatiosToTheFullRun) {
  testing::TempDir dir;
  Json main;
  main["ate_rmse_m"] = 0.003;
  ASSERT_TRUE(WriteJsonFile(main, dir.File("results.json")).ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("report.md"), "# Split-replay report\n").ok());
  // r = 1 without selection is the reference: 8000 + 2000 bytes, 1000 points.
  std::vector<AblationRow> rows;
  rows.push_back({1, false, "ablation/r1_every_keyframe", RunResults(8000, 2000, 1000, 20, 20)});
  rows.push_back({2, true, ".", RunResults(1500, 1000, 400, 5, 20)});
  rows.push_back({4, true, "ablation/r4_selected", RunResults(500, 500, 100, 5, 21)});
  ASSERT_TRUE(AppendAblation(dir.path(), rows).ok());

  auto results = ReadJsonFile(dir.File("results.json"));
  ASSERT_TRUE(results.ok());
  EXPECT_DOUBLE_EQ(results->Get("ate_rmse_m")->number(), 0.003);  // what was there stays
  const Json* ablation = results->Get("ablation");
  ASSERT_NE(ablation, nullptr);
  ASSERT_EQ(ablation->size(), 3u);
  const Json& half = ablation->array()[1];
  EXPECT_DOUBLE_EQ(half.Get("r")->number(), 0.5);
  EXPECT_TRUE(half.Get("selection")->boolean());
  EXPECT_DOUBLE_EQ(half.Get("rgbd_bytes")->number(), 2500);
  EXPECT_DOUBLE_EQ(half.Get("map_points")->number(), 400);
  EXPECT_DOUBLE_EQ(ablation->array()[2].Get("keyframes")->number(), 21);

  auto report = ReadFileToString(dir.File("report.md"));
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(report->rfind("# Split-replay report\n", 0), 0u);  // appended, not replaced
  // 2500 / 10000 bytes and 400 / 1000 points; 1000 / 10000 and 100 / 1000 for r = 1/4.
  EXPECT_NE(report->find("| 1/2 | on | 5 of 20 | 2 kB | 0.12 kB | 0.250 | 400 | 0.400 |"),
            std::string::npos)
      << *report;
  EXPECT_NE(report->find("| 1/4 | on | 5 of 21 | 1 kB | 0.05 kB | 0.100 | 100 | 0.100 |"),
            std::string::npos)
      << *report;
  EXPECT_NE(report->find("| 1 | off | 20 of 20 | 10 kB | 0.50 kB | 1.000 | 1000 | 1.000 |"),
            std::string::npos)
      << *report;
}

TEST(ReplayReportTest, AblationNeedsTheMainRunsFiles) {
  testing::TempDir dir;
  EXPECT_FALSE(AppendAblation(dir.path(), {}).ok());
}

}  // namespace
}  // namespace ccmd
