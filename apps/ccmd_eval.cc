// ccmd_eval: evaluation tools over standard files.
//   ate    absolute trajectory error (evo_ape tum -a)
//   rpe    relative pose error
//   jumps  where a trajectory leaves the line between its neighbouring poses
//   shared how much of two estimates' errors against one ground truth they share
//   recon  reconstruction error between two PLY clouds
//   split  split-replay segments of a sequence
//   map-pictures  top and perspective pictures of a dense map (what ccmd_replay's report shows)

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include "apps/app_common.h"
#include "libccmd/eval/map_picture.h"
#include "libccmd/eval/plot.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/split.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"

namespace {

int Fail(const ccmd::Status& status) {
  std::fprintf(stderr, "ccmd_eval: %s\n", status.ToString().c_str());
  return 1;
}

// --gt: a TUM trajectory file, or a dataset folder (its groundtruth.txt, or a 7-Scenes
// sequence's pose files) read as the replay reads it.
ccmd::StatusOr<ccmd::Trajectory> ReadGroundTruth(const std::string& path) {
  if (!ccmd::IsDirectory(path)) return ccmd::ReadTumTrajectory(path);
  ccmd::PinholeCamera any;  // the poses need no camera
  auto sequence = ccmd::TumSequence::Open(path, any);
  if (!sequence.ok()) return sequence.status();
  if (sequence->groundtruth().empty()) return ccmd::NotFound(path + " has no ground truth");
  return sequence->groundtruth();
}

ccmd::Json StatsJson(const ccmd::ErrorStatistics& s) {
  ccmd::Json j;
  j["rmse"] = s.rmse;
  j["mean"] = s.mean;
  j["median"] = s.median;
  j["std"] = s.std;
  j["min"] = s.min;
  j["max"] = s.max;
  return j;
}

int RunAte(const std::string& gt_path, const std::string& est_path, const std::string& json_path,
           double max_diff, bool scale, const std::string& aligned_out) {
  auto gt = ReadGroundTruth(gt_path);
  if (!gt.ok()) return Fail(gt.status());
  auto est = ccmd::ReadTumTrajectory(est_path);
  if (!est.ok()) return Fail(est.status());
  ccmd::AteOptions options;
  options.max_time_difference = max_diff;
  options.correct_scale = scale;
  ccmd::LogOptions("ate", options);
  auto ate = ccmd::ComputeAte(*gt, *est, options);
  if (!ate.ok()) return Fail(ate.status());
  std::printf("ATE  matched %zu of %zu poses\n", ate->matched, est->size());
  std::printf("     rmse %.4f m  mean %.4f m  median %.4f m  std %.4f m  max %.4f m\n",
              ate->error.rmse, ate->error.mean, ate->error.median, ate->error.std, ate->error.max);
  if (scale) std::printf("     scale %.5f\n", ate->alignment.scale);
  if (!json_path.empty()) {
    ccmd::Json j;
    j["ate_rmse_m"] = ate->error.rmse;
    j["ate_mean_m"] = ate->error.mean;
    j["ate_median_m"] = ate->error.median;
    j["ate_std_m"] = ate->error.std;
    j["ate_min_m"] = ate->error.min;
    j["ate_max_m"] = ate->error.max;
    j["matched"] = ate->matched;
    j["estimated_poses"] = est->size();
    j["scale"] = ate->alignment.scale;
    const ccmd::Status s = ccmd::WriteJsonFile(j, json_path);
    if (!s.ok()) return Fail(s);
  }
  if (!aligned_out.empty()) {
    const ccmd::Status s = ccmd::WriteTumTrajectory(ccmd::TransformTrajectory(*est, ate->alignment),
                                                    aligned_out, "aligned to " + gt_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

int RunRpe(const std::string& gt_path, const std::string& est_path, const std::string& json_path,
           double max_diff, int delta) {
  auto gt = ReadGroundTruth(gt_path);
  if (!gt.ok()) return Fail(gt.status());
  auto est = ccmd::ReadTumTrajectory(est_path);
  if (!est.ok()) return Fail(est.status());
  ccmd::RpeOptions options;
  options.max_time_difference = max_diff;
  options.delta_frames = delta;
  ccmd::LogOptions("rpe", options);
  auto rpe = ccmd::ComputeRpe(*gt, *est, options);
  if (!rpe.ok()) return Fail(rpe.status());
  std::printf("RPE  %zu pairs, delta %d frames\n", rpe->pairs, delta);
  std::printf("     translation rmse %.4f m  mean %.4f m  max %.4f m\n", rpe->translation.rmse,
              rpe->translation.mean, rpe->translation.max);
  std::printf("     rotation    rmse %.3f deg mean %.3f deg max %.3f deg\n", rpe->rotation.rmse,
              rpe->rotation.mean, rpe->rotation.max);
  if (!json_path.empty()) {
    ccmd::Json j;
    j["pairs"] = rpe->pairs;
    j["delta_frames"] = delta;
    j["translation_m"] = StatsJson(rpe->translation);
    j["rotation_deg"] = StatsJson(rpe->rotation);
    const ccmd::Status s = ccmd::WriteJsonFile(j, json_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

int RunShared(const std::string& gt_path, const std::vector<std::string>& est_paths,
              const std::string& json_path, double max_diff) {
  if (est_paths.size() != 2) {
    return Fail(ccmd::InvalidArgument("shared compares two estimates: give --est twice"));
  }
  auto gt = ReadGroundTruth(gt_path);
  if (!gt.ok()) return Fail(gt.status());
  auto a = ccmd::ReadTumTrajectory(est_paths[0]);
  if (!a.ok()) return Fail(a.status());
  auto b = ccmd::ReadTumTrajectory(est_paths[1]);
  if (!b.ok()) return Fail(b.status());
  ccmd::AteOptions options;
  options.max_time_difference = max_diff;
  ccmd::LogOptions("ate", options);
  auto shared = ccmd::ComputeSharedError(*gt, *a, *b, options);
  if (!shared.ok()) return Fail(shared.status());
  std::printf("%zu ground-truth poses matched by both estimates, each aligned on its own\n",
              shared->matched);
  std::printf("     ATE rmse  first %.2f mm  second %.2f mm\n", shared->rmse_a * 1e3,
              shared->rmse_b * 1e3);
  std::printf(
      "     shared (a + b) / 2 rmse %.2f mm  apart (a - b) / 2 rmse %.2f mm  "
      "correlation %.2f\n",
      shared->shared_rmse * 1e3, shared->apart_rmse * 1e3, shared->correlation);
  if (!json_path.empty()) {
    ccmd::Json j;
    j["matched"] = shared->matched;
    j["ate_rmse_first_m"] = shared->rmse_a;
    j["ate_rmse_second_m"] = shared->rmse_b;
    j["shared_rmse_m"] = shared->shared_rmse;
    j["apart_rmse_m"] = shared->apart_rmse;
    j["correlation"] = shared->correlation;
    const ccmd::Status s = ccmd::WriteJsonFile(j, json_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

int RunJumps(const std::string& path, int top, const std::string& json_path) {
  auto trajectory = ccmd::ReadTumTrajectory(path);
  if (!trajectory.ok()) return Fail(trajectory.status());
  if (trajectory->size() < 3) {
    return Fail(ccmd::InvalidArgument(path + ": " + std::to_string(trajectory->size()) +
                                      " poses; jumps need at least 3"));
  }
  const std::vector<double> deviations = ccmd::NeighbourDeviations(*trajectory);
  const ccmd::ErrorStatistics stats =
      ccmd::ComputeStatistics(std::vector<double>(deviations.begin() + 1, deviations.end() - 1));
  std::vector<std::size_t> order(deviations.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return deviations[a] > deviations[b]; });
  order.resize(std::min<std::size_t>(order.size(), static_cast<std::size_t>(top)));
  std::printf(
      "off the line between neighbours, %zu poses: median %.2f mm  rmse %.2f mm  "
      "max %.2f mm\n",
      deviations.size() - 2, 1e3 * stats.median, 1e3 * stats.rmse, 1e3 * stats.max);
  for (std::size_t i : order) {
    std::printf("  pose %6zu  t %.6f  %7.2f mm\n", i, (*trajectory)[i].timestamp,
                1e3 * deviations[i]);
  }
  if (!json_path.empty()) {
    ccmd::Json j;
    j["poses"] = deviations.size();
    j["deviation_m"] = StatsJson(stats);
    ccmd::Json largest = ccmd::Json::MakeArray();
    for (std::size_t i : order) {
      ccmd::Json e;
      e["index"] = i;
      e["timestamp"] = (*trajectory)[i].timestamp;
      e["deviation_m"] = deviations[i];
      largest.Push(e);
    }
    j["largest"] = largest;
    const ccmd::Status s = ccmd::WriteJsonFile(j, json_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

int RunRecon(const std::string& ref_path, const std::string& rec_path, const std::string& json_path,
             const std::string& gt_traj, const std::string& est_traj, double alignment_arm,
             bool icp, bool point_to_point, double completeness_threshold) {
  auto ref = ccmd::ReadPly(ref_path);
  if (!ref.ok()) return Fail(ref.status());
  auto rec = ccmd::ReadPly(rec_path);
  if (!rec.ok()) return Fail(rec.status());
  if (!gt_traj.empty() || !est_traj.empty()) {
    // The map is in the estimate's world frame: move it into the ground truth's with the
    // alignment fitted to the keyframes' whole poses at the distance they see the map from,
    // as ccmd_replay's report does (positions alone leave the rotation to the noise on a short
    // path, and a degree tilts a room's walls by centimetres), so that its figures reproduce
    // here.
    if (gt_traj.empty() || est_traj.empty()) {
      return Fail(ccmd::InvalidArgument("--gt-traj and --est-traj go together"));
    }
    auto gt = ccmd::ReadTumTrajectory(gt_traj);
    if (!gt.ok()) return Fail(gt.status());
    auto est = ccmd::ReadTumTrajectory(est_traj);
    if (!est.ok()) return Fail(est.status());
    const double seen_from = ccmd::MapViewingDistance(*rec, *est);
    const double arm = alignment_arm > 0 ? alignment_arm : seen_from;
    auto ate = ccmd::AlignMap(*gt, *est, *rec, arm);
    if (!ate.ok()) return Fail(ate.status());
    std::printf(
        "aligned the reconstruction with the trajectory's poses, arms %.2f m (the map seen from "
        "%.2f m; ATE rmse %.4f m)\n",
        arm, seen_from, ate->error.rmse);
    for (auto& p : rec->points) p = (ate->alignment * p.cast<double>()).cast<float>();
  }
  // A mesh (e.g. ICL-NUIM's living room model) is its surface, not its vertices, as
  // ccmd_replay --reference takes it; point to point needs no normals fitted.
  if (!point_to_point || !ref->triangles.empty()) {
    std::string how;
    *ref = ccmd::AsReferenceSurface(std::move(*ref), &how);
    if (!how.empty()) std::printf("the reference: %s\n", how.c_str());
  }
  if (icp) {
    // Onto the reference's planes (fitted for this when the error is measured point to point).
    auto placed = ccmd::AlignByIcp(ref->HasNormals() ? *ref : ccmd::AsReferenceSurface(*ref), *rec);
    if (!placed.ok()) return Fail(placed.status());
    for (auto& p : rec->points) p = (placed->T_reference_map * p.cast<double>()).cast<float>();
    std::printf("placed on the reference by ICP: turned %.3f degrees, moved %.4f m\n",
                placed->turn_deg, placed->shift_m);
  }
  ccmd::ReconstructionOptions options;
  options.point_to_plane = !point_to_point;
  options.completeness_threshold = completeness_threshold;
  ccmd::LogOptions("reconstruction", options);
  auto error = ccmd::ComputeReconstructionError(*ref, *rec, options);
  if (!error.ok()) return Fail(error.status());
  std::printf("reconstruction %zu points vs reference %zu points (%s)\n",
              error->reconstructed_points, error->reference_points,
              error->point_to_plane ? "point-to-plane" : "point-to-point");
  std::printf("  rec->ref mean %.4f m  median %.4f m  p95 %.4f m  max %.4f m\n", error->mean,
              error->median, error->p95, error->max);
  std::printf("  rec->ref mean to the nearest reference point %.4f m\n",
              error->mean_point_to_point);
  std::printf("  ref->rec mean %.4f m  max %.4f m  completeness %.1f%% within %.3f m\n",
              error->mean_reverse, error->max_reverse, 100 * error->completeness,
              completeness_threshold);
  std::printf("  hausdorff %.4f m\n", error->hausdorff);
  if (!json_path.empty()) {
    ccmd::Json j;
    j["mean_m"] = error->mean;
    j["mean_point_to_point_m"] = error->mean_point_to_point;
    j["median_m"] = error->median;
    j["rmse_m"] = error->rmse;
    j["p95_m"] = error->p95;
    j["max_m"] = error->max;
    j["mean_reverse_m"] = error->mean_reverse;
    j["max_reverse_m"] = error->max_reverse;
    j["completeness"] = error->completeness;
    j["completeness_threshold_m"] = completeness_threshold;
    j["hausdorff_m"] = error->hausdorff;
    j["reconstructed_points"] = error->reconstructed_points;
    j["reference_points"] = error->reference_points;
    j["point_to_plane"] = error->point_to_plane;
    const ccmd::Status s = ccmd::WriteJsonFile(j, json_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

int RunSplit(int frames, const std::string& dataset, const std::string& config, int agents,
             double overlap) {
  if (!dataset.empty()) {
    ccmd::SourceOptions options;
    options.camera_config = config;
    options.configs_dir = ccmd::app::ConfigDir();
    auto source = ccmd::OpenSource("tum:" + dataset, options);
    if (!source.ok()) return Fail(source.status());
    frames = (*source)->FrameCount();
  }
  if (frames <= 0) return Fail(ccmd::InvalidArgument("give --frames N or --dataset DIR"));
  auto segments = ccmd::SplitWithOverlap(frames, agents, overlap);
  if (!segments.ok()) return Fail(segments.status());
  for (const auto& s : *segments) std::printf("%d %d\n", s.first, s.last);
  return 0;
}

// Agents named in a server's statistics ("agent_ids": {name: id}) get the report's colours,
// in name order.
int RunMapPictures(const std::string& map_path, const std::string& cameras_path,
                   const std::string& stats_path, const std::string& out) {
  auto map = ccmd::ReadPly(map_path);
  if (!map.ok()) return Fail(map.status());
  ccmd::Trajectory cameras;
  if (!cameras_path.empty()) {
    auto read = ccmd::ReadTumTrajectory(cameras_path);
    if (!read.ok()) return Fail(read.status());
    cameras = *read;
  }
  ccmd::MapPictureOptions options;
  if (!stats_path.empty()) {
    auto stats = ccmd::ReadJsonFile(stats_path);
    if (!stats.ok()) return Fail(stats.status());
    int index = 0;
    if (const ccmd::Json* ids = stats->Get("agent_ids")) {
      for (const auto& [name, id] : ids->object()) {
        options.agents[static_cast<int>(id.number())] = {name, ccmd::SeriesColor(index++)};
      }
    }
  }
  if (ccmd::Status s = ccmd::MakeDirectories(out); !s.ok()) return Fail(s);
  ccmd::LogOptions("pictures", options);
  if (ccmd::Status s = ccmd::WriteMapPictures(*map, cameras, options, out); !s.ok()) return Fail(s);
  std::printf("%s/map_top.png\n%s/map_view.png\n", out.c_str(), out.c_str());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"CCMD evaluation tools: trajectory error, reconstruction error, split ranges."};
  app.require_subcommand(1);

  std::string gt, est, json, aligned_out;
  double max_diff = 0.01;
  bool scale = false;
  auto* ate =
      app.add_subcommand("ate", "Absolute trajectory error after rigid alignment (evo_ape tum -a)");
  ate->add_option("--gt", gt,
                  "Ground-truth trajectory (TUM format), or a dataset folder (its "
                  "groundtruth.txt, or a 7-Scenes sequence's pose files)")
      ->required();
  ate->add_option("--est", est, "Estimated trajectory (TUM format)")->required();
  ate->add_option("--json", json, "Write the figures as JSON");
  ate->add_option("--max-diff", max_diff, "Timestamp matching tolerance (s)")
      ->capture_default_str();
  ate->add_flag("--correct-scale", scale, "Similarity alignment (monocular)");
  ate->add_option("--aligned-out", aligned_out, "Write the aligned estimate (TUM format)");

  int delta = 1;
  auto* rpe = app.add_subcommand("rpe", "Relative pose error");
  rpe->add_option("--gt", gt, "Ground-truth trajectory (TUM format), or a dataset folder")
      ->required();
  rpe->add_option("--est", est, "Estimated trajectory")->required();
  rpe->add_option("--json", json, "Write the figures as JSON");
  rpe->add_option("--max-diff", max_diff, "Timestamp matching tolerance (s)")
      ->capture_default_str();
  rpe->add_option("--delta", delta, "Frames between compared poses")->capture_default_str();

  std::string traj;
  int top = 10;
  auto* jumps = app.add_subcommand(
      "jumps",
      "How far each pose is from the line between its neighbours: where a trajectory (a ground "
      "truth made by tracking) jumps");
  jumps->add_option("--traj", traj, "Trajectory (TUM format)")->required();
  jumps->add_option("--top", top, "How many of the largest to list")
      ->capture_default_str()
      ->check(CLI::Range(0, 1000000));
  jumps->add_option("--json", json, "Write the figures as JSON");

  std::vector<std::string> ests;
  auto* shared = app.add_subcommand(
      "shared",
      "How much of two estimates' errors they share (e.g. runs on the frames forwards and "
      "backwards): what is shared is fixed to the frames (the reference's own error, or the "
      "sensor's), what is apart is the runs' own");
  shared->add_option("--gt", gt, "Ground-truth trajectory (TUM format), or a dataset folder")
      ->required();
  shared->add_option("--est", ests, "An estimated trajectory (TUM format); give two")->required();
  shared->add_option("--json", json, "Write the figures as JSON");
  shared->add_option("--max-diff", max_diff, "Timestamp matching tolerance (s)")
      ->capture_default_str();

  std::string ref, rec, gt_traj, est_traj;
  bool point_to_point = false;
  double completeness_threshold = 0.02;
  auto* recon = app.add_subcommand("recon", "Reconstruction error between two PLY clouds");
  recon
      ->add_option("--ref", ref,
                   "Reference cloud or mesh (e.g. surface.ply, a run's reference.ply, a dataset's "
                   "model); the map's error is measured to the plane of the nearest reference "
                   "point, its normal fitted to the reference's neighbours when the file has none")
      ->required();
  recon->add_option("--rec", rec, "Reconstructed cloud (e.g. map.ply)")->required();
  recon->add_option("--json", json, "Write the figures as JSON");
  recon->add_option("--gt-traj", gt_traj, "Ground-truth trajectory, to align the map first");
  recon->add_option("--est-traj", est_traj, "Estimated trajectory the map was built with");
  double alignment_arm = 0;
  recon
      ->add_option("--alignment-arm", alignment_arm,
                   "Metres along each pose's axes at which the alignment compares the poses "
                   "(0: the distance the keyframes see the map from, as ccmd_replay's report; "
                   "0.1: the report before)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  bool icp = false;
  recon->add_flag("--icp", icp,
                  "Then place the map on the reference by point-to-plane ICP (as the paper "
                  "aligns its maps) and measure it there");
  recon->add_flag("--point-to-point", point_to_point,
                  "Distance to the nearest reference point only (no normals)");
  recon
      ->add_option("--completeness-threshold", completeness_threshold,
                   "Distance (m) within which a reference point counts as covered")
      ->capture_default_str();

  int frames = 0, agents = 2;
  double overlap = 0.1;
  std::string dataset, config;
  auto* split = app.add_subcommand(
      "split", "Print split-replay segments: one 'first last' line each (0-based, inclusive)");
  split->add_option("--frames", frames, "Number of frames");
  split->add_option("--dataset", dataset, "Count the frames of this TUM-layout folder");
  split->add_option("--config", config, "Camera config for --dataset");
  split->add_option("--agents", agents, "Number of segments")->required()->check(CLI::Range(1, 64));
  split->add_option("--overlap", overlap, "Overlap as a fraction of the segment length")
      ->capture_default_str();

  std::string map_path, cameras_path, stats_path, pictures_out;
  auto* pictures = app.add_subcommand(
      "map-pictures",
      "Top and perspective pictures of a dense map: DIR/map_top.png, DIR/map_view.png");
  pictures->add_option("--map", map_path, "Dense map (map.ply of ccmd_server)")->required();
  pictures->add_option("--cameras", cameras_path,
                       "Keyframe trajectory in the map's frame (trajectory_fused.txt): where up "
                       "is, what is ceiling");
  pictures->add_option("--server-stats", stats_path,
                       "server_stats.json: agents' names for the agent colours");
  pictures->add_option("--out", pictures_out, "Folder for the pictures")->required();

  CLI11_PARSE(app, argc, argv);
  if (*pictures) return RunMapPictures(map_path, cameras_path, stats_path, pictures_out);
  if (*ate) return RunAte(gt, est, json, max_diff, scale, aligned_out);
  if (*rpe) return RunRpe(gt, est, json, max_diff, delta);
  if (*jumps) return RunJumps(traj, top, json);
  if (*shared) return RunShared(gt, ests, json, max_diff);
  if (*recon) {
    return RunRecon(ref, rec, json, gt_traj, est_traj, alignment_arm, icp, point_to_point,
                    completeness_threshold);
  }
  if (*split) return RunSplit(frames, dataset, config, agents, overlap);
  return 1;
}
