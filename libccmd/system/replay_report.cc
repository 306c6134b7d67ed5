#include "libccmd/system/replay_report.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "libccmd/dense/dense_map.h"
#include "libccmd/dense/label.h"
#include "libccmd/eval/map_picture.h"
#include "libccmd/eval/plot.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/system/link_report.h"
#include "libccmd/system/report_format.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "proto/messages.h"

namespace ccmd {

Status ReferenceOptions::Validate() const {
  if (stride < 1) return InvalidArgument("reference stride must be at least 1");
  if (first < 0) return InvalidArgument("reference first frame must be >= 0");
  if (downsample < 1 || downsample > 16)
    return InvalidArgument("reference downsample must be 1..16");
  if (!(voxel_m > 0)) return InvalidArgument("reference voxel must be positive");
  if (registration) CCMD_RETURN_IF_ERROR(registration->depth.Validate().WithContext("Depth block"));
  return Status::Ok();
}

void ReferenceOptions::Describe(OptionsWriter* out) const {
  out->Add("reference_ply", reference_ply);
  out->Add("first", first);
  out->Add("stride", stride);
  out->Add("downsample", downsample);
  out->Add("voxel_m", voxel_m);
  out->Add("registration", registration ? "Depth block" : "none");
  out->Add("ground_truth_camera_in_colour_m", T_color_trajectory.translation().norm());
}

Status ReadReferenceCamera(const std::string& camera_file, ReferenceOptions* options) {
  if (!FileExists(camera_file)) return Status::Ok();
  CCMD_ASSIGN_OR_RETURN(options->registration, LoadDepthToColorCalibration(camera_file));
  CCMD_ASSIGN_OR_RETURN(const Pose T_color_trajectory, LoadTrajectoryCamera(camera_file));
  if (options->registration) options->T_color_trajectory = T_color_trajectory;
  return Status::Ok();
}

StatusOr<PointCloud> LoadOrBuildReference(const TumSequence& dataset,
                                          const ReferenceOptions& options, std::string* source) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  std::string path = options.reference_ply;
  if (path.empty() && FileExists(JoinPath(dataset.folder(), "surface.ply")))
    path = JoinPath(dataset.folder(), "surface.ply");
  if (!path.empty()) {
    CCMD_ASSIGN_OR_RETURN(PointCloud cloud, ReadPly(path));
    std::string how;
    cloud = AsReferenceSurface(std::move(cloud), &how);
    if (source) *source = how.empty() ? path : path + " (" + how + ")";
    return cloud;
  }
  // Ground-truth poses and the same depth: the best map the depth can make.
  DenseMapOptions dense_options;
  dense_options.voxel_size_m = options.voxel_m;
  CCMD_ASSIGN_OR_RETURN(auto dense, DenseMap::Create(dense_options));
  const int factor = std::max(1, options.downsample);
  int added = 0;
  for (std::size_t i = options.first; i < dataset.size(); i += options.stride) {
    if (!dataset.frame(i).T_world_cam_gt) continue;
    CCMD_ASSIGN_OR_RETURN(RgbdFrame frame, dataset.LoadFrame(i));
    DenseKeyframe kf;
    kf.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(i))};
    kf.T_world_cam = *dataset.frame(i).T_world_cam_gt * options.T_color_trajectory.inverse();
    cv::Mat depth = frame.depth_mm, bgr = frame.bgr;
    if (options.registration) {
      CCMD_ASSIGN_OR_RETURN(depth, RegisterDepth(depth, *options.registration, dataset.camera()));
    }
    if (bgr.size() != depth.size()) cv::resize(bgr, bgr, depth.size(), 0, 0, cv::INTER_AREA);
    if (factor > 1) {
      // Nearest (not averaging) for depth: no mixed depths across edges.
      cv::resize(depth, depth, cv::Size(depth.cols / factor, depth.rows / factor), 0, 0,
                 cv::INTER_NEAREST);
      cv::resize(bgr, bgr, depth.size(), 0, 0, cv::INTER_AREA);
    }
    kf.depth_mm = depth;
    kf.bgr = bgr;
    kf.camera = dataset.camera().Resized(depth.cols, depth.rows);
    CCMD_RETURN_IF_ERROR(dense->AddKeyframe(kf));
    ++added;
  }
  if (added == 0) return NotFound("no frames with ground truth to build a reference cloud from");
  // With normals the map's error is measured to the reference's local plane: the voxel
  // sampling alone puts a map lying on the true surface 0.4 voxel from the nearest sample.
  CCMD_ASSIGN_OR_RETURN(PointCloud cloud, dense->Extract(DenseSelection::Global()));
  std::string how;
  cloud = AsReferenceSurface(std::move(cloud), &how);
  if (source) {
    *source = "back-projected from " + std::to_string(added) + " ground-truth frames (every " +
              std::to_string(options.stride) + "th, 1/" + std::to_string(factor) + " resolution, " +
              std::to_string(static_cast<int>(options.voxel_m * 1000)) + " mm voxels, " + how + ")";
  }
  return cloud;
}

