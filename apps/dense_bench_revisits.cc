// ccmd_dense_bench recon --passes N / --drift-deg D: what compacting keyframes that left the
// filter window costs in memory and accuracy when a place is revisited again and again, and
// after a large loop correction, against from-scratch builds with the final poses.

#include "apps/dense_bench_revisits.h"

#include <cmath>
#include <cstdio>

#include "libccmd/eval/reconstruction_error.h"

namespace ccmd::dense_bench {
namespace {

std::unique_ptr<DenseMap> MakeStore(double voxel, bool compact) {
  DenseMapOptions options;
  options.voxel_size_m = voxel;
  options.compact_keyframes = compact;
  auto store = DenseMap::Create(options);
  return store.ok() ? std::move(store).value() : nullptr;
}

// Adds every keyframe once more, with ids after the earlier passes'.
Status AddPass(DenseMap* store, const std::vector<DenseKeyframe>& keyframes, int pass,
               const std::vector<Pose>* poses = nullptr) {
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    DenseKeyframe k = keyframes[i];
    k.id.keyframe = KeyframeId(static_cast<std::uint32_t>(pass * keyframes.size() + i));
    if (poses) k.T_world_cam = (*poses)[i];
    CCMD_RETURN_IF_ERROR(store->AddKeyframe(k));
  }
  return Status::Ok();
}

struct MapFigures {
  std::size_t points = 0, stored = 0;
  std::size_t keyframes = 0, released = 0;  // entries held, and released (too few points)
  double memory_mb = 0;
  ReconstructionError surface;  // against the sequence's surface
  ReconstructionError
      scratch;  // against the exact from-scratch build (completeness: within a voxel)
};

StatusOr<MapFigures> Measure(DenseMap* store, const PointCloud& surface, const PointCloud* scratch,
                             double voxel) {
  MapFigures f;
  CCMD_ASSIGN_OR_RETURN(const PointCloud map, store->Extract(DenseSelection::Global()));
  const DenseMapStats stats = store->Stats();
  f.points = map.size();
  f.stored = stats.points;
  f.keyframes = stats.keyframes;
  f.released = stats.released_keyframes;
  f.memory_mb = stats.memory_bytes / 1e6;
  CCMD_ASSIGN_OR_RETURN(f.surface, ComputeReconstructionError(surface, map));
  if (scratch) {
    ReconstructionOptions within_voxel;
    within_voxel.point_to_plane = false;
    within_voxel.completeness_threshold = voxel;
    CCMD_ASSIGN_OR_RETURN(f.scratch, ComputeReconstructionError(*scratch, map, within_voxel));
  }
  return f;
}

Json FiguresJson(const MapFigures& f) {
  Json j;
  j["map_points"] = f.points;
  j["stored_points"] = f.stored;
  j["keyframes"] = f.keyframes;
  j["released_keyframes"] = f.released;
  j["memory_mb"] = f.memory_mb;
  j["mean_m"] = f.surface.mean;
  j["median_m"] = f.surface.median;
  j["completeness"] = f.surface.completeness;
  if (f.scratch.reference_points > 0) {
    j["coverage_of_scratch_within_voxel"] = f.scratch.completeness;
    j["distance_to_scratch_p95_m"] = f.scratch.p95;
  }
  return j;
}

void PrintRow(const std::string& what, const MapFigures& f) {
  std::printf("| %s | %zu | %zu | %zu (%zu) | %.1f | %.2f | %.2f | %.3f | %s |\n", what.c_str(),
              f.points, f.stored, f.keyframes, f.released, f.memory_mb, f.surface.mean * 1e3,
              f.surface.median * 1e3, f.surface.completeness,
              f.scratch.reference_points > 0
                  ? std::to_string(f.scratch.completeness).substr(0, 5).c_str()
                  : "-");
}

// The poses of a loop that drifted: keyframe i of n turned about the vertical through the
// room's centre by drift_deg i / n and shifted by 1.5 cm per degree of it.
std::vector<Pose> Drifted(const std::vector<DenseKeyframe>& keyframes, double drift_deg) {
  std::vector<Pose> poses;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    const double f = static_cast<double>(i) / keyframes.size();
    Pose drift = Pose::Identity();
    drift.linear() =
        Eigen::AngleAxisd(drift_deg * f * M_PI / 180, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    drift.translation() = Eigen::Vector3d(0.015 * drift_deg * f, -0.01 * drift_deg * f, 0);
    poses.push_back(drift * keyframes[i].T_world_cam);
  }
  return poses;
}

}  // namespace

