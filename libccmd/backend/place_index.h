#pragma once

// Place recognition for the server: a bag-of-words vocabulary and keyframe database
// (libccmd/features). The vocabulary is either given (trained offline with ccmd_vocab) or
// trained online from the keyframes the server receives, and retrained on a growing schedule
// (VocabularyBuilder); after each training every stored keyframe is transformed again.
// Used by the back-end's loop stage only (one thread).

#include <functional>
#include <map>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/bow_database.h"
#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/features/descriptor.h"
#include "libccmd/features/vocabulary_builder.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct PlaceIndexOptions {
  std::shared_ptr<const Vocabulary> vocabulary;  // null: train online
  bool online_training = true;                   // (re)train from received keyframes
  VocabularyBuilderOptions online;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct PlaceHit {
  GlobalKeyframeId keyframe;
  double score = 0;
};

class PlaceIndex {
 public:
  explicit PlaceIndex(const PlaceIndexOptions& options);

  // Stores a keyframe. Returns the keyframes that could not be queried so far and can be now:
  // those added before the first online training, once it has happened (empty otherwise).
  std::vector<GlobalKeyframeId> Add(const GlobalKeyframeId& id,
                                    const std::vector<Descriptor>& descriptors);
  std::vector<PlaceHit> Query(const std::vector<Descriptor>& descriptors, int max_results,
                              const std::function<bool(const GlobalKeyframeId&)>& accept) const;
  double Score(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const;
  // Forgets a keyframe (culled): it is never a hit again and its descriptors are dropped.
  void Remove(const GlobalKeyframeId& id);

  bool ready() const { return vocabulary_ != nullptr; }
  int trainings() const { return trainings_; }
  // Bytes held: the database, and the descriptors kept for retraining.
  std::size_t MemoryBytes() const;

 private:
  void Retrain();

  PlaceIndexOptions options_;
  std::shared_ptr<const Vocabulary> vocabulary_;
  std::unique_ptr<VocabularyBuilder> builder_;
  BowDatabase database_;
  // To transform again after a retraining: kept only while online training may still retrain
  // (with a given vocabulary, or once the training schedule has ended, never).
  std::map<GlobalKeyframeId, cv::Mat> descriptors_;
  std::vector<GlobalKeyframeId> before_training_;  // added before the first vocabulary existed
  int trainings_ = 0;
};

}  // namespace ccmd