namespace {

using report::FindAgentTraffic;
using report::Fmt;
using report::Num;

// The plane of most motion of the ground truth (its two principal directions): a "top view"
// that does not depend on which world axis is up.
Eigen::Matrix<double, 2, 3> ViewPlane(const Trajectory& gt) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& p : gt) mean += p.T_world_cam.translation();
  mean /= std::max<std::size_t>(1, gt.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : gt) {
    const Eigen::Vector3d d = p.T_world_cam.translation() - mean;
    cov += d * d.transpose();
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(cov);
  Eigen::Matrix<double, 2, 3> P;
  P.row(0) = eig.eigenvectors().col(2).transpose();
  P.row(1) = eig.eigenvectors().col(1).transpose();
  return P;
}

PlotSeries Projected(const Trajectory& t, const Eigen::Matrix<double, 2, 3>& P,
                     const std::string& label, cv::Scalar color, int thickness) {
  PlotSeries s;
  s.label = label;
  s.color = color;
  s.thickness = thickness;
  for (const auto& p : t) {
    const Eigen::Vector2d q = P * p.T_world_cam.translation();
    s.x.push_back(q.x());
    s.y.push_back(q.y());
  }
  return s;
}

// Which map each agent's keyframes ended in, from server_stats.json ("agent_maps"; runs
// written before it only say how many maps there were), and how many of them are placed
// ("agent_placed_keyframes"): an agent whose keyframes all wait unplaced in the primary map
// (a fusion through a restarted segment) is in none of its outputs.
struct MapMembership {
  int primary = -1;
  std::map<std::string, int> map_of;
  std::map<std::string, int> placed;

  bool InPrimary(const std::string& agent) const {
    const auto it = map_of.find(agent);
    return it != map_of.end() && it->second == primary && !Unplaced(agent);
  }
  bool Unplaced(const std::string& agent) const {
    const auto it = placed.find(agent);
    return it != placed.end() && it->second == 0;
  }
  std::vector<std::string> PrimaryAgents() const {
    std::vector<std::string> names;
    for (const auto& [name, map] : map_of) {
      if (InPrimary(name)) names.push_back(name);
    }
    return names;
  }
};

MapMembership ReadMembership(const Json& stats, int agents) {
  MapMembership m;
  m.primary = static_cast<int>(Num(&stats, "primary_map", -1));
  if (const Json* maps = stats.Get("agent_maps")) {
    for (int i = 1; i <= agents; ++i) {
      const std::string name = "agent" + std::to_string(i);
      if (maps->Has(name)) m.map_of[name] = static_cast<int>(Num(maps, name));
      if (const Json* placed = stats.Get("agent_placed_keyframes"); placed && placed->Has(name))
        m.placed[name] = static_cast<int>(Num(placed, name));
    }
  } else if (Num(stats.Get("backend"), "maps", -1) == 1) {
    for (int i = 1; i <= agents; ++i) m.map_of["agent" + std::to_string(i)] = m.primary;
  }
  return m;
}

// The ATE of one map's keyframes (in that map's frame), aligned by positions as evo does. Maps
// of one or two keyframes, or of keyframes within a centimetre of a line (agents that did not
// fuse often have such maps), are aligned by the keyframes' whole poses instead: positions
// cannot fix the rotation there, and the dense map would be tilted with it.
std::optional<AteResult> MapAte(const Trajectory& gt, const Trajectory& keyframes) {
  if (gt.empty() || keyframes.empty()) return std::nullopt;
  AteOptions options;
  options.pose_alignment_below_spread_m = 0.01;
  auto ate = ComputeAte(gt, keyframes, options);
  if (!ate.ok()) return std::nullopt;
  return *ate;
}

std::string JoinNames(const std::vector<std::string>& names) {
  std::string out;
  for (const std::string& n : names) out += (out.empty() ? "" : ", ") + n;
  return out.empty() ? "none" : out;
}

// plots/map_top.png and plots/map_view.png, drawn from the server's map.ply (in its own world
// frame, up from its keyframes); agents coloured as in the other plots. False without a map.
bool WriteMapPlots(const std::string& server_dir, const std::string& plots_dir,
                   const Json& server_stats, int agents) {
  auto map = ReadPly(JoinPath(server_dir, "map.ply"));
  if (!map.ok() || map->size() == 0) return false;
  auto cameras = ReadTumTrajectory(JoinPath(server_dir, "trajectory_fused.txt"));
  MapPictureOptions options;
  const Json* ids = server_stats.Get("agent_ids");
  for (int i = 1; i <= agents; ++i) {
    const std::string name = "agent" + std::to_string(i);
    if (ids && ids->Get(name))
      options.agents[static_cast<int>(ids->Get(name)->number())] = {name, SeriesColor(i - 1)};
  }
  const Status s =
      WriteMapPictures(*map, cameras.ok() ? *cameras : Trajectory{}, options, plots_dir);
  if (!s.ok()) CCMD_LOG(WARNING) << "map pictures: " << s.ToString();
  return s.ok();
}

