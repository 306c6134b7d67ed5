#pragma once

// Part of ccmd_dense_bench: revisits and a large loop correction with compacted keyframes
// (dense_bench_revisits.cc).

#include <vector>

#include "libccmd/dense/dense_map.h"
#include "libccmd/io/ply.h"
#include "libccmd/util/json.h"

namespace ccmd::dense_bench {

// `keyframes` at their true poses; `surface` the sequence's ground-truth surface. Prints the
// tables and returns the figures.
StatusOr<Json> RunRevisits(const std::vector<DenseKeyframe>& keyframes, const PointCloud& surface,
                           double voxel, int passes, double drift_deg);

}  // namespace ccmd::dense_bench
