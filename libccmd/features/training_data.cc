#include "libccmd/features/training_data.h"

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <functional>
#include <mutex>
#include <thread>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

Status TrainingImageOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(orb.Validate().WithContext("ORB options"));
  if (step < 1) return InvalidArgument("step must be at least 1");
  if (max_images < 0) return InvalidArgument("max_images must be >= 0 (0: no limit)");
  if (threads < 0) return InvalidArgument("threads must be >= 0 (0: all cores)");
  return Status::Ok();
}

void TrainingImageOptions::Describe(OptionsWriter* out) const {
  out->Nested("orb", orb);
  out->Add("step", step);
  out->Add("max_images", max_images);
  out->Add("threads", threads);
}

namespace {

// Picks every step-th of `count` items, at most max_images of them.
std::vector<int> Selected(int count, const TrainingImageOptions& options) {
  std::vector<int> indices;
  for (int i = 0; i < count; i += std::max(1, options.step)) {
    if (options.max_images > 0 && static_cast<int>(indices.size()) >= options.max_images) break;
    indices.push_back(i);
  }
  return indices;
}

// Runs `gray_of(i)` for every selected item in parallel and extracts ORB from each image.
// The first error (in item order) wins.
StatusOr<TrainingImages> Describe(const std::vector<int>& items,
                                  const TrainingImageOptions& options,
                                  const std::function<StatusOr<cv::Mat>(int)>& gray_of) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  const OrbExtractor orb(options.orb);
  const int n = static_cast<int>(items.size());
  std::vector<cv::Mat> descriptors(n);
  std::vector<Status> errors(n);
  int threads = options.threads > 0
                    ? options.threads
                    : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  threads = std::max(1, std::min(threads, n));
  std::atomic<int> next{0};
  auto work = [&] {
    for (int i = next++; i < n; i = next++) {
      StatusOr<cv::Mat> gray = gray_of(items[i]);
      if (!gray.ok()) {
        errors[i] = gray.status();
        continue;
      }
      descriptors[i] = orb.Extract(*gray).descriptors;
    }
  };
  std::vector<std::thread> workers;
  for (int t = 1; t < threads; ++t) workers.emplace_back(work);
  work();
  for (auto& w : workers) w.join();
  TrainingImages result;
  for (int i = 0; i < n; ++i) {
    CCMD_RETURN_IF_ERROR(errors[i]);
    result.total_descriptors += descriptors[i].rows;
  }
  result.descriptors = std::move(descriptors);
  return result;
}

StatusOr<cv::Mat> ReadGray(const std::string& path) {
  cv::Mat gray;
  try {
    gray = cv::imread(path, cv::IMREAD_GRAYSCALE);
  } catch (const cv::Exception& e) {
    return IoError("decoding " + path + ": " + e.what());
  }
  if (gray.empty()) return IoError("cannot read image " + path);
  return gray;
}

}  // namespace

StatusOr<TrainingImages> DescriptorsFromImageFolder(const std::string& folder,
                                                    const TrainingImageOptions& options) {
  if (!IsDirectory(folder)) return NotFound("image folder " + folder + " does not exist");
  std::vector<std::string> files;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator(folder, ec)) {
    if (!entry.is_regular_file()) continue;
    std::string ext = entry.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return std::tolower(c); });
    if (ext == ".png" || ext == ".jpg" || ext == ".jpeg" || ext == ".bmp") {
      files.push_back(entry.path().string());
    }
  }
  if (ec) return IoError("listing " + folder + ": " + ec.message());
  if (files.empty()) return NotFound("no images (.png, .jpg, .bmp) in " + folder);
  std::sort(files.begin(), files.end());
  return Describe(Selected(static_cast<int>(files.size()), options), options,
                  [&](int i) { return ReadGray(files[i]); });
}

StatusOr<TrainingImages> DescriptorsFromTumDataset(const std::string& folder,
                                                   const TrainingImageOptions& options) {
  std::vector<std::string> files;
  if (FileExists(JoinPath(folder, "rgb.txt"))) {
    auto list = ReadTimedFileList(JoinPath(folder, "rgb.txt"));
    if (!list.ok()) return list.status().WithContext("dataset " + folder);
    for (const TimedFile& f : *list) files.push_back(JoinPath(folder, f.path));
  } else {
    // associations.txt only, or a 7-Scenes sequence: the colour images the reader pairs.
    auto sequence = TumSequence::Open(folder, PinholeCamera());  // paths only: no camera needed
    if (!sequence.ok()) return sequence.status().WithContext("dataset " + folder);
    for (std::size_t i = 0; i < sequence->size(); ++i) files.push_back(sequence->frame(i).rgb_path);
  }
  if (files.empty()) return NotFound("dataset " + folder + " lists no colour images");
  return Describe(Selected(static_cast<int>(files.size()), options), options,
                  [&](int i) { return ReadGray(files[i]); });
}

StatusOr<TrainingImages> DescriptorsFromSynthetic(const std::string& spec,
                                                  const TrainingImageOptions& options) {
  TrainingImageOptions local = options;
  std::vector<std::string> rest;
  for (const std::string& item : Split(spec, ',')) {
    const auto kv = Split(item, '=');
    if (kv.size() == 2 && Trim(kv[0]) == "step") {
      auto step = ParseInt(kv[1]);
      if (!step.ok() || *step < 1 || *step > 1000000) {
        return InvalidArgument("synthetic option step must be a positive integer");
      }
      local.step = static_cast<int>(*step);
    } else if (!Trim(item).empty()) {
      rest.push_back(item);
    }
  }
  std::string joined;
  for (const std::string& item : rest) joined += (joined.empty() ? "" : ",") + item;
  CCMD_ASSIGN_OR_RETURN(SyntheticSequenceOptions sequence, ParseSyntheticSpec(joined));
  RoomSceneOptions room = sequence.room;
  room.seed = sequence.seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(sequence.frames, sequence.fps, sequence.path);
  const PinholeCamera camera = SyntheticCamera(sequence.width, sequence.height);
  return Describe(Selected(sequence.frames, local), local, [&](int i) -> StatusOr<cv::Mat> {
    const RenderedFrame frame =
        RenderFrame(scene, camera, path[i].T_world_cam, FrameRenderOptions(sequence, i));
    cv::Mat gray;
    cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
    return gray;
  });
}

}  // namespace ccmd
