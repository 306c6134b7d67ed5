// Place recognition end to end on rendered images: a vocabulary trained in another synthetic
// room, the keyframes of the first loop of the camera path in the database, queries from the
// second loop. Ground truth (the path) says which keyframe shows the same place.

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>

#include "libccmd/features/bow_database.h"
#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/features/orb_extractor.h"
#include "libccmd/synth/sequence.h"

namespace ccmd {
namespace {

constexpr int kPathFrames = 720;  // 24 s at 30 fps; the loop takes 16 s (480 frames)

std::vector<cv::Mat> RenderDescriptors(std::uint64_t seed, const std::vector<int>& frames) {
  SyntheticSequenceOptions options;
  options.seed = seed;
  RoomSceneOptions room = options.room;
  room.seed = seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(kPathFrames, options.fps, options.path);
  const OrbExtractor orb;
  std::vector<cv::Mat> descriptors;
  for (int f : frames) {
    const RenderedFrame frame =
        RenderFrame(scene, SyntheticCamera(), path[f].T_world_cam, FrameRenderOptions(options, f));
    cv::Mat gray;
    cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
    descriptors.push_back(orb.Extract(gray).descriptors);
  }
  return descriptors;
}

TEST(PlaceRecognitionTest, QueryFindsTheKeyframeOfTheSamePlace) {
  // Vocabulary from another room (seed 2): nothing of the test room was seen in training.
  std::vector<int> training_frames;
  for (int f = 0; f < 480; f += 12) training_frames.push_back(f);
  VocabularyOptions vo;
  vo.branching = 10;
  vo.depth = 5;
  auto vocabulary = Vocabulary::Train(RenderDescriptors(2, training_frames), vo);
  ASSERT_TRUE(vocabulary.ok()) << vocabulary.status().ToString();

  // Keyframes every second along the first loop; queries from the second loop: frame 515
  // retraces frame 35 and frame 605 frame 125 (new sensor noise), so the nearest keyframes
  // are those of frames 30 and 120, about 7 cm and 4 degrees away.
  std::vector<int> keyframes;
  for (int f = 0; f < 480; f += 30) keyframes.push_back(f);
  std::vector<int> frames = keyframes;
  frames.push_back(515);
  frames.push_back(605);
  const std::vector<cv::Mat> descriptors = RenderDescriptors(7, frames);
  const Trajectory path = MakeLoopPath(kPathFrames, 30.0);

  BowDatabase db;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    ASSERT_TRUE(db.Add({AgentId(0), KeyframeId(keyframes[i])}, MapId(0),
                       vocabulary->Transform(descriptors[i]))
                    .ok());
  }
  const std::pair<int, int> queries[] = {{515, 30}, {605, 120}};
  for (std::size_t q = 0; q < 2; ++q) {
    const auto [query_frame, expected] = queries[q];
    // The setup itself: the expected keyframe is the nearest one by camera centre.
    int nearest = -1;
    double nearest_distance = 1e9;
    for (int k : keyframes) {
      const double d =
          (path[k].T_world_cam.translation() - path[query_frame].T_world_cam.translation()).norm();
      if (d < nearest_distance) nearest_distance = d, nearest = k;
    }
    ASSERT_EQ(nearest, expected);

    PlaceQueryOptions options;
    options.max_results = 0;
    const auto result = db.Query(vocabulary->Transform(descriptors[keyframes.size() + q]), options);
    ASSERT_FALSE(result.empty());
    EXPECT_EQ(static_cast<int>(result[0].keyframe.keyframe.value()), expected) << query_frame;
    // Clearly above every keyframe of another place (more than 1 m away).
    for (const auto& c : result) {
      const int k = static_cast<int>(c.keyframe.keyframe.value());
      const double d =
          (path[k].T_world_cam.translation() - path[query_frame].T_world_cam.translation()).norm();
      if (d > 1.0) {
        EXPECT_GT(result[0].score, 1.5 * c.score) << query_frame << " vs " << k;
      }
    }
  }
}

}  // namespace
}  // namespace ccmd
