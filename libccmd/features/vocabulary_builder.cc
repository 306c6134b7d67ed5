#include "libccmd/features/vocabulary_builder.h"

#include <algorithm>
#include <cmath>

namespace ccmd {

Status VocabularyBuilderOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(vocabulary.Validate());
  if (first_training < 2) return InvalidArgument("first_training must be at least 2 keyframes");
  if (!(growth > 1.0)) return InvalidArgument("growth must be greater than 1");
  if (last_training < first_training) {
    return InvalidArgument("last_training must be >= first_training");
  }
  if (max_images < 2) return InvalidArgument("max_images must be at least 2");
  if (max_descriptors_per_image < 1) {
    return InvalidArgument("max_descriptors_per_image must be positive");
  }
  return Status::Ok();
}

void VocabularyBuilderOptions::Describe(OptionsWriter* out) const {
  out->Nested("vocabulary", vocabulary);
  out->Add("first_training", first_training);
  out->Add("growth", growth);
  out->Add("last_training", last_training);
  out->Add("max_images", max_images);
  out->Add("max_descriptors_per_image", max_descriptors_per_image);
  out->Add("seed", seed);
}

VocabularyBuilder::VocabularyBuilder(const VocabularyBuilderOptions& options)
    : options_(options), rng_(options.seed), next_training_(options.first_training) {}

Status VocabularyBuilder::Add(const cv::Mat& descriptors) {
  if (!descriptors.empty() && (descriptors.type() != CV_8UC1 || descriptors.cols != 32)) {
    return InvalidArgument("keyframe descriptors are not N x 32 CV_8U");
  }
  cv::Mat kept;
  const int limit = options_.max_descriptors_per_image;
  if (descriptors.rows <= limit) {
    kept = descriptors.clone();
  } else {
    kept.create(limit, 32, CV_8UC1);
    for (int i = 0; i < limit; ++i) {
      const int row = static_cast<int>(static_cast<std::int64_t>(i) * descriptors.rows / limit);
      descriptors.row(row).copyTo(kept.row(i));
    }
  }
  ++seen_;
  if (static_cast<int>(images_.size()) < options_.max_images) {
    images_.push_back(std::move(kept));
  } else {
    // Reservoir sampling: every keyframe seen so far is kept with the same probability.
    const int slot = rng_.UniformInt(0, seen_ - 1);
    if (slot < options_.max_images) images_[slot] = std::move(kept);  // replaces, never writes
  }
  return Status::Ok();
}

std::vector<cv::Mat> VocabularyBuilder::TakeTrainingSet() {
  if (next_training_ >= 0) {
    int next = std::max(seen_ + 1, static_cast<int>(std::ceil(seen_ * options_.growth)));
    next_training_ = next > options_.last_training ? -1 : next;
  }
  return images_;
}

StatusOr<Vocabulary> VocabularyBuilder::Train(VocabularyStats* stats) {
  const std::vector<cv::Mat> images = TakeTrainingSet();
  return Vocabulary::Train(images, options_.vocabulary, stats);
}

}  // namespace ccmd
