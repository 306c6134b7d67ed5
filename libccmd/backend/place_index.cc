#include "libccmd/backend/place_index.h"

#include <algorithm>
#include <cstring>

#include "libccmd/util/logging.h"

namespace ccmd {

Status PlaceIndexOptions::Validate() const {
  if (online_training) CCMD_RETURN_IF_ERROR(online.Validate().WithContext("online vocabulary"));
  return Status::Ok();
}

void PlaceIndexOptions::Describe(OptionsWriter* out) const {
  out->Add("vocabulary", vocabulary ? "given" : "none");
  out->Add("online_training", online_training);
  out->Nested("online", online);
}
namespace {

cv::Mat ToMat(const std::vector<Descriptor>& descriptors) {
  cv::Mat m(static_cast<int>(descriptors.size()), 32, CV_8U);
  for (std::size_t i = 0; i < descriptors.size(); ++i)
    std::memcpy(m.ptr(static_cast<int>(i)), descriptors[i].data(), 32);
  return m;
}

}  // namespace

PlaceIndex::PlaceIndex(const PlaceIndexOptions& options)
    : options_(options), vocabulary_(options.vocabulary) {
  if (options_.online_training && !vocabulary_)
    builder_ = std::make_unique<VocabularyBuilder>(options_.online);
}

std::vector<GlobalKeyframeId> PlaceIndex::Add(const GlobalKeyframeId& id,
                                              const std::vector<Descriptor>& descriptors) {
  const cv::Mat mat = ToMat(descriptors);
  const bool had_vocabulary = vocabulary_ != nullptr;
  if (builder_) {
    descriptors_[id] = mat;
    builder_->Add(mat).IgnoreError();
    if (builder_->TrainingDue()) Retrain();  // adds every stored keyframe, this one included
    if (builder_->next_training() < 0) {
      // The schedule has ended: nothing is ever transformed again.
      builder_.reset();
      descriptors_.clear();
    }
  }
  if (vocabulary_ && !database_.Contains(id))
    database_.Add(id, MapId(0), vocabulary_->Transform(mat)).IgnoreError();
  std::vector<GlobalKeyframeId> late;
  if (!had_vocabulary && vocabulary_) {
    for (const GlobalKeyframeId& stored : before_training_) {
      if (stored != id) late.push_back(stored);
    }
    before_training_.clear();
    std::sort(late.begin(), late.end());  // oldest first, agent by agent
  } else if (!vocabulary_ && builder_) {
    before_training_.push_back(id);
  }
  return late;
}

std::size_t PlaceIndex::MemoryBytes() const {
  std::size_t bytes =
      database_.MemoryBytes() + before_training_.capacity() * sizeof(GlobalKeyframeId);
  for (const auto& [id, m] : descriptors_) bytes += m.total() * m.elemSize() + sizeof(cv::Mat) + 48;
  return bytes;
}

void PlaceIndex::Retrain() {
  VocabularyStats stats;
  auto trained = builder_->Train(&stats);
  if (!trained.ok()) {
    CCMD_LOG(WARNING) << "vocabulary training failed: " << trained.status().ToString();
    return;
  }
  vocabulary_ = std::make_shared<const Vocabulary>(std::move(trained).value());
  ++trainings_;
  database_.Clear();
  for (const auto& [id, mat] : descriptors_)
    database_.Add(id, MapId(0), vocabulary_->Transform(mat)).IgnoreError();
  CCMD_LOG(INFO) << "place recognition vocabulary trained online: " << stats.words << " words from "
                 << stats.images << " keyframes in " << stats.seconds << " s";
}

std::vector<PlaceHit> PlaceIndex::Query(
    const std::vector<Descriptor>& descriptors, int max_results,
    const std::function<bool(const GlobalKeyframeId&)>& accept) const {
  std::vector<PlaceHit> hits;
  if (!vocabulary_) return hits;
  PlaceQueryOptions query;
  query.max_results = max_results;
  query.accept = [&](const GlobalKeyframeId& id, MapId) { return accept(id); };
  for (const PlaceCandidate& c :
       database_.Query(vocabulary_->Transform(ToMat(descriptors)), query)) {
    hits.push_back({c.keyframe, c.score});
  }
  return hits;
}

void PlaceIndex::Remove(const GlobalKeyframeId& id) {
  database_.Erase(id);
  descriptors_.erase(id);
  before_training_.erase(std::remove(before_training_.begin(), before_training_.end(), id),
                         before_training_.end());
}

double PlaceIndex::Score(const GlobalKeyframeId& a, const GlobalKeyframeId& b) const {
  const auto va = database_.Get(a), vb = database_.Get(b);
  if (!va || !vb) return 0;
  return L1Score(*va, *vb);
}

}  // namespace ccmd
