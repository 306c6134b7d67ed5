#pragma once

// Opens a source from its command-line spec:
//   tum:DIR         a TUM-layout folder (TUM RGB-D, ICL-NUIM, 7-Scenes converted, ccmd_synth)
//   synth[:k=v,..]  the synthetic room rendered on the fly (frames, seed, width, height, noise)
// Live cameras (openni2, v4l2) are added by their modules.

#include <memory>
#include <optional>
#include <string>

#include "libccmd/io/split.h"
#include "libccmd/sensors/rgbd_source.h"

namespace ccmd {

struct SourceOptions {
  std::string camera_config;               // YAML; empty: the dataset's camera.yaml or a guess
  std::optional<std::pair<int, int>> segment;  // (i, k): replay segment i of k (1-based)
  double segment_overlap = 0.1;
  std::string configs_dir;                 // where shipped configs live, for guesses
};

StatusOr<std::unique_ptr<RgbdSource>> OpenSource(const std::string& spec,
                                                 const SourceOptions& options);

}  // namespace ccmd
