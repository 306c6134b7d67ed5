#include "libccmd/system/replay_plots.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <opencv2/imgproc.hpp>

#include "libccmd/eval/map_picture.h"
#include "libccmd/eval/plot.h"
#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/ply.h"
#include "libccmd/system/report_format.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

using report::FindAgentTraffic;
using report::Num;
using report::Str;

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

void WriteTrajectoryPlot(const ReplayPlotInputs& in, const std::string& plots_dir) {
  const auto P = ViewPlane(in.ground_truth);
  std::vector<PlotSeries> series = {
      Projected(in.ground_truth, P, "ground truth", cv::Scalar(160, 160, 160), 4)};
  for (std::size_t i = 0; i < in.agent_trajectories.size(); ++i) {
    const Trajectory aligned = in.alignment
                                   ? TransformTrajectory(in.agent_trajectories[i], *in.alignment)
                                   : in.agent_trajectories[i];
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

void WriteTrafficPlot(const Json& server_stats, int agents, const std::string& plots_dir) {
  std::vector<PlotSeries> series;
  for (int i = 1; i <= agents; ++i) {
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

void WriteBytesPerKindPlot(const Json& results, const std::string& plots_dir) {
  std::vector<BarGroup> groups;
  if (const Json* kinds = results.Get("bytes_per_kind")) {
    for (const Json& e : kinds->array()) {
      const std::string kind = Str(&e, "kind");
      if (kind == "other") continue;
      groups.push_back(
          {kind, {Num(&e, "bytes_per_keyframe"), Num(&e, "uncompressed_bytes_per_keyframe")}});
    }
  }
  PlotOptions o;
  o.title = "Bytes per keyframe by kind (log scale)";
  o.y_label = "log10(bytes)";
  WritePng(PlotBars(groups, {"sent", "uncompressed"}, {SeriesColor(0), SeriesColor(6)}, o,
                    /*log_scale=*/true),
           JoinPath(plots_dir, "bytes_per_kind.png"))
      .IgnoreError();
}

void WriteCpuPlot(const ReplayRunInfo& info, const std::string& plots_dir) {
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

void WriteMemoryPlot(const ReplayRunInfo& info, const std::string& plots_dir) {
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

}  // namespace

bool WriteReplayPlots(const std::string& run_dir, const std::string& plots_dir,
                      const ReplayPlotInputs& in) {
  const bool map_plots = WriteMapPlots(run_dir, plots_dir, *in.server_stats, in.info->agents);
  if (!in.ground_truth.empty()) WriteTrajectoryPlot(in, plots_dir);
  WriteTrafficPlot(*in.server_stats, in.info->agents, plots_dir);
  WriteBytesPerKindPlot(*in.results, plots_dir);
  WriteCpuPlot(*in.info, plots_dir);
  if (!in.info->server_memory.empty()) WriteMemoryPlot(*in.info, plots_dir);
  return map_plots;
}

}  // namespace ccmd