// Reconstruction error of the server's map.ply, moved into the ground truth's frame by
// `alignment`, into `results`; returns each agent's mean error by its id (the points' labels:
// which keyframe, so which agent, each came from), empty without a map or a reference.
std::map<std::uint32_t, double> EvaluateMap(const std::string& run_dir, const TumSequence& dataset,
                                            const ReferenceOptions& reference,
                                            const Similarity3& alignment, Json* results) {
  std::map<std::uint32_t, double> by_agent;
  const std::string map_path = JoinPath(run_dir, "map.ply");
  if (!FileExists(map_path)) return by_agent;
  std::string source;
  auto ref = LoadOrBuildReference(dataset, reference, &source);
  if (!ref.ok()) {
    CCMD_LOG(WARNING) << "no reference cloud: " << ref.status().ToString();
    return by_agent;
  }
  // A reference built here is kept, so that the map can be compared again (ccmd_eval recon).
  if (reference.reference_ply.empty() && !FileExists(JoinPath(dataset.folder(), "surface.ply"))) {
    const Status kept = WritePly(*ref, JoinPath(run_dir, "reference.ply"));
    if (!kept.ok()) CCMD_LOG(WARNING) << kept.ToString();
  }
  auto rec = ReadPly(map_path);
  if (!rec.ok() || rec->size() == 0) return by_agent;
  for (auto& p : rec->points) p = (alignment * p.cast<double>()).cast<float>();
  std::vector<double> per_point;
  auto error = ComputeReconstructionError(*ref, *rec, {}, &per_point);
  if (!error.ok()) return by_agent;
  Json& r = *results;
  r["recon_mean_m"] = error->mean;
  r["recon_mean_point_to_point_m"] = error->mean_point_to_point;
  r["recon_median_m"] = error->median;
  r["recon_p95_m"] = error->p95;
  r["recon_hausdorff_m"] = error->hausdorff;
  r["recon_max_map_to_reference_m"] = error->max;
  r["recon_max_reference_to_map_m"] = error->max_reverse;
  r["recon_completeness"] = error->completeness;
  r["map_points"] = rec->size();
  r["reference"] = source;
  r["reference_points"] = ref->size();
  if (rec->HasLabels()) {
    std::map<std::uint32_t, std::pair<double, std::size_t>> sums;
    for (std::size_t i = 0; i < rec->size(); ++i) {
      auto& [sum, count] = sums[DecodeLabel(rec->labels[i]).agent.value()];
      sum += per_point[i];
      ++count;
    }
    for (const auto& [agent, sum_count] : sums)
      by_agent[agent] = sum_count.first / static_cast<double>(sum_count.second);
  }
  return by_agent;
}

}  // namespace

