// ccmd_agent as users run it offline: trajectory, stats JSON fields, recording, errors.

#include <gtest/gtest.h>

#include <cstdio>

#include <opencv2/core.hpp>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/config.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using testing::ProgramPath;
using testing::RunCommand;

// A recording processed offline as fast as it goes maps each keyframe before the next frame:
// the same recording gives the same trajectory, run after run. Paced replays map beside
// tracking, as a live camera does, and either way can be asked for.
TEST(AgentCliTest, AnOfflineRecordingIsMappedInTheTrackingThreadByDefault) {
  testing::TempDir dir;
  const std::string agent =
      ProgramPath("ccmd_agent") + " --source synth:frames=30,seed=5 --offline";
  auto synchronous = [&](const std::string& flags, const std::string& name) {
    std::string out;
    EXPECT_EQ(RunCommand(agent + " " + flags + " --trajectory " + dir.File(name + ".txt") +
                             " --stats " + dir.File(name + ".json"),
                         &out),
              0)
        << out;
    auto stats = ReadJsonFile(dir.File(name + ".json"));
    EXPECT_TRUE(stats.ok() && stats->Has("synchronous_mapping")) << out;
    return stats.ok() && stats->Get("synchronous_mapping")->boolean();
  };
  EXPECT_TRUE(synchronous("", "a"));
  EXPECT_TRUE(synchronous("", "b"));
  EXPECT_FALSE(synchronous("--asynchronous", "c"));
  EXPECT_FALSE(synchronous("--rate realtime", "d"));
  EXPECT_TRUE(synchronous("--rate realtime --synchronous", "e"));
  auto a = ReadFileToString(dir.File("a.txt")), b = ReadFileToString(dir.File("b.txt"));
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(*a, *b);  // deterministic
  std::string out;
  EXPECT_NE(RunCommand(agent + " --synchronous --asynchronous", &out), 0);
}

