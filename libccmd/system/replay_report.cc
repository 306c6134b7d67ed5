#include "libccmd/system/replay_report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>

#include "libccmd/codec/depth_downsample.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/dense/label.h"
#include "libccmd/eval/plot.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/system/link_report.h"
#include "libccmd/system/replay_markdown.h"
#include "libccmd/system/replay_plots.h"
#include "libccmd/system/report_format.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "proto/messages.h"

namespace ccmd {

Status ReferenceOptions::Validate() const {
  if (stride < 1) return InvalidArgument("reference stride must be at least 1");
  if (!(max_move_m > 0) || !(max_turn_deg > 0))
    return InvalidArgument("reference frame spacing (move, turn) must be positive");
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
  out->Add("max_move_m", max_move_m);
  out->Add("max_turn_deg", max_turn_deg);
  out->Add("downsample", downsample);
  out->Add("voxel_m", voxel_m);
  out->Add("registration", registration ? "Depth block" : "none");
  out->Add("ground_truth_camera_in_colour_m", T_color_trajectory.translation().norm());
  out->Add("depth_at_own_time", depth_at_own_time);
}

Status ReadReferenceCamera(const std::string& camera_file, ReferenceOptions* options) {
  if (!FileExists(camera_file)) return Status::Ok();
  CCMD_ASSIGN_OR_RETURN(options->registration, LoadDepthToColorCalibration(camera_file));
  CCMD_ASSIGN_OR_RETURN(const Pose T_color_trajectory, LoadTrajectoryCamera(camera_file));
  if (options->registration) options->T_color_trajectory = T_color_trajectory;
  CCMD_ASSIGN_OR_RETURN(const ConfigFile config, ConfigFile::Open(camera_file));
  CCMD_ASSIGN_OR_RETURN(const int lag, config.GetInt("Tracking.depthLagCompensation", 0));
  options->depth_at_own_time = lag != 0;
  return Status::Ok();
}

namespace {

// Whether a frame sees enough that the last reference frame did not: the reference is to cover
// what the recording saw however fast the camera went (a recording at a low frame rate, or
// every n-th frame of one, has views far apart), so frames are taken by the way the camera
// went, and at least every stride-th frame.
bool ViewChanged(const std::optional<Pose>& last_taken, const Pose& T_world_cam,
                 std::size_t frames_since, const ReferenceOptions& options) {
  if (!last_taken || frames_since >= static_cast<std::size_t>(options.stride)) return true;
  const Pose move = last_taken->inverse() * T_world_cam;
  return move.translation().norm() >= options.max_move_m ||
         RotationAngle(move) >= options.max_turn_deg * M_PI / 180.0;
}

}  // namespace

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
  std::optional<Pose> last_taken;
  std::size_t since_taken = 0;
  for (std::size_t i = options.first; i < dataset.size(); ++i) {
    if (!dataset.frame(i).T_world_cam_gt) continue;
    if (!ViewChanged(last_taken, *dataset.frame(i).T_world_cam_gt, ++since_taken, options))
      continue;
    auto loaded = dataset.LoadFrame(i);
    if (!loaded.ok()) {  // as the agents did, the reference does without a damaged frame
      CCMD_LOG(WARNING) << "reference cloud: frame " << i
                        << " left out: " << loaded.status().message();
      continue;
    }
    RgbdFrame frame = std::move(loaded).value();
    // The camera where the depth image was taken, when the agents move depth taken apart from
    // its colour to the colour image's time: the ground truth's pose at the depth's own time.
    std::optional<Pose> T_world_gt = dataset.frame(i).T_world_cam_gt;
    if (options.depth_at_own_time && frame.depth_time_offset != 0) {
      T_world_gt = InterpolateTrajectory(dataset.groundtruth(), dataset.frame(i).depth_timestamp,
                                         TumOptions().groundtruth_max_gap);
      if (!T_world_gt) continue;
    }
    DenseKeyframe kf;
    kf.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(i))};
    kf.T_world_cam = *T_world_gt * options.T_color_trajectory.inverse();
    cv::Mat depth = frame.depth_mm, bgr = frame.bgr;
    if (options.registration) {
      CCMD_ASSIGN_OR_RETURN(depth, RegisterDepth(depth, *options.registration, dataset.camera()));
    }
    if (bgr.size() != depth.size()) cv::resize(bgr, bgr, depth.size(), 0, 0, cv::INTER_AREA);
    if (factor > 1) {
      // The keyframe codec's rule: no mixed depths across edges, and on a surface the depth
      // at the block's centre, where the resized camera's ray passes (a block's top-left
      // pixel lies half a pixel off that ray).
      CCMD_ASSIGN_OR_RETURN(depth, DownsampleDepth(depth, factor));
      cv::resize(bgr, bgr, depth.size(), 0, 0, cv::INTER_AREA);
    }
    kf.depth_mm = depth;
    kf.bgr = bgr;
    kf.camera = dataset.camera().Resized(depth.cols, depth.rows);
    CCMD_RETURN_IF_ERROR(dense->AddKeyframe(kf));
    ++added;
    last_taken = dataset.frame(i).T_world_cam_gt;
    since_taken = 0;
  }
  if (added == 0) return NotFound("no frames with ground truth to build a reference cloud from");
  // With normals the map's error is measured to the reference's local plane: the voxel
  // sampling alone puts a map lying on the true surface 0.4 voxel from the nearest sample.
  CCMD_ASSIGN_OR_RETURN(PointCloud cloud, dense->Extract(DenseSelection::Global()));
  std::string how;
  cloud = AsReferenceSurface(std::move(cloud), &how);
  if (source) {
    *source = "back-projected from " + std::to_string(added) + " ground-truth frames (one per " +
              report::Fmt("%g", options.max_move_m * 100) + " cm or " +
              report::Fmt("%g", options.max_turn_deg) +
              " degrees of the camera's way, at least every " + std::to_string(options.stride) +
              "th, 1/" + std::to_string(factor) + " resolution, " +
              std::to_string(static_cast<int>(options.voxel_m * 1000)) + " mm voxels, " + how + ")";
  }
  return cloud;
}