StatusOr<Json> EvaluateReplay(const std::string& run_dir, const TumSequence& dataset,
                              const ReplayRunInfo& info, const ReferenceOptions& reference) {
  const std::string& server_dir = run_dir;  // the server writes its results into the run folder
  const std::string plots_dir = JoinPath(run_dir, "plots");
  CCMD_RETURN_IF_ERROR(MakeDirectories(plots_dir));
  CCMD_ASSIGN_OR_RETURN(const Json server_stats,
                        ReadJsonFile(JoinPath(server_dir, "server_stats.json")));
  const Trajectory gt = dataset.GroundTruthAtFrames();
  Json results;
  results["dataset"] = info.dataset_dir;
  results["agents_count"] = info.agents;
  results["command"] = info.command;
  results["wall_seconds"] = info.wall_seconds;
  const Json* backend = server_stats.Get("backend");
  results["maps_after_fusion"] = Num(backend, "maps", -1);
  results["loops"] = Num(backend, "loops");
  results["fusions"] = Num(backend, "fusions");
  results["global_ba_runs"] = Num(backend, "global_ba_runs");
  results["segments_restarted"] = Num(backend, "segments_restarted");
  results["segments_placed"] = Num(backend, "segments_placed");
  results["segments_unplaced"] = Num(backend, "segments_unplaced");

  // Trajectories: the agents' own odometry, then the primary map's keyframes (every agent's
  // when all fused; otherwise those of the agents in it, named in the results).
  const MapMembership membership = ReadMembership(server_stats, info.agents);
  const std::vector<std::string> primary_agents = membership.PrimaryAgents();
  Json primary_names = Json::MakeArray();
  for (const std::string& n : primary_agents) primary_names.Push(n);
  results["primary_map_agents"] = primary_names;
  bool all_fused = results["maps_after_fusion"].number() == 1;
  for (int i = 1; i <= info.agents; ++i)
    all_fused = all_fused && !membership.Unplaced("agent" + std::to_string(i));
  results["all_maps_fused"] = all_fused;
  std::optional<AteResult> fused_ate;
  auto read_fused = ReadTumTrajectory(JoinPath(server_dir, "trajectory_fused.txt"));
  // The dense map is put in the ground truth's frame by the alignment fitted to the keyframes'
  // whole poses: on a short or nearly straight path, positions leave the rotation to the
  // noise (a degree tilts the map by 3-5 cm at the room's walls); on a long one both agree.
  std::optional<Similarity3> map_alignment;
  if (read_fused.ok()) {
    AteOptions by_poses;
    by_poses.pose_alignment_below_spread_m = std::numeric_limits<double>::infinity();
    auto posed = ComputeAte(gt, *read_fused, by_poses);
    if (posed.ok()) map_alignment = posed->alignment;
    fused_ate = MapAte(gt, *read_fused);
    if (fused_ate) {
      results["ate_rmse_m"] = fused_ate->error.rmse;
      results["ate_mean_m"] = fused_ate->error.mean;
      results["ate_max_m"] = fused_ate->error.max;
      results["fused_keyframes"] = fused_ate->matched;
      results["ate_aligned_by"] = fused_ate->aligned_by_poses ? "poses" : "positions";
    }
  }
  const std::map<std::uint32_t, double> map_error_of_agent =
      map_alignment ? EvaluateMap(run_dir, dataset, reference, *map_alignment, &results)
                    : std::map<std::uint32_t, double>{};
  const Json* agent_ids = server_stats.Get("agent_ids");
  Json agents = Json::MakeArray();
  std::vector<Trajectory> agent_trajectories;
  double atps_sum = 0, akfs_sum = 0, akfr_sum = 0;
  int with_traffic = 0;
  KeyframeSizeBreakdown parts_total;
  double keyframes_total = 0, rgbd_keyframes_total = 0;
  double naive_pose = 0, naive_keypoints = 0, naive_descriptors = 0, naive_points = 0,
         naive_colour = 0, naive_depth = 0;
  for (int i = 1; i <= info.agents; ++i) {
    const std::string name = "agent" + std::to_string(i);
    Json a;
    a["name"] = name;
    if (i - 1 < static_cast<int>(info.segments.size())) {
      a["first_frame"] = info.segments[i - 1].first;
      a["last_frame"] = info.segments[i - 1].last;
    }
    auto t = ReadTumTrajectory(JoinPath(server_dir, "trajectory_" + name + ".txt"));
    agent_trajectories.push_back(t.ok() ? *t : Trajectory{});
    a["in_primary_map"] = membership.InPrimary(name);
    if (const Json* id = agent_ids ? agent_ids->Get(name) : nullptr) {
      const auto found = map_error_of_agent.find(static_cast<std::uint32_t>(id->number()));
      if (found != map_error_of_agent.end()) a["map_mean_error_m"] = found->second;
    }
    if (t.ok()) {
      const auto ate = MapAte(gt, *t);
      if (ate) a["ate_rmse_m"] = ate->error.rmse;
    }
    auto frames = ReadTumTrajectory(JoinPath(run_dir, "agents/" + name + "_frames.txt"));
    if (frames.ok() && !gt.empty()) {
      auto ate = ComputeAte(gt, *frames);
      if (ate.ok()) a["agent_frames_ate_rmse_m"] = ate->error.rmse;  // the agent's own odometry
    }
    const Json* traffic = FindAgentTraffic(server_stats, name);
    if (traffic) {
      const Json* kf =
          traffic->Get("messages") ? traffic->Get("messages")->Get("keyframe") : nullptr;
      a["keyframes"] = Num(kf, "count");
      a["bytes"] =
          Num(kf, "bytes") +
          Num(traffic->Get("messages") ? traffic->Get("messages")->Get("pose_update") : nullptr,
              "bytes");
      a["atps_kBps"] = Num(traffic, "average_traffic_bytes_per_s") / 1e3;
      a["akfs_kB"] = Num(traffic, "average_keyframe_bytes") / 1e3;
      a["akfr_hz"] = Num(traffic, "keyframe_rate_hz");
      atps_sum += a["atps_kBps"].number();
      akfs_sum += a["akfs_kB"].number();
      akfr_sum += a["akfr_hz"].number();
      ++with_traffic;
      if (const Json* p = traffic->Get("keyframe_parts_bytes")) {
        parts_total.pose += static_cast<std::size_t>(Num(p, "pose"));
        parts_total.keypoints += static_cast<std::size_t>(Num(p, "keypoints"));
        parts_total.descriptors += static_cast<std::size_t>(Num(p, "descriptors"));
        parts_total.map_points += static_cast<std::size_t>(Num(p, "map_points"));
        parts_total.colour += static_cast<std::size_t>(Num(p, "colour"));
        parts_total.depth += static_cast<std::size_t>(Num(p, "depth"));
        parts_total.other += static_cast<std::size_t>(Num(p, "other"));
      }
    }
    auto agent_stats = ReadJsonFile(JoinPath(run_dir, "agents/" + name + "_stats.json"));
    if (agent_stats.ok()) {
      a["frames"] = Num(&*agent_stats, "frames");
      a["lost_frames"] = Num(&*agent_stats, "lost_frames");
      a["restarts"] = Num(&*agent_stats, "restarts");
      a["fps"] = Num(&*agent_stats, "fps");
      if (const Json* link = agent_stats->Get("link")) {
        const double k = Num(link, "keyframes_sent");
        keyframes_total += k;
        rgbd_keyframes_total += Num(link, "rgbd_keyframes_sent");
        a["rgbd_keyframes"] = Num(link, "rgbd_keyframes_sent");
        // What a format without any of the packing would need: a 4x4 float pose, 5 floats per
        // keypoint, every descriptor, an id and xyz floats per keypoint's map point, colour at
        // 3 bytes and depth as a float per pixel of the full image for every keyframe.
        naive_pose += 64 * k;
        naive_keypoints += 20 * Num(link, "keypoints_extracted");
        naive_descriptors += 32 * Num(link, "keypoints_extracted");
        naive_points += 16 * Num(link, "keypoints_extracted");
        naive_colour += 3 * Num(link, "full_rgbd_pixels");
        naive_depth += 4 * Num(link, "full_rgbd_pixels");
      }
    }
    for (const ReplayProcess& p : info.processes) {
      if (p.name != name) continue;
      a["cpu_seconds"] = p.cpu_seconds;
      a["cpu_percent"] = p.wall_seconds > 0 ? 100 * p.cpu_seconds / p.wall_seconds : 0.0;
      a["max_rss_mb"] = p.max_rss_mb;
    }
    agents.Push(a);
  }
  results["agents"] = agents;
  // Rates per second of dataset time: each agent's bytes and keyframes over its segment's duration.
  double dataset_bytes_per_s = 0, dataset_keyframes_per_s = 0;
  int with_duration = 0;
  for (const Json& a : agents.array()) {
    const int first = static_cast<int>(Num(&a, "first_frame", -1)),
              last = static_cast<int>(Num(&a, "last_frame", -1));
    if (first < 0 || last <= first || last >= static_cast<int>(dataset.size())) continue;
    const double duration = dataset.frame(last).timestamp - dataset.frame(first).timestamp;
    if (duration <= 0) continue;
    dataset_bytes_per_s += Num(&a, "bytes") / duration;
    dataset_keyframes_per_s += Num(&a, "keyframes") / duration;
    ++with_duration;
  }
  if (with_duration) {
    results["atps_dataset_kBps"] = dataset_bytes_per_s / with_duration / 1e3;
    results["akfr_dataset_hz"] = dataset_keyframes_per_s / with_duration;
  }
  if (with_traffic) {
    results["atps_kBps"] = atps_sum / with_traffic;
    results["akfs_kB"] = akfs_sum / with_traffic;
    results["akfr_hz"] = akfr_sum / with_traffic;
  }
  for (const ReplayProcess& p : info.processes) {
    if (p.name != "server") continue;
    results["server_cpu_seconds"] = p.cpu_seconds;
    results["server_cpu_percent"] = p.wall_seconds > 0 ? 100 * p.cpu_seconds / p.wall_seconds : 0.0;
    results["server_max_rss_mb"] = p.max_rss_mb;
    results["server_peak_rss_mb"] = p.max_rss_mb;  // the name ccmd_load reports it under
  }
  Json memory = Json::MakeArray();
  for (const auto& [t, keyframes, rss_mb] : info.server_memory) {
    Json sample;
    sample["t_s"] = t;
    sample["keyframes"] = keyframes;
    sample["rss_mb"] = rss_mb;
    memory.Push(sample);
  }
  results["server_memory"] = memory;
  const double k = std::max(1.0, keyframes_total);
  Json kinds = Json::MakeArray();
  const std::vector<std::tuple<std::string, double, double>> per_kind = {
      {"pose", parts_total.pose / k, naive_pose / k},
      {"keypoints", parts_total.keypoints / k, naive_keypoints / k},
      {"descriptors", parts_total.descriptors / k, naive_descriptors / k},
      {"map points", parts_total.map_points / k, naive_points / k},
      {"colour", parts_total.colour / k, naive_colour / k},
      {"depth", parts_total.depth / k, naive_depth / k},
      {"other", parts_total.other / k, 0.0}};
  for (const auto& [kind, ours, naive] : per_kind) {
    Json e;
    e["kind"] = kind;
    e["bytes_per_keyframe"] = ours;
    e["uncompressed_bytes_per_keyframe"] = naive;
    kinds.Push(e);
  }
  results["bytes_per_kind"] = kinds;
  results["rgbd_keyframe_fraction"] = rgbd_keyframes_total / k;
  results["rgbd_keyframes"] = rgbd_keyframes_total;
  results["keyframes_sent"] = keyframes_total;
  results["colour_bytes"] = static_cast<double>(parts_total.colour);
  results["depth_bytes"] = static_cast<double>(parts_total.depth);

  // Plots.
  const bool map_plots = WriteMapPlots(server_dir, plots_dir, server_stats, info.agents);
  if (!gt.empty()) {
    const auto P = ViewPlane(gt);
    std::vector<PlotSeries> series = {
        Projected(gt, P, "ground truth", cv::Scalar(160, 160, 160), 4)};
    for (std::size_t i = 0; i < agent_trajectories.size(); ++i) {
      Trajectory aligned = fused_ate
                               ? TransformTrajectory(agent_trajectories[i], fused_ate->alignment)
                               : agent_trajectories[i];
      series.push_back(Projected(aligned, P, "agent" + std::to_string(i + 1),
                                 SeriesColor(static_cast<int>(i)), 2));
      series.back().points = true;
    }
    PlotOptions o;
    o.title = "Keyframe trajectories (top view, aligned to ground truth)";
    o.x_label = "metres";
    o.y_label = "metres";
    o.equal_aspect = true;
    WritePng(PlotLines(series, o), JoinPath(plots_dir, "trajectories.png")).IgnoreError();
  }
  {
    std::vector<PlotSeries> series;
    for (int i = 1; i <= info.agents; ++i) {
      const Json* traffic = FindAgentTraffic(server_stats, "agent" + std::to_string(i));
      if (!traffic || !traffic->Get("per_bucket")) continue;
      PlotSeries s;
      s.label = "agent" + std::to_string(i);
      s.color = SeriesColor(i - 1);
      const double bucket = Num(server_stats.Get("transport"), "bucket_seconds", 1.0);
      for (const Json& b : traffic->Get("per_bucket")->array()) {
        s.x.push_back(Num(&b, "t"));
        s.y.push_back(Num(&b, "bytes") / 1e3 / bucket);
      }
      series.push_back(s);
    }
    PlotOptions o;
    o.title = "Traffic per agent";
    o.x_label = "seconds since the server started";
    o.y_label = "kB/s";
    WritePng(PlotLines(series, o), JoinPath(plots_dir, "traffic.png")).IgnoreError();
  }
  {
    std::vector<BarGroup> groups;
    for (const auto& [kind, ours, naive] : per_kind) {
      if (kind == "other") continue;
      groups.push_back({kind, {ours, naive}});
    }
    PlotOptions o;
    o.title = "Bytes per keyframe by kind (log scale)";
    o.y_label = "log10(bytes)";
    WritePng(PlotBars(groups, {"sent", "uncompressed"}, {SeriesColor(0), SeriesColor(6)}, o,
                      /*log_scale=*/true),
             JoinPath(plots_dir, "bytes_per_kind.png"))
        .IgnoreError();
  }
  {
    std::vector<PlotSeries> series;
    int index = 0;
    for (const ReplayProcess& p : info.processes) {
      PlotSeries s;
      s.label = p.name;
      s.color = p.name == "server" ? cv::Scalar(0, 0, 0) : SeriesColor(index++);
      for (const auto& [t, cpu] : p.cpu_percent) {
        s.x.push_back(t);
        s.y.push_back(cpu);
      }
      series.push_back(s);
    }
    PlotOptions o;
    o.title = "CPU use per process";
    o.x_label = "seconds";
    o.y_label = "% of one core";
    WritePng(PlotLines(series, o), JoinPath(plots_dir, "cpu.png")).IgnoreError();
  }
  if (!info.server_memory.empty()) {
    PlotSeries s;
    s.label = "server";
    s.color = cv::Scalar(0, 0, 0);
    for (const auto& [t, keyframes, rss_mb] : info.server_memory) {
      s.x.push_back(keyframes);
      s.y.push_back(rss_mb);
    }
    PlotOptions o;
    o.title = "Server resident memory";
    o.x_label = "keyframes in the server's maps";
    o.y_label = "MB";
    WritePng(PlotLines({s}, o), JoinPath(plots_dir, "server_memory.png")).IgnoreError();
  }

  // report.md
  std::ostringstream md;
  md << "# Split-replay report\n\n";
  md << "- dataset: `" << info.dataset_dir << "` (" << dataset.size() << " frames)\n";
  md << "- agents: " << info.agents << ", pace: " << info.rate << ", wall time "
     << Fmt("%.1f", info.wall_seconds) << " s\n";
  md << "- command: `" << info.command << "`\n";
  if (!info.config.empty()) md << "- config: `" << info.config << "` (copied to config.yaml)\n";
  md << "\n## Maps and trajectories\n\n";
  md << "Maps left after fusion: " << results["maps_after_fusion"].number() << " (loops "
     << results["loops"].number() << ", fusions " << results["fusions"].number()
     << ", global BA runs " << results["global_ba_runs"].number() << ")\n\n";
  if (const double restarted = results["segments_restarted"].number(); restarted > 0) {
    const double unplaced = results["segments_unplaced"].number();
    md << "Agents lost tracking and restarted " << restarted << " time(s) in a new map segment; "
       << (unplaced > 0 ? Fmt("%.0f", unplaced) +
                              " segment(s) no loop has placed are left out of the trajectories "
                              "and the dense map (the agents' own trajectories keep them).\n\n"
                        : std::string("loops placed every segment.\n\n"));
  }
  if (!results["all_maps_fused"].boolean()) {
    std::vector<std::string> others, unplaced;
    for (int i = 1; i <= info.agents; ++i) {
      const std::string name = "agent" + std::to_string(i);
      if (membership.Unplaced(name)) {
        unplaced.push_back(name);
      } else if (!membership.InPrimary(name)) {
        others.push_back(name);
      }
    }
    md << "**Not every map fused.** The fused trajectory and the dense map below are the primary "
          "map's, which holds "
       << JoinNames(primary_agents);
    if (!others.empty()) {
      md << "; " << JoinNames(others)
         << " kept their own maps: their server ATE in the table is in their own map's frame";
    }
    if (!unplaced.empty()) {
      md << "; the keyframes of " << JoinNames(unplaced)
         << " wait unplaced in it (they joined through a restarted segment no loop has placed)";
    }
    md << ".\n\n";
  }
  md << "| agent | frames | map | server keyframes | ATE RMSE (server, m) | ATE RMSE (agent "
        "odometry, m) | its map points' mean error (m) | lost frames | restarts |\n"
        "|---|---|---|---|---|---|---|---|---|\n";
  for (const Json& a : agents.array()) {
    md << "| " << a.Get("name")->string() << " | " << Num(&a, "first_frame") << "-"
       << Num(&a, "last_frame") << " | "
       << (a.Get("in_primary_map")->boolean()             ? "primary"
           : membership.Unplaced(a.Get("name")->string()) ? "unplaced"
                                                          : "own")
       << " | " << Num(&a, "keyframes") << " | "
       << (a.Has("ate_rmse_m") ? Fmt("%.4f", Num(&a, "ate_rmse_m")) : "-") << " | "
       << (a.Has("agent_frames_ate_rmse_m") ? Fmt("%.4f", Num(&a, "agent_frames_ate_rmse_m")) : "-")
       << " | " << (a.Has("map_mean_error_m") ? Fmt("%.4f", Num(&a, "map_mean_error_m")) : "-")
       << " | " << Num(&a, "lost_frames") << " | " << Num(&a, "restarts") << " |\n";
  }
  if (results.Has("ate_rmse_m")) {
    md << "\nFused trajectory (every keyframe of the primary map: " << JoinNames(primary_agents)
       << "): ATE RMSE **" << Fmt("%.4f", results["ate_rmse_m"].number()) << " m** over "
       << results["fused_keyframes"].number() << " keyframes (max "
       << Fmt("%.4f", results["ate_max_m"].number()) << " m)"
       << (results["ate_aligned_by"].string() == "poses"
               ? ", aligned by whole keyframe poses: too few keyframes, or all within a centimetre "
                 "of a line, to "
                 "align by positions"
               : "")
       << ".\n";
  } else {
    md << "\nNo fused ATE: the primary map has no keyframe matching the ground truth.\n";
  }
  md << "\n![trajectories](plots/trajectories.png)\n\n## Dense map\n\n";
  if (results.Has("recon_mean_m")) {
    md << "| points | mean distance (m) | median (m) | 95% (m) | Hausdorff (m) | completeness (2 "
          "cm) |\n|---|---|---|---|---|---|\n";
    md << "| " << Fmt("%.0f", results["map_points"].number()) << " | "
       << Fmt("%.4f", results["recon_mean_m"].number()) << " | "
       << Fmt("%.4f", results["recon_median_m"].number()) << " | "
       << Fmt("%.4f", results["recon_p95_m"].number()) << " | "
       << Fmt("%.4f", results["recon_hausdorff_m"].number()) << " | "
       << Fmt("%.1f%%", 100 * results["recon_completeness"].number()) << " |\n\n";
    md << "Reference: " << results["reference"].string() << " ("
       << results["reference_points"].number()
       << " points). The map is aligned to it by the fit of the primary map's keyframe poses "
          "(centres and "
          "orientations) to the ground truth.\n";
  } else {
    md << "No dense map or no reference to compare with.\n";
  }
  if (map_plots)
    md << "\n![dense map, top view](plots/map_top.png)\n\n![dense map, "
          "perspective](plots/map_view.png)\n";
  md << "\n## Bandwidth\n\n| agent | ATPS (kB/s) | AKFS (kB) | AKFR (Hz) | keyframes with RGB-D | "
        "bytes |\n|---|---|---|---|---|---|\n";
  for (const Json& a : agents.array()) {
    md << "| " << a.Get("name")->string() << " | " << Fmt("%.1f", Num(&a, "atps_kBps")) << " | "
       << Fmt("%.1f", Num(&a, "akfs_kB")) << " | " << Fmt("%.2f", Num(&a, "akfr_hz")) << " | "
       << Num(&a, "rgbd_keyframes") << " of " << Num(&a, "keyframes") << " | "
       << Fmt("%.0f", Num(&a, "bytes")) << " |\n";
  }
  md << "| mean | " << Fmt("%.1f", Num(&results, "atps_kBps")) << " | "
     << Fmt("%.1f", Num(&results, "akfs_kB")) << " | " << Fmt("%.2f", Num(&results, "akfr_hz"))
     << " | | |\n\n";
  md << "ATPS and AKFR are per second of connection (wall clock of this run); per second of the "
        "dataset's own time "
        "(what a robot moving at that speed would send): "
     << Fmt("%.1f", Num(&results, "atps_dataset_kBps")) << " kB/s and "
     << Fmt("%.2f", Num(&results, "akfr_dataset_hz")) << " keyframes/s per agent.\n\n";
  md << "Bytes per keyframe by kind, against an uncompressed format (4x4 float pose, 5 floats per "
        "keypoint, every "
        "descriptor, id + xyz per map point, full-resolution colour and float depth with every "
        "keyframe):\n\n";
  md << "| kind | sent (B/keyframe) | uncompressed (B/keyframe) | ratio |\n|---|---|---|---|\n";
  for (const auto& [kind, ours, naive] : per_kind) {
    md << "| " << kind << " | " << Fmt("%.0f", ours) << " | " << Fmt("%.0f", naive) << " | "
       << (naive > 0 ? Fmt("%.3f", ours / naive) : "-") << " |\n";
  }
  md << "\n![traffic](plots/traffic.png)\n\n![bytes per kind](plots/bytes_per_kind.png)\n\n## "
        "CPU\n\n";
  md << "| process | CPU (s) | CPU (% of one core) | peak memory (MB) |\n|---|---|---|---|\n";
  for (const ReplayProcess& p : info.processes) {
    md << "| " << p.name << " | " << Fmt("%.1f", p.cpu_seconds) << " | "
       << Fmt("%.0f", p.wall_seconds > 0 ? 100 * p.cpu_seconds / p.wall_seconds : 0.0) << " | "
       << Fmt("%.0f", p.max_rss_mb) << " |\n";
  }
  md << "\n![cpu](plots/cpu.png)\n";
  auto link_section =
      AddLinkFigures(run_dir, LinkRunInfo{info.link, info.link_stats, info.agents}, &results);
  if (link_section.ok()) {
    md << *link_section;
  } else {
    CCMD_LOG(WARNING) << "link figures: " << link_section.status().ToString();
  }
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(run_dir, "report.md"), md.str()));
  CCMD_RETURN_IF_ERROR(WriteJsonFile(results, JoinPath(run_dir, "results.json")));
  return results;
}