// A recording's config gives the sensor's and tracking options with the camera, whether it is
// given with --config, is the folder's camera.yaml (ccmd_synth writes one) or is the shipped
// config the folder's name points to: the runs are the same. Before, only the camera came from
// the two last, and an ICL-NUIM folder was tracked with a Kinect's depth noise.
TEST(AgentCliTest, AGuessedOrOwnConfigGivesTheTrackingOptionsTooAsAGivenOne) {
  testing::TempDir dir;
  std::string out;
  const std::string icl = std::string(CCMD_CONFIG_DIR) + "/icl_nuim.yaml";
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_synth") + " --out " + dir.File("seq") +
                           " --frames 60 --surface-spacing 0.05 --config " + icl,
                       &out),
            0)
      << out;
  const auto run = [&](const std::string& folder, const std::string& flags,
                       const std::string& name) {
    std::string log;
    // No CPU budget: its account follows the machine's load, and a reduced local BA would
    // make runs differ that the options do not.
    EXPECT_EQ(
        RunCommand(ProgramPath("ccmd_agent") + " --source tum:" + folder +
                       " --offline --cpu-budget 0 --trajectory " + dir.File(name) + " " + flags,
                   &log),
        0)
        << log;
    auto text = ReadFileToString(dir.File(name));
    return text.ok() ? *text : std::string();
  };
  // Its own camera.yaml (the config's camera, depth noise and frame depth weight).
  const std::string given =
      run(dir.File("seq"), "--config " + icl + " --record " + dir.File("rec"), "given.txt");
  ASSERT_FALSE(given.empty());
  // What the agent records carries the sensor's options as well.
  auto config = ConfigFile::Open(icl);
  auto recorded = ConfigFile::Open(dir.File("rec/camera.yaml"));
  ASSERT_TRUE(config.ok() && recorded.ok());
  for (const char* key : {"DepthNoise.sigma0", "DepthNoise.sigma2", "Tracking.frameDepthWeight"}) {
    ASSERT_TRUE(config->Has(key)) << key;
    EXPECT_EQ(*recorded->GetDouble(key, -1), *config->GetDouble(key, -2)) << key;
  }
  EXPECT_EQ(run(dir.File("seq"), "", "own.txt"), given);
  // No camera.yaml, a folder named as ICL-NUIM's archives: the shipped icl_nuim.yaml.
  ASSERT_EQ(std::rename(dir.File("seq").c_str(), dir.File("traj0_frei_png").c_str()), 0);
  std::remove(dir.File("traj0_frei_png/camera.yaml").c_str());
  EXPECT_EQ(run(dir.File("traj0_frei_png"), "", "guessed.txt"), given);
  // And the options matter here: the same camera with a Kinect's depth noise tracks otherwise.
  const std::string kinect = dir.File("kinect.yaml");
  std::string text = *ReadFileToString(icl);
  for (const char* key : {"DepthNoise.sigma0", "DepthNoise.sigma2"}) {
    const std::size_t at = text.find(key);
    ASSERT_NE(at, std::string::npos) << key;
    text = text.substr(0, at) + "# " + text.substr(at);
  }
  ASSERT_TRUE(WriteFileAtomic(kinect, text).ok());
  EXPECT_NE(run(dir.File("traj0_frei_png"), "--config " + kinect, "kinect.txt"), given);
  // A rolling shutter's readout is recorded too (and moves the keypoints, so the run differs).
  const std::string rolling = dir.File("rolling.yaml");
  ASSERT_TRUE(
      WriteFileAtomic(rolling, *ReadFileToString(icl) + "Camera.rollingShutterReadout: 0.02\n")
          .ok());
  EXPECT_NE(run(dir.File("traj0_frei_png"), "--config " + rolling + " --record " + dir.File("rs"),
                "rolling.txt"),
            given);
  auto recorded_rolling = ConfigFile::Open(dir.File("rs/camera.yaml"));
  ASSERT_TRUE(recorded_rolling.ok());
  EXPECT_EQ(*recorded_rolling->GetDouble("Camera.rollingShutterReadout", -1), 0.02);
}

// A recording mapped in the tracking thread keeps to the CPU budget by its pace: every local
// BA stays whole however slow the machine (here, a budget under what it needs), so the
// trajectory does not depend on its speed. (That a mapper following the budget shrinks its
// BA: CpuBudgetTest.)
TEST(AgentCliTest, AnOfflineRecordingKeepsEveryLocalBaWholeUnderASmallBudget) {
  testing::TempDir dir;
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_agent") +
                           " --source synth:frames=30,seed=5 --offline --cpu-budget 0.3 --stats " +
                           dir.File("s.json"),
                       &out),
            0)
      << out;
  auto stats = ReadJsonFile(dir.File("s.json"));
  ASSERT_TRUE(stats.ok()) << out;
  EXPECT_GT(stats->Get("local_ba_runs")->number(), 0);
  EXPECT_EQ(stats->Get("local_ba_reduced")->number(), 0);
  EXPECT_EQ(stats->Get("local_ba_skipped_budget")->number(), 0);
}

