#include "libccmd/features/vocabulary_builder.h"

#include <gtest/gtest.h>

#include <set>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

cv::Mat Rows(int n, std::uint8_t tag, Rng& rng) {
  cv::Mat m(n, 32, CV_8UC1);
  for (int r = 0; r < n; ++r) {
    for (int c = 0; c < 32; ++c) m.at<std::uint8_t>(r, c) = static_cast<std::uint8_t>(rng.Next());
    m.at<std::uint8_t>(r, 0) = tag;  // which keyframe the row came from
    m.at<std::uint8_t>(r, 1) = static_cast<std::uint8_t>(r);
  }
  return m;
}

TEST(VocabularyBuilderTest, GeometricSchedule) {
  VocabularyBuilderOptions options;
  options.first_training = 4;
  options.growth = 2.0;
  options.last_training = 20;
  options.vocabulary.branching = 3;
  options.vocabulary.depth = 2;
  VocabularyBuilder builder(options);
  Rng rng(1);
  std::vector<int> trained_at;
  for (int k = 1; k <= 40; ++k) {
    ASSERT_TRUE(builder.Add(Rows(20, static_cast<std::uint8_t>(k), rng)).ok());
    if (builder.TrainingDue()) {
      trained_at.push_back(k);
      auto v = builder.Train();
      ASSERT_TRUE(v.ok()) << v.status().ToString();
      EXPECT_EQ(v->training_images(), k);
    }
  }
  // 4, then 8, 16; the next (32) is beyond last_training.
  EXPECT_EQ(trained_at, (std::vector<int>{4, 8, 16}));
  EXPECT_EQ(builder.next_training(), -1);
  EXPECT_FALSE(builder.TrainingDue());
}

TEST(VocabularyBuilderTest, KeepsABoundedSpreadSample) {
  VocabularyBuilderOptions options;
  options.max_images = 10;
  options.max_descriptors_per_image = 5;
  VocabularyBuilder builder(options);
  Rng rng(2);
  for (int k = 0; k < 100; ++k)
    ASSERT_TRUE(builder.Add(Rows(50, static_cast<std::uint8_t>(k), rng)).ok());
  EXPECT_EQ(builder.keyframes_seen(), 100);
  EXPECT_EQ(builder.images_kept(), 10);
  const auto images = builder.TakeTrainingSet();
  std::set<int> tags;
  for (const cv::Mat& m : images) {
    ASSERT_EQ(m.rows, 5);
    tags.insert(m.at<std::uint8_t>(0, 0));
    // Rows are evenly spaced over the keyframe's 50: 0, 10, 20, 30, 40.
    for (int r = 0; r < 5; ++r) EXPECT_EQ(m.at<std::uint8_t>(r, 1), 10 * r);
  }
  EXPECT_EQ(tags.size(), 10u);
  // Reservoir sampling keeps keyframes from all over, not only the first ten.
  EXPECT_GT(*tags.rbegin(), 30);
}

TEST(VocabularyBuilderTest, TrainingSetStaysValidWhileAdding) {
  VocabularyBuilderOptions options;
  options.max_images = 3;
  VocabularyBuilder builder(options);
  Rng rng(3);
  for (int k = 0; k < 3; ++k)
    ASSERT_TRUE(builder.Add(Rows(4, static_cast<std::uint8_t>(k), rng)).ok());
  const auto taken = builder.TakeTrainingSet();
  std::vector<cv::Mat> copies;
  for (const auto& m : taken) copies.push_back(m.clone());
  for (int k = 3; k < 50; ++k)
    ASSERT_TRUE(builder.Add(Rows(4, static_cast<std::uint8_t>(k), rng)).ok());
  for (std::size_t i = 0; i < taken.size(); ++i) {
    EXPECT_EQ(cv::norm(taken[i], copies[i], cv::NORM_INF), 0.0);
  }
}

TEST(VocabularyBuilderTest, RejectsBadInput) {
  VocabularyBuilder builder;
  EXPECT_FALSE(builder.Add(cv::Mat(3, 16, CV_8UC1)).ok());
  EXPECT_EQ(builder.keyframes_seen(), 0);
  VocabularyBuilderOptions bad;
  bad.growth = 1.0;
  EXPECT_FALSE(bad.Validate().ok());
  EXPECT_TRUE(VocabularyBuilderOptions().Validate().ok());
}

}  // namespace
}  // namespace ccmd