Status AppendAblation(const std::string& run_dir, const std::vector<AblationRow>& rows) {
  CCMD_ASSIGN_OR_RETURN(Json results, ReadJsonFile(JoinPath(run_dir, "results.json")));
  CCMD_ASSIGN_OR_RETURN(std::string report, ReadFileToString(JoinPath(run_dir, "report.md")));
  // The reference row: r = 1 with RGB-D for every keyframe, what a system without either
  // saving sends.
  double reference_bytes = 0, reference_points = 0;
  for (const AblationRow& row : rows) {
    if (row.downsample == 1 && !row.selection) {
      reference_bytes = Num(&row.results, "colour_bytes") + Num(&row.results, "depth_bytes");
      reference_points = Num(&row.results, "map_points");
    }
  }
  std::ostringstream md;
  md << "\n## Sampling rate and RGB-D keyframe selection\n\n"
     << "Each row is a full run of the same replay; only the agents' RGB-D settings differ. RGB-D "
        "bytes are "
        "colour and depth over all agents; ratios are to r = 1 with RGB-D for every keyframe.\n\n"
     << "| r | selection | RGB-D keyframes | RGB-D bytes | per keyframe | ratio | map points | "
        "ratio | recon mean (m) | "
        "fused ATE (m) | run |\n|---|---|---|---|---|---|---|---|---|---|---|\n";
  Json list = Json::MakeArray();
  for (const AblationRow& row : rows) {
    const double bytes = Num(&row.results, "colour_bytes") + Num(&row.results, "depth_bytes");
    const double points = Num(&row.results, "map_points");
    Json e;
    e["r"] = 1.0 / row.downsample;
    e["selection"] = row.selection;
    e["run_dir"] = row.run_dir;
    e["rgbd_keyframes"] = Num(&row.results, "rgbd_keyframes");
    e["keyframes"] = Num(&row.results, "keyframes_sent");
    e["rgbd_bytes"] = bytes;
    e["map_points"] = points;
    if (row.results.Has("recon_mean_m")) e["recon_mean_m"] = Num(&row.results, "recon_mean_m");
    if (row.results.Has("ate_rmse_m")) e["ate_rmse_m"] = Num(&row.results, "ate_rmse_m");
    e["maps_after_fusion"] = Num(&row.results, "maps_after_fusion", -1);
    list.Push(e);
    md << "| " << (row.downsample == 1 ? std::string("1") : "1/" + std::to_string(row.downsample))
       << " | " << (row.selection ? "on" : "off") << " | "
       << Fmt("%.0f", e["rgbd_keyframes"].number()) << " of "
       << Fmt("%.0f", e["keyframes"].number()) << " | " << Fmt("%.0f", bytes / 1e3) << " kB | "
       << Fmt("%.2f", bytes / std::max(1.0, e["keyframes"].number()) / 1e3) << " kB | "
       << (reference_bytes > 0 ? Fmt("%.3f", bytes / reference_bytes) : "-") << " | "
       << Fmt("%.0f", points) << " | "
       << (reference_points > 0 ? Fmt("%.3f", points / reference_points) : "-") << " | "
       << (e.Has("recon_mean_m") ? Fmt("%.4f", e["recon_mean_m"].number()) : "-") << " | "
       << (e.Has("ate_rmse_m") ? Fmt("%.4f", e["ate_rmse_m"].number()) : "-") << " | `"
       << row.run_dir << "` |\n";
  }
  md << "\nPer keyframe: RGB-D bytes over all keyframes sent, with or without RGB-D (the paper's "
        "Table V measure).\n";
  results["ablation"] = list;
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(run_dir, "report.md"), report + md.str()));
  return WriteJsonFile(results, JoinPath(run_dir, "results.json"));
}

}  // namespace ccmd