TEST(AgentCliTest, OfflineRunWritesTrajectoryStatsAndRecording) {
  testing::TempDir dir;
  std::string out;
  const std::string spec = "synth:frames=45,seed=3";
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_agent") + " --source " + spec +
                           " --offline --synchronous" + " --trajectory " + dir.File("traj.txt") +
                           " --stats " + dir.File("stats.json") + " --record " + dir.File("rec"),
                       &out),
            0)
      << out;
  auto stats = ReadJsonFile(dir.File("stats.json"));
  ASSERT_TRUE(stats.ok());
  for (const char* key : {"frames", "keyframes", "lost_frames", "fps", "extract_ms_mean",
                          "track_ms_mean", "local_ba_ms_mean", "rgbd_decisions"}) {
    EXPECT_TRUE(stats->Has(key)) << key;
  }
  EXPECT_EQ(stats->Get("frames")->number(), 45);
  EXPECT_EQ(stats->Get("lost_frames")->number(), 0);
  // The trajectory matches the renderer's ground truth.
  auto trajectory = ReadTumTrajectory(dir.File("traj.txt"));
  ASSERT_TRUE(trajectory.ok());
  EXPECT_EQ(trajectory->size(), 45u);
  auto ground_truth = ReadTumTrajectory(dir.File("rec/groundtruth.txt"));
  ASSERT_TRUE(ground_truth.ok());
  auto ate = ComputeAte(*ground_truth, *trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);
  // The recording reads back as the frames the agent saw.
  auto recorded = TumSequence::Open(dir.File("rec"), std::nullopt);
  ASSERT_TRUE(recorded.ok()) << recorded.status().ToString();
  ASSERT_EQ(recorded->size(), 45u);
  auto options = ParseSyntheticSpec("frames=45,seed=3");
  ASSERT_TRUE(options.ok());
  SyntheticSource source(*options);
  RgbdFrame live;
  ASSERT_TRUE(source.Read(&live).ok());
  auto first = recorded->LoadFrame(0);
  ASSERT_TRUE(first.ok());
  EXPECT_EQ(cv::norm(live.depth_mm, first->depth_mm, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(live.bgr, first->bgr, cv::NORM_INF), 0);
}

// A recording with a damaged frame is mapped without it; one that becomes unreadable for good
// stops the run with an error, and what was tracked until then is still written.
TEST(AgentCliTest, DamagedFramesOfARecordingCostOnlyThemselves) {
  testing::TempDir dir;
  std::string out;
  ASSERT_EQ(
      RunCommand(ProgramPath("ccmd_synth") + " --out " + dir.File("seq") + " --frames 40", &out), 0)
      << out;
  auto sequence = TumSequence::Open(dir.File("seq"), std::nullopt);
  ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
  ASSERT_TRUE(WriteFileAtomic(sequence->frame(20).rgb_path, "truncated").ok());
  const std::string agent = ProgramPath("ccmd_agent") + " --source tum:" + dir.File("seq") +
                            " --offline --trajectory " + dir.File("t.txt") + " --stats " +
                            dir.File("s.json");
  ASSERT_EQ(RunCommand(agent, &out), 0) << out;
  EXPECT_NE(out.find("damaged or unreadable: 1 "), std::string::npos) << out;
  auto stats = ReadJsonFile(dir.File("s.json"));
  ASSERT_TRUE(stats.ok()) << out;
  EXPECT_EQ(stats->Get("dropped_frames")->number(), 1);
  EXPECT_EQ(stats->Get("lost_frames")->number(), 0);
  auto trajectory = ReadTumTrajectory(dir.File("t.txt"));
  ASSERT_TRUE(trajectory.ok());
  EXPECT_EQ(trajectory->size(), 39u);
  auto ate = ComputeAte(*ReadTumTrajectory(dir.File("seq/groundtruth.txt")), *trajectory);
  ASSERT_TRUE(ate.ok());
  EXPECT_LT(ate->error.rmse, 0.01);

  // From frame 25 on every depth image is gone: at 5 frames/s, three seconds of them.
  for (int i = 25; i < 40; ++i) std::remove(sequence->frame(i).depth_path.c_str());
  auto camera = ReadFileToString(dir.File("seq/camera.yaml"));
  ASSERT_TRUE(camera.ok());
  const std::size_t at = camera->find("Camera.fps: 30");
  ASSERT_NE(at, std::string::npos);
  ASSERT_TRUE(
      WriteFileAtomic(dir.File("seq/camera.yaml"), camera->replace(at, 14, "Camera.fps: 5")).ok());
  std::remove(dir.File("t.txt").c_str());
  EXPECT_EQ(RunCommand(agent, &out), 1) << out;
  EXPECT_NE(out.find("frames 25-39"), std::string::npos) << out;
  trajectory = ReadTumTrajectory(dir.File("t.txt"));
  ASSERT_TRUE(trajectory.ok()) << out;
  EXPECT_EQ(trajectory->size(), 24u);  // 0-24 but 20
}

