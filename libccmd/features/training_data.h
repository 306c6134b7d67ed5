#pragma once

// Descriptors to train a vocabulary on, one matrix per image, from the places a vocabulary
// can be learnt from: a folder of images, a TUM-layout dataset (its colour images), or the
// synthetic room rendered on the fly. Used by ccmd_vocab and the place-recognition
// benchmark; kept out of ccmd_features so that the features module does not depend on the
// renderer.

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct TrainingImageOptions {
  OrbOptions orb;      // features per image and pyramid, as the agents extract them
  int step = 1;        // every step-th image
  int max_images = 0;  // after the step; 0 = no limit
  int threads = 1;     // images decoded/rendered and described in parallel (same result)

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct TrainingImages {
  std::vector<cv::Mat> descriptors;  // per image, N x 32 CV_8U
  std::size_t total_descriptors = 0;
};

// Every .png/.jpg/.jpeg/.bmp file of `folder` (not recursive), in name order.
StatusOr<TrainingImages> DescriptorsFromImageFolder(const std::string& folder,
                                                    const TrainingImageOptions& options);

// The colour images of a dataset folder: those listed in its rgb.txt (TUM RGB-D, ccmd_synth
// output, converted copies), else those the sequence reader pairs (an associations.txt only,
// as ICL-NUIM ships it, or a 7-Scenes sequence as unpacked).
StatusOr<TrainingImages> DescriptorsFromTumDataset(const std::string& folder,
                                                   const TrainingImageOptions& options);

// Frames of a synthetic sequence rendered in memory. `spec` takes the keys of a synth:
// source (frames, seed, width, height, noise, fps) plus step=K (overrides options.step).
// The frames are those ccmd_synth writes with the same options.
StatusOr<TrainingImages> DescriptorsFromSynthetic(const std::string& spec,
                                                  const TrainingImageOptions& options);

}  // namespace ccmd
