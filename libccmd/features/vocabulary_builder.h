#pragma once

// Online vocabulary training: collects the descriptors of keyframes as a system receives
// them and says when a vocabulary should be (re)trained from them, so that place
// recognition adapts to an environment no shipped vocabulary has seen.
//
// Retraining follows a geometric schedule (first at `first_training` keyframes, then each
// time the count has grown by `growth`), so its total cost stays proportional to the last
// training, and it stops once `last_training` keyframes have been seen. Keyframes beyond
// `max_images` replace earlier ones by reservoir sampling (fixed seed), so the sample stays
// spread over everything seen.
//
//   VocabularyBuilder builder(options);
//   builder.Add(keyframe_descriptors);              // for every keyframe received
//   if (builder.TrainingDue()) {
//     auto images = builder.TakeTrainingSet();      // cheap, advances the schedule
//     ... in a background thread: Vocabulary::Train(images, builder.options().vocabulary)
//     ... then transform every keyframe again and rebuild the BowDatabase.
//   }
//
// Thread safety: not synchronised; one owner thread calls Add/TrainingDue/TakeTrainingSet.
// The matrices TakeTrainingSet returns are never written again, so training may read them
// in another thread while the owner keeps adding.

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/util/random.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct VocabularyBuilderOptions {
  VocabularyOptions vocabulary;
  int first_training = 20;               // keyframes before the first training
  double growth = 2.0;                   // next training when the count has grown this much
  int last_training = 2000;              // no training once this many keyframes were seen
  int max_images = 1000;                 // keyframes kept for training
  int max_descriptors_per_image = 1000;  // rows kept per keyframe (evenly spaced)
  std::uint64_t seed = 1;                // reservoir sampling

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class VocabularyBuilder {
 public:
  explicit VocabularyBuilder(const VocabularyBuilderOptions& options = {});

  const VocabularyBuilderOptions& options() const { return options_; }

  // Records one keyframe's descriptors (N x 32 CV_8U; copied). InvalidArgument otherwise.
  Status Add(const cv::Mat& descriptors);

  int keyframes_seen() const { return seen_; }
  int images_kept() const { return static_cast<int>(images_.size()); }
  // Keyframe count at which the next training is due (-1 when the schedule has ended).
  int next_training() const { return next_training_; }
  bool TrainingDue() const { return next_training_ >= 0 && seen_ >= next_training_; }

  // The kept descriptor matrices, and moves the schedule on to the next training.
  std::vector<cv::Mat> TakeTrainingSet();
  // Trains now on the kept keyframes (in the calling thread) and moves the schedule on.
  StatusOr<Vocabulary> Train(VocabularyStats* stats = nullptr);

 private:
  VocabularyBuilderOptions options_;
  Rng rng_;
  std::vector<cv::Mat> images_;
  int seen_ = 0;
  int next_training_ = 0;
};

}  // namespace ccmd