// Frame after frame the agent allocates the same image-sized buffers, which the heap must
// reuse: with glibc's mmap threshold fixed at 128 kB (as the server sets it) each was mapped
// and faulted in afresh, about 3000 pages a frame here and half the frame rate. What 60 more
// frames cost in page faults says which it is, whatever the start-up costs.
TEST(AgentCliTest, TheAgentReusesItsMemoryFromFrameToFrame) {
#ifdef CCMD_OWN_ALLOCATOR
  GTEST_SKIP() << "a sanitizer's allocator, not glibc's, serves this build";
#endif
  testing::TempDir dir;
  auto faults = [&](int frames) {
    std::string out;
    const std::string stats = dir.File(std::to_string(frames) + ".json");
    EXPECT_EQ(RunCommand(ProgramPath("ccmd_agent") + " --source synth:frames=" +
                             std::to_string(frames) + ",seed=5 --offline --stats " + stats,
                         &out),
              0)
        << out;
    auto json = ReadJsonFile(stats);
    return json.ok() && json->Has("minor_page_faults") ? json->Get("minor_page_faults")->number()
                                                       : -1.0;
  };
  const double short_run = faults(30), long_run = faults(90);
  ASSERT_GT(short_run, 0);
  EXPECT_LT((long_run - short_run) / 60, 500) << short_run << " then " << long_run;
}

// --rgbd-every-keyframe turns the covisibility selection off: every keyframe's decision is
// "transmit", where the default skips views that transmitted keyframes already cover.
TEST(AgentCliTest, RgbdEveryKeyframeOverridesTheSelection) {
  testing::TempDir dir;
  auto decisions = [&](const std::string& flags, int* transmitted, int* total) {
    std::string out;
    ASSERT_EQ(RunCommand(ProgramPath("ccmd_agent") +
                             " --source synth:frames=60,seed=3 --offline --synchronous " + flags +
                             " --stats " + dir.File("stats.json"),
                         &out),
              0)
        << out;
    auto stats = ReadJsonFile(dir.File("stats.json"));
    ASSERT_TRUE(stats.ok());
    ASSERT_TRUE(stats->Has("rgbd_decisions"));
    *transmitted = *total = 0;
    for (const Json& d : stats->Get("rgbd_decisions")->array()) {
      ++*total;
      *transmitted += d.Get("transmit")->boolean();
    }
  };
  int selected = 0, selected_total = 0, every = 0, every_total = 0;
  decisions("", &selected, &selected_total);
  decisions("--rgbd-every-keyframe", &every, &every_total);
  ASSERT_GT(selected_total, 3);
  EXPECT_LT(selected, selected_total);  // the selection skipped some
  EXPECT_GT(selected, 0);
  EXPECT_EQ(every, every_total);
  EXPECT_EQ(every_total,
            selected_total);  // the same keyframes (synchronous mapping is deterministic)
}

TEST(AgentCliTest, MissingServerOrSourceIsExplained) {
  std::string out;
  EXPECT_NE(RunCommand(ProgramPath("ccmd_agent") + " --source synth:frames=5", &out), 0);
  EXPECT_NE(out.find("--offline"), std::string::npos) << out;
  EXPECT_NE(RunCommand(ProgramPath("ccmd_agent") + " --source tum:/no/such --offline", &out), 0);
  EXPECT_NE(out.find("/no/such"), std::string::npos) << out;
  EXPECT_NE(
      RunCommand(ProgramPath("ccmd_agent") + " --source synth:frames=5 --offline --segment 4/3",
                 &out),
      0);
}

}  // namespace
}  // namespace ccmd