StatusOr<Json> RunRevisits(const std::vector<DenseKeyframe>& keyframes, const PointCloud& surface,
                           double voxel, int passes, double drift_deg) {
  Json json;
  std::printf(
      "| store | map points | stored points | keyframes held (released) | memory MB | mean mm | "
      "median mm | completeness 2 cm | covers the exact build within a voxel |\n"
      "|---|---|---|---|---|---|---|---|---|\n");
  // The reference: every point kept, true poses.
  auto exact = MakeStore(voxel, false);
  CCMD_RETURN_IF_ERROR(AddPass(exact.get(), keyframes, 0));
  CCMD_ASSIGN_OR_RETURN(const PointCloud scratch, exact->Extract(DenseSelection::Global()));
  // Revisits: the same keyframes again and again, compacted and not.
  Json revisits = Json::MakeArray();
  auto compact = MakeStore(voxel, true), full = MakeStore(voxel, false);
  for (int pass = 0; pass < passes; ++pass) {
    CCMD_RETURN_IF_ERROR(AddPass(compact.get(), keyframes, pass));
    CCMD_RETURN_IF_ERROR(AddPass(full.get(), keyframes, pass));
    CCMD_ASSIGN_OR_RETURN(const MapFigures c, Measure(compact.get(), surface, &scratch, voxel));
    CCMD_ASSIGN_OR_RETURN(const MapFigures x, Measure(full.get(), surface, &scratch, voxel));
    PrintRow("compacted, pass " + std::to_string(pass + 1), c);
    PrintRow("every point, pass " + std::to_string(pass + 1), x);
    std::fflush(stdout);
    Json row;
    row["pass"] = pass + 1;
    row["compacted"] = FiguresJson(c);
    row["every_point"] = FiguresJson(x);
    revisits.Push(row);
  }
  json["revisits"] = revisits;
  if (drift_deg > 0) {
    // A loop that drifted, then its correction (a pose graph), with compaction.
    auto corrected = MakeStore(voxel, true);
    const std::vector<Pose> drifted = Drifted(keyframes, drift_deg);
    CCMD_RETURN_IF_ERROR(AddPass(corrected.get(), keyframes, 0, &drifted));
    CCMD_ASSIGN_OR_RETURN(const MapFigures before,
                          Measure(corrected.get(), surface, &scratch, voxel));
    std::vector<KeyframePose> loop;
    for (std::size_t i = 0; i < keyframes.size(); ++i) {
      loop.push_back({{keyframes[i].id.agent, KeyframeId(static_cast<std::uint32_t>(i))},
                      keyframes[i].T_world_cam});
    }
    CCMD_RETURN_IF_ERROR(corrected->UpdateLoopPoses(loop));
    corrected->Maintain();
    CCMD_ASSIGN_OR_RETURN(const MapFigures after,
                          Measure(corrected.get(), surface, &scratch, voxel));
    CCMD_ASSIGN_OR_RETURN(const MapFigures reference,
                          Measure(exact.get(), surface, &scratch, voxel));
    PrintRow("drifted " + std::to_string(drift_deg).substr(0, 4) +
                 " deg, compacted, before the correction",
             before);
    PrintRow("after the loop correction, compacted", after);
    PrintRow("from scratch with the final poses, every point", reference);
    Json loop_json;
    loop_json["drift_deg"] = drift_deg;
    loop_json["before"] = FiguresJson(before);
    loop_json["after"] = FiguresJson(after);
    loop_json["from_scratch"] = FiguresJson(reference);
    json["loop_correction"] = loop_json;
  }
  return json;
}

}  // namespace ccmd::dense_bench