namespace {

using report::FindAgentTraffic;
using report::Fmt;
using report::Num;

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

// Reconstruction error of the server's map.ply, moved into the ground truth's frame by the
// alignment of the primary map's `keyframes` to it (AlignMap: their whole poses, weighed at
// the distance they see the map from), into `results`; returns each agent's mean error by its
// id (the points' labels: which keyframe, so which agent, each came from), empty without a
// map or a reference.
std::map<std::uint32_t, double> EvaluateMap(const std::string& run_dir, const TumSequence& dataset,
                                            const ReferenceOptions& reference, const Trajectory& gt,
                                            const Trajectory& keyframes, Json* results) {
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
  const double seen_from = MapViewingDistance(*rec, keyframes);
  auto aligned = AlignMap(gt, keyframes, *rec, seen_from);
  if (!aligned.ok()) return by_agent;
  for (auto& p : rec->points) p = (aligned->alignment * p.cast<double>()).cast<float>();
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
  r["recon_viewing_distance_m"] = seen_from;
  // The paper places its maps on the reference by ICP instead: the same map's error after that
  // (how far the keyframes' fit is from the best rigid placement), beside the figure above.
  if (auto icp = AlignByIcp(*ref, *rec); icp.ok()) {
    PointCloud placed = *rec;
    for (auto& p : placed.points) p = (icp->T_reference_map * p.cast<double>()).cast<float>();
    if (auto after = ComputeReconstructionError(*ref, placed); after.ok()) {
      r["recon_mean_after_icp_m"] = after->mean;
      r["recon_icp_turn_deg"] = icp->turn_deg;
      r["recon_icp_shift_m"] = icp->shift_m;
    }
  }
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

// The run's own figures out of server_stats.json: maps, loops, fusions, restarted segments.
Json RunSummary(const ReplayRunInfo& info, const Json& server_stats) {
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
  return results;
}

// What the agents sent, summed over them, and what a format without any packing would have
// needed for the same keyframes.
struct TrafficTotals {
  double atps_sum = 0, akfs_sum = 0, akfr_sum = 0;
  int with_traffic = 0;
  KeyframeSizeBreakdown parts;
  double keyframes = 0, rgbd_keyframes = 0;
  double naive_pose = 0, naive_keypoints = 0, naive_descriptors = 0, naive_points = 0,
         naive_colour = 0, naive_depth = 0;
};

// The agent's traffic as the server counted it (server_stats.json's transport) into `a`.
void AddServerTraffic(const Json& traffic, Json* agent, TrafficTotals* sums) {
  Json& a = *agent;
  TrafficTotals& totals = *sums;
  const Json* messages = traffic.Get("messages");
  const Json* kf = messages ? messages->Get("keyframe") : nullptr;
  a["keyframes"] = Num(kf, "count");
  a["bytes"] = Num(kf, "bytes") + Num(messages ? messages->Get("pose_update") : nullptr, "bytes");
  a["atps_kBps"] = Num(&traffic, "average_traffic_bytes_per_s") / 1e3;
  a["akfs_kB"] = Num(&traffic, "average_keyframe_bytes") / 1e3;
  a["akfr_hz"] = Num(&traffic, "keyframe_rate_hz");
  totals.atps_sum += a["atps_kBps"].number();
  totals.akfs_sum += a["akfs_kB"].number();
  totals.akfr_sum += a["akfr_hz"].number();
  ++totals.with_traffic;
  if (const Json* p = traffic.Get("keyframe_parts_bytes")) {
    auto bytes = [&](const char* kind) { return static_cast<std::size_t>(Num(p, kind)); };
    totals.parts.pose += bytes("pose");
    totals.parts.keypoints += bytes("keypoints");
    totals.parts.descriptors += bytes("descriptors");
    totals.parts.map_points += bytes("map_points");
    totals.parts.colour += bytes("colour");
    totals.parts.depth += bytes("depth");
    totals.parts.other += bytes("other");
  }
}

// The agent's own statistics (agents/NAME_stats.json): frames, losses, what its link sent.
void AddAgentStats(const Json& agent_stats, Json* agent, TrafficTotals* sums) {
  Json& a = *agent;
  TrafficTotals& totals = *sums;
  a["frames"] = Num(&agent_stats, "frames");
  a["lost_frames"] = Num(&agent_stats, "lost_frames");
  a["restarts"] = Num(&agent_stats, "restarts");
  a["fps"] = Num(&agent_stats, "fps");
  if (agent_stats.Has("depth_noise_ratio"))
    a["depth_noise_ratio"] = Num(&agent_stats, "depth_noise_ratio");
  const Json* link = agent_stats.Get("link");
  if (!link) return;
  const double k = Num(link, "keyframes_sent");
  totals.keyframes += k;
  totals.rgbd_keyframes += Num(link, "rgbd_keyframes_sent");
  a["rgbd_keyframes"] = Num(link, "rgbd_keyframes_sent");
  // What a format without any of the packing would need: a 4x4 float pose, 5 floats per
  // keypoint, every descriptor, an id and xyz floats per keypoint's map point, colour at
  // 3 bytes and depth as a float per pixel of the full image for every keyframe.
  const double keypoints = Num(link, "keypoints_extracted");
  totals.naive_pose += 64 * k;
  totals.naive_keypoints += 20 * keypoints;
  totals.naive_descriptors += 32 * keypoints;
  totals.naive_points += 16 * keypoints;
  totals.naive_colour += 3 * Num(link, "full_rgbd_pixels");
  totals.naive_depth += 4 * Num(link, "full_rgbd_pixels");
}

// Everything the report says of agent `i` (1-based).
struct AgentInputs {
  const std::string& run_dir;
  const Json& server_stats;
  const ReplayRunInfo& info;
  const Trajectory& gt;
  const MapMembership& membership;
  const std::map<std::uint32_t, double>& map_error_of_agent;
};

Json EvaluateAgent(int i, const AgentInputs& in, Trajectory* keyframes, TrafficTotals* totals) {
  const std::string name = "agent" + std::to_string(i);
  Json a;
  a["name"] = name;
  if (i - 1 < static_cast<int>(in.info.segments.size())) {
    a["first_frame"] = in.info.segments[i - 1].first;
    a["last_frame"] = in.info.segments[i - 1].last;
  }
  auto t = ReadTumTrajectory(JoinPath(in.run_dir, "trajectory_" + name + ".txt"));
  *keyframes = t.ok() ? *t : Trajectory{};
  a["in_primary_map"] = in.membership.InPrimary(name);
  a["map"] = in.membership.InPrimary(name)  ? "primary"
             : in.membership.Unplaced(name) ? "unplaced"
                                            : "own";
  const Json* agent_ids = in.server_stats.Get("agent_ids");
  if (const Json* id = agent_ids ? agent_ids->Get(name) : nullptr) {
    const auto found = in.map_error_of_agent.find(static_cast<std::uint32_t>(id->number()));
    if (found != in.map_error_of_agent.end()) a["map_mean_error_m"] = found->second;
  }
  if (t.ok()) {
    const auto ate = MapAte(in.gt, *t);
    if (ate) a["ate_rmse_m"] = ate->error.rmse;
  }
  auto frames = ReadTumTrajectory(JoinPath(in.run_dir, "agents/" + name + "_frames.txt"));
  if (frames.ok() && !in.gt.empty()) {
    auto ate = ComputeAte(in.gt, *frames);
    if (ate.ok()) a["agent_frames_ate_rmse_m"] = ate->error.rmse;  // the agent's own odometry
  }
  if (const Json* traffic = FindAgentTraffic(in.server_stats, name))
    AddServerTraffic(*traffic, &a, totals);
  auto agent_stats = ReadJsonFile(JoinPath(in.run_dir, "agents/" + name + "_stats.json"));
  if (agent_stats.ok()) AddAgentStats(*agent_stats, &a, totals);
  for (const ReplayProcess& p : in.info.processes) {
    if (p.name != name) continue;
    a["cpu_seconds"] = p.cpu_seconds;
    a["cpu_percent"] = p.wall_seconds > 0 ? 100 * p.cpu_seconds / p.wall_seconds : 0.0;
    a["max_rss_mb"] = p.max_rss_mb;
  }
  return a;
}

// Mean rates over the agents: per second of connection, and per second of dataset time (each
// agent's bytes and keyframes over its segment's duration).
void AddRates(const TumSequence& dataset, const TrafficTotals& totals, Json* out) {
  Json& results = *out;
  double dataset_bytes_per_s = 0, dataset_keyframes_per_s = 0;
  int with_duration = 0;
  for (const Json& a : results["agents"].array()) {
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
  if (totals.with_traffic) {
    results["atps_kBps"] = totals.atps_sum / totals.with_traffic;
    results["akfs_kB"] = totals.akfs_sum / totals.with_traffic;
    results["akfr_hz"] = totals.akfr_sum / totals.with_traffic;
  }
}

// Bytes per keyframe by kind, sent and unpacked, and how many keyframes carried RGB-D.
void AddBytesPerKind(const TrafficTotals& totals, Json* out) {
  Json& results = *out;
  const double k = std::max(1.0, totals.keyframes);
  const KeyframeSizeBreakdown& parts = totals.parts;
  const std::vector<std::tuple<std::string, double, double>> per_kind = {
      {"pose", parts.pose / k, totals.naive_pose / k},
      {"keypoints", parts.keypoints / k, totals.naive_keypoints / k},
      {"descriptors", parts.descriptors / k, totals.naive_descriptors / k},
      {"map points", parts.map_points / k, totals.naive_points / k},
      {"colour", parts.colour / k, totals.naive_colour / k},
      {"depth", parts.depth / k, totals.naive_depth / k},
      {"other", parts.other / k, 0.0}};
  Json kinds = Json::MakeArray();
  for (const auto& [kind, ours, naive] : per_kind) {
    Json e;
    e["kind"] = kind;
    e["bytes_per_keyframe"] = ours;
    e["uncompressed_bytes_per_keyframe"] = naive;
    kinds.Push(e);
  }
  results["bytes_per_kind"] = kinds;
  results["rgbd_keyframe_fraction"] = totals.rgbd_keyframes / k;
  results["rgbd_keyframes"] = totals.rgbd_keyframes;
  results["keyframes_sent"] = totals.keyframes;
  results["colour_bytes"] = static_cast<double>(parts.colour);
  results["depth_bytes"] = static_cast<double>(parts.depth);
}

// The server process's CPU and memory, and its memory as sampled during the run.
void AddServerProcess(const ReplayRunInfo& info, Json* out) {
  Json& results = *out;
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
}

}  // namespace

StatusOr<Json> EvaluateReplay(const std::string& run_dir, const TumSequence& dataset,
                              const ReplayRunInfo& info, const ReferenceOptions& reference) {
  const std::string plots_dir = JoinPath(run_dir, "plots");
  CCMD_RETURN_IF_ERROR(MakeDirectories(plots_dir));
  // The server writes its results into the run folder.
  CCMD_ASSIGN_OR_RETURN(const Json server_stats,
                        ReadJsonFile(JoinPath(run_dir, "server_stats.json")));
  const Trajectory gt = dataset.GroundTruthAtFrames();
  Json results = RunSummary(info, server_stats);

  // Trajectories: the agents' own odometry, then the primary map's keyframes (every agent's
  // when all fused; otherwise those of the agents in it, named in the results).
  const MapMembership membership = ReadMembership(server_stats, info.agents);
  Json primary_names = Json::MakeArray();
  for (const std::string& n : membership.PrimaryAgents()) primary_names.Push(n);
  results["primary_map_agents"] = primary_names;
  bool all_fused = results["maps_after_fusion"].number() == 1;
  for (int i = 1; i <= info.agents; ++i)
    all_fused = all_fused && !membership.Unplaced("agent" + std::to_string(i));
  results["all_maps_fused"] = all_fused;
  std::optional<AteResult> fused_ate;
  auto read_fused = ReadTumTrajectory(JoinPath(run_dir, "trajectory_fused.txt"));
  if (read_fused.ok()) {
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
      read_fused.ok() ? EvaluateMap(run_dir, dataset, reference, gt, *read_fused, &results)
                      : std::map<std::uint32_t, double>{};

  ReplayPlotInputs plots;
  plots.agent_trajectories.resize(std::max(0, info.agents));
  const AgentInputs agent_inputs{run_dir, server_stats, info, gt, membership, map_error_of_agent};
  TrafficTotals totals;
  Json agents = Json::MakeArray();
  for (int i = 1; i <= info.agents; ++i)
    agents.Push(EvaluateAgent(i, agent_inputs, &plots.agent_trajectories[i - 1], &totals));
  results["agents"] = agents;
  AddRates(dataset, totals, &results);
  AddServerProcess(info, &results);
  AddBytesPerKind(totals, &results);

  plots.server_stats = &server_stats;
  plots.results = &results;
  plots.info = &info;
  plots.ground_truth = gt;
  if (fused_ate) plots.alignment = fused_ate->alignment;
  const bool map_plots = WriteReplayPlots(run_dir, plots_dir, plots);

  std::string md = ReplayMarkdown(results, info, dataset.size(), map_plots);
  auto link_section =
      AddLinkFigures(run_dir, LinkRunInfo{info.link, info.link_stats, info.agents}, &results);
  if (link_section.ok()) {
    md += *link_section;
  } else {
    CCMD_LOG(WARNING) << "link figures: " << link_section.status().ToString();
  }
  CCMD_RETURN_IF_ERROR(WriteFileAtomic(JoinPath(run_dir, "report.md"), md));
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
