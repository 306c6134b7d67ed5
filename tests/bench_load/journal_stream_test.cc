// ccmd_load's streams: journals read back, laps renumbered, agents offset; and the program
// against a real ccmd_server.

#include "tests/bench_load/journal_stream.h"

#include <gtest/gtest.h>

#include <signal.h>

#include <cmath>

#include "libccmd/codec/wire_pose.h"
#include "libccmd/net/journal.h"
#include "libccmd/tracking/keyframe_message.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/random.h"
#include "libccmd/util/subprocess.h"
#include "tests/support/test_support.h"

namespace ccmd::load {
namespace {

SessionCamera Camera() { return {525, 525, 319.5, 239.5, 640, 480, 5000}; }

// Keyframe i of a recorded agent: 60 keypoints, 40 of them new map points (ids 40 i ..), the
// rest linked to the previous keyframe's; a covisibility link and a depth link to keyframe
// i - 1; the pose moves along x.
KeyframeMessage RecordedKeyframe(std::uint32_t i, Rng* rng) {
  KeyframeMessage m;
  m.id = KeyframeId(i);
  m.timestamp = 1.0 + i;
  Pose T = Pose::Identity();
  T.translation() = Eigen::Vector3d(0.1 * i, 0, 0);
  m.T_world_cam = PoseToWire(T);
  if (i > 0) {
    m.parent = KeyframeId(i - 1);
    m.covisibility.push_back({KeyframeId(i - 1), 20});
    DepthLink link;
    link.keyframe = KeyframeId(i - 1);
    link.information[0] = 1;
    m.depth_links.push_back(link);
  }
  for (int k = 0; k < 60; ++k) {
    WireKeypoint kp;
    kp.u = static_cast<float>(rng->Uniform(10, 630));
    kp.v = static_cast<float>(rng->Uniform(10, 470));
    kp.depth_m = 2.0f;
    if (k < 40) {
      NewMapPoint p;
      p.id = MapPointId(40 * i + k);
      p.p_cam = {static_cast<float>(rng->Uniform(-1, 1)), static_cast<float>(rng->Uniform(-1, 1)),
                 2.0f};
      for (auto& b : p.descriptor) b = static_cast<std::uint8_t>(rng->Next());
      kp.descriptor = p.descriptor;
      kp.map_point = p.id;
      m.new_map_points.push_back(p);
    } else if (i > 0) {
      kp.map_point = MapPointId(40 * (i - 1) + k - 40);
    } else {
      for (auto& b : kp.descriptor) b = static_cast<std::uint8_t>(rng->Next());
    }
    m.keypoints.push_back(kp);
  }
  return m;
}

// A journal of `keyframes` keyframes with a pose update after every third.
void WriteJournal(const std::string& folder, int keyframes) {
  ASSERT_TRUE(MakeDirectories(folder).ok());
  auto writer = JournalWriter::Create(JoinPath(folder, JournalFileName(AgentId(1))),
                                      {AgentId(1), "recorded", Camera()});
  ASSERT_TRUE(writer.ok()) << writer.status().ToString();
  Rng rng(9);
  std::uint64_t seq = 0;
  for (int i = 0; i < keyframes; ++i) {
    auto bytes = SerializeKeyframe(RecordedKeyframe(static_cast<std::uint32_t>(i), &rng));
    ASSERT_TRUE(bytes.ok()) << bytes.status().ToString();
    ASSERT_TRUE(
        (*writer)->Append(static_cast<std::uint8_t>(MessageType::kKeyframe), ++seq, *bytes).ok());
    if (i % 3 == 2) {
      PoseUpdateMessage update;
      Pose T = Pose::Identity();
      T.translation() = Eigen::Vector3d(0.1 * i + 0.01, 0, 0);
      update.entries.push_back({KeyframeId(static_cast<std::uint32_t>(i)), PoseToWire(T)});
      auto u = SerializePoseUpdate(update);
      ASSERT_TRUE(u.ok());
      ASSERT_TRUE(
          (*writer)->Append(static_cast<std::uint8_t>(MessageType::kPoseUpdate), ++seq, *u).ok());
    }
  }
  ASSERT_TRUE((*writer)->Sync().ok());
}

TEST(JournalStreamTest, ReadsAJournalAndRenumbersEveryLap) {
  testing::TempDir dir;
  WriteJournal(dir.File("journal"), 10);
  auto streams = ReadJournalStreams(dir.File("journal"));
  ASSERT_TRUE(streams.ok()) << streams.status().ToString();
  ASSERT_EQ(streams->size(), 1u);
  const JournalStream& s = (*streams)[0];
  EXPECT_EQ(s.name, "recorded");
  EXPECT_EQ(s.camera, Camera());
  EXPECT_EQ(s.keyframes, 10u);
  EXPECT_EQ(s.messages.size(), 13u);  // and three pose updates
  EXPECT_EQ(s.keyframe_ids, 10u);
  EXPECT_EQ(s.map_point_ids, 400u);
  EXPECT_GT(s.keyframe_bytes, 10u * 60 * 8);

  const KeyframeMessage& recorded = *s.messages[5].keyframe;  // keyframe 4
  ASSERT_EQ(recorded.id, KeyframeId(4));
  const Pose offset = AgentOffset(3);
  const KeyframeMessage lap2 = LapKeyframe(s, recorded, 2, offset);
  EXPECT_EQ(lap2.id, KeyframeId(24));
  EXPECT_EQ(lap2.parent, KeyframeId(23));
  EXPECT_EQ(lap2.covisibility[0].keyframe, KeyframeId(23));
  EXPECT_EQ(lap2.depth_links[0].keyframe, KeyframeId(23));
  EXPECT_EQ(lap2.new_map_points[0].id, MapPointId(800 + 160));
  EXPECT_EQ(lap2.keypoints[0].map_point, MapPointId(800 + 160));
  EXPECT_EQ(lap2.keypoints[50].map_point, MapPointId(800 + 130));  // linked to keyframe 3's
  EXPECT_EQ(lap2.new_map_points[0].p_cam, recorded.new_map_points[0].p_cam);  // camera frame
  const Pose moved = PoseFromWire(lap2.T_world_cam),
             expected = offset * PoseFromWire(recorded.T_world_cam);
  EXPECT_LT((moved.matrix() - expected.matrix()).cwiseAbs().maxCoeff(), 1e-9);
  const KeyframeMessage lap0 =
      LapKeyframe(s, recorded, 0, AgentOffset(0));  // agent 0, first lap: as recorded
  EXPECT_EQ(lap0.id, recorded.id);
  EXPECT_LT((PoseFromWire(lap0.T_world_cam).matrix() - PoseFromWire(recorded.T_world_cam).matrix())
                .cwiseAbs()
                .maxCoeff(),
            1e-12);

  const PoseUpdateMessage update = LapPoseUpdate(s, *s.messages[3].pose_update, 1, offset);
  EXPECT_EQ(update.entries[0].keyframe, KeyframeId(12));
  EXPECT_GT(TranslationDistance(AgentOffset(1), AgentOffset(2)), 1.0);
}

TEST(JournalStreamTest, AFolderWithoutJournalsIsAnError) {
  testing::TempDir dir;
  EXPECT_FALSE(ReadJournalStreams(dir.path()).ok());
  EXPECT_FALSE(ReadJournalStreams(dir.File("missing")).ok());
}

TEST(LoadCliTest, AgentsReplayTheStreamsAndTheServersIntakeIsReported) {
  testing::TempDir dir;
  WriteJournal(dir.File("recorded"), 10);
  auto server = Subprocess::Start(
      {testing::ProgramPath("ccmd_server"), "--listen", "127.0.0.1:0", "--journal", dir.File("run"),
       "--out", dir.File("out"), "--no-dense", "--stats-interval", "0.2"},
      "", dir.File("server.log"), /*pipe_stdout=*/true);
  ASSERT_TRUE(server.ok()) << server.status().ToString();
  std::string port;
  while (port.empty()) {
    auto line = server->ReadLine(30);
    ASSERT_TRUE(line.ok()) << "ccmd_server did not start";
    if (line->find("listening on") != std::string::npos)
      port = line->substr(line->find_last_of(':') + 1);
  }
  server->DrainStdoutTo(dir.File("server.out"));
  std::string output;
  const int code = testing::RunCommand(
      testing::ProgramPath("ccmd_load") + " --server 127.0.0.1:" + port + " --journals " +
          dir.File("recorded") + " --agents 2 --rate 10 --seconds 2 --json " +
          dir.File("load.json") + " --server-stats " + dir.File("out/server_stats.json") +
          " --plots " + dir.File("plots"),
      &output);
  ASSERT_EQ(code, 0) << output;
  ASSERT_TRUE(server->Signal(SIGTERM).ok());
  EXPECT_EQ(server->Wait().exit_code, 0);
  auto text = ReadFileToString(dir.File("load.json"));
  ASSERT_TRUE(text.ok());
  auto j = Json::Parse(*text);
  ASSERT_TRUE(j.ok());
  // Two agents at 10 keyframes/s for 2 s: 40 keyframes, two laps of the 10 recorded each.
  EXPECT_NEAR(j->Get("keyframes_sent")->number(), 40, 2);
  EXPECT_EQ(j->Get("lost")->number(), 0);
  EXPECT_EQ(j->Get("keyframes_acked")->number(), j->Get("keyframes_sent")->number());
  EXPECT_EQ(j->Get("server_keyframes_received")->number(), j->Get("keyframes_sent")->number());
  EXPECT_GE(j->Get("intake_p99_ms")->number(-1), 0);
  EXPECT_GT(j->Get("server_peak_rss_mb")->number(-1), 1);
  EXPECT_GT(j->Get("series")->size(), 1u);
  EXPECT_TRUE(FileExists(dir.File("plots/memory.png")));
  // The server kept every keyframe, renumbered by lap (ids 0..19 per agent).
  EXPECT_EQ(j->Get("server_backend")->Get("keyframes")->number(),
            j->Get("keyframes_sent")->number());
}

}  // namespace
}  // namespace ccmd::load
