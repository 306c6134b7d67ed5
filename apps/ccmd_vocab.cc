// ccmd_vocab: trains the bag-of-words vocabulary used for place recognition, from image
// folders, TUM-layout datasets and/or synthetic sequences rendered in memory, and saves it
// in the versioned binary format (libccmd/features/bow_vocabulary.h). --info prints what a
// vocabulary file holds.

#include <CLI/CLI.hpp>
#include <cstdio>

#include "apps/app_common.h"
#include "libccmd/features/bow_vocabulary.h"
#include "libccmd/features/training_data.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/timer.h"

namespace {

int Fail(const ccmd::Status& status) {
  std::fprintf(stderr, "ccmd_vocab: %s\n", status.ToString().c_str());
  return 1;
}

int PrintInfo(const std::string& path) {
  auto vocabulary = ccmd::Vocabulary::Load(path);
  if (!vocabulary.ok()) return Fail(vocabulary.status());
  int zero = 0;
  for (int w = 0; w < vocabulary->word_count(); ++w) zero += vocabulary->Weight(w) == 0.0;
  std::printf(
      "%s: format %u, k=%d L=%d, %d nodes, %d words (%d with weight 0), "
      "%d training images, fingerprint %08x\n",
      path.c_str(), ccmd::Vocabulary::kFormatVersion, vocabulary->branching(), vocabulary->depth(),
      vocabulary->node_count(), vocabulary->word_count(), zero, vocabulary->training_images(),
      vocabulary->Fingerprint());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Train a bag-of-words vocabulary (hierarchical k-medians over ORB descriptors, TF-IDF)\n"
      "from image folders, TUM-layout datasets and/or synthetic sequences, and save it."};
  std::string out, info, json_path;
  std::vector<std::string> image_folders, datasets, synth_specs;
  ccmd::VocabularyOptions vocabulary_options;
  vocabulary_options.threads = 0;
  ccmd::TrainingImageOptions images_options;
  images_options.threads = 0;
  app.add_option("--out", out, "Vocabulary file to write");
  app.add_option("--info", info, "Print what a vocabulary file holds, then exit");
  app.add_option("--images", image_folders, "Folder of .png/.jpg images (repeatable)");
  app.add_option("--dataset", datasets,
                 "Dataset folder (TUM layout, ICL-NUIM, a 7-Scenes sequence): its colour images "
                 "(repeatable)");
  app.add_option("--synth", synth_specs,
                 "Synthetic sequence rendered in memory: frames=N,seed=S[,step=K,width=,height=,"
                 "noise=,fps=] (repeatable)");
  app.add_option("--k", vocabulary_options.branching, "Branching factor")
      ->check(CLI::Range(2, ccmd::Vocabulary::kMaxBranching))
      ->capture_default_str();
  app.add_option("--depth", vocabulary_options.depth, "Levels below the root")
      ->check(CLI::Range(1, ccmd::Vocabulary::kMaxDepth))
      ->capture_default_str();
  app.add_option("--iterations", vocabulary_options.max_iterations, "k-medians rounds per node")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--seed", vocabulary_options.seed, "Clustering seed")->capture_default_str();
  app.add_option("--step", images_options.step, "Use every N-th image of folders and datasets")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  app.add_option("--max-images", images_options.max_images,
                 "At most this many images per input (0: all)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--features", images_options.orb.features, "ORB features per image")
      ->check(CLI::Range(10, 100000))
      ->capture_default_str();
  int threads = 0;
  app.add_option("--threads", threads, "Worker threads (0: all cores)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--json", json_path, "Write the statistics as JSON here");
  CLI11_PARSE(app, argc, argv);

  if (!info.empty()) return PrintInfo(info);
  if (out.empty()) return Fail(ccmd::InvalidArgument("--out is required (or --info FILE)"));
  if (image_folders.empty() && datasets.empty() && synth_specs.empty()) {
    return Fail(ccmd::InvalidArgument("no training data: give --images, --dataset or --synth"));
  }
  vocabulary_options.threads = threads;
  images_options.threads = threads;

  const ccmd::Stopwatch extraction_watch;
  std::vector<cv::Mat> images;
  std::size_t descriptors = 0;
  auto take = [&](const std::string& what, ccmd::StatusOr<ccmd::TrainingImages> result) {
    if (!result.ok()) return result.status().WithContext(what);
    std::fprintf(stderr, "%s: %zu images, %zu descriptors\n", what.c_str(),
                 result->descriptors.size(), result->total_descriptors);
    descriptors += result->total_descriptors;
    for (cv::Mat& m : result->descriptors) images.push_back(std::move(m));
    return ccmd::Status::Ok();
  };
  ccmd::LogOptions("images", images_options);
  ccmd::LogOptions("vocabulary", vocabulary_options);
  for (const auto& folder : image_folders) {
    if (auto s = take("images " + folder, ccmd::DescriptorsFromImageFolder(folder, images_options));
        !s.ok())
      return Fail(s);
  }
  for (const auto& folder : datasets) {
    if (auto s = take("dataset " + folder, ccmd::DescriptorsFromTumDataset(folder, images_options));
        !s.ok())
      return Fail(s);
  }
  for (const auto& spec : synth_specs) {
    if (auto s = take("synth " + spec, ccmd::DescriptorsFromSynthetic(spec, images_options));
        !s.ok())
      return Fail(s);
  }
  const double extraction_seconds = extraction_watch.ElapsedSeconds();

  ccmd::VocabularyStats stats;
  auto vocabulary = ccmd::Vocabulary::Train(images, vocabulary_options, &stats);
  if (!vocabulary.ok()) return Fail(vocabulary.status());
  if (auto s = vocabulary->Save(out); !s.ok()) return Fail(s);
  auto bytes = ccmd::ReadFileToString(out);
  const std::size_t file_bytes = bytes.ok() ? bytes->size() : 0;

  std::printf(
      "vocabulary %s: k=%d L=%d, %d words, %d nodes, trained on %d images / %zu "
      "descriptors in %.2f s (feature extraction %.2f s), %zu bytes, fingerprint %08x\n",
      out.c_str(), vocabulary->branching(), vocabulary->depth(), stats.words, stats.nodes,
      stats.images, stats.descriptors, stats.seconds, extraction_seconds, file_bytes,
      vocabulary->Fingerprint());
  if (!json_path.empty()) {
    ccmd::Json json = ccmd::Json::MakeObject();
    json["file"] = out;
    json["branching"] = vocabulary->branching();
    json["depth"] = vocabulary->depth();
    json["words"] = stats.words;
    json["nodes"] = stats.nodes;
    json["images"] = stats.images;
    json["descriptors"] = stats.descriptors;
    json["training_seconds"] = stats.seconds;
    json["extraction_seconds"] = extraction_seconds;
    json["file_bytes"] = file_bytes;
    json["fingerprint"] = vocabulary->Fingerprint();
    if (auto s = ccmd::WriteJsonFile(json, json_path); !s.ok()) return Fail(s);
  }
  return 0;
}
