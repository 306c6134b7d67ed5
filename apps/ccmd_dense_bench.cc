// ccmd_dense_bench: what the dense map store costs, against a naive rebuild measured in the
// same run, and how accurate a dense map built with ground-truth poses is.
//
//   ccmd_dense_bench [--json OUT] [--quick]
//       Stores of 50 k, 500 k and 5 M stored points filled with rendered keyframes of the
//       synthetic room, a room after another (160x120, i.e. rate 0.25 of 640x480; and 320x240,
//       rate 0.5). Per size: one keyframe pose update (local BA), the window re-filter it leaves
//       for Maintain(), a naive rebuild (every keyframe cloud transformed, everything
//       voxel-filtered), adding a keyframe (back-projection + window filter), an export, and
//       memory per stored point.
//   ccmd_dense_bench recon [--sequence DIR] [--every 10] [--rate 0.5] [--voxels 0.01,...]
//                          [--max-depths 3,...] [--max-incidences 75,...]
//                          [--downsample median|nearest|topleft]
//                          [--out MAP.ply] [--json OUT] [--passes N [--drift-deg D]]
//       Dense map of a synthetic sequence (generated, 600 frames, unless --sequence) from every
//       Nth frame at its ground-truth pose, downsampled by the rate, against surface.ply. With
//       --passes: the keyframes added N times (memory over revisits), and with --drift-deg a
//       loop that drifted by D degrees corrected, against from-scratch builds.

#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <map>
#include <numeric>
#include <opencv2/imgproc.hpp>

#include "apps/dense_bench_revisits.h"
#include "libccmd/codec/depth_downsample.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/dense/label.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/synth/renderer.h"
#include "libccmd/synth/scene.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/random.h"
#include "libccmd/util/string_util.h"
#include "libccmd/util/timer.h"

namespace {

using ccmd::AgentId;
using ccmd::GlobalKeyframeId;
using ccmd::KeyframeId;
using ccmd::Pose;

int Fail(const ccmd::Status& status) {
  std::fprintf(stderr, "ccmd_dense_bench: %s\n", status.ToString().c_str());
  return 1;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// CPU time of the calling thread: unlike wall time, not inflated when other processes share
// the cores (the development machine has two, shared by everyone).
double ThreadCpuMillis() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

// The one-minute load average, recorded with each row.
double LoadAverage() {
  double load = -1;
  if (std::FILE* f = std::fopen("/proc/loadavg", "r")) {
    if (std::fscanf(f, "%lf", &load) != 1) load = -1;
    std::fclose(f);
  }
  return load;
}

double Max(const std::vector<double>& v) {
  return v.empty() ? 0 : *std::max_element(v.begin(), v.end());
}

// ---- store costs -----------------------------------------------------------------------------

// Keyframes along the synthetic camera path, one every 10 frames (48 per 16 s loop); each
// further loop shrinks and raises the ellipse a little and maps another room of a building of
// identical rooms (the same room, placed 12 m further along x), so that the mapped space, and
// with it the points the store keeps, grows with the keyframes.
class KeyframeSource {
 public:
  KeyframeSource(int width, int height)
      : scene_(ccmd::SyntheticScene::MakeRoom({})), camera_(ccmd::SyntheticCamera(width, height)) {}

  const ccmd::PinholeCamera& camera() const { return camera_; }

  Pose PoseOf(int i) {
    const int loop = i / 48;
    auto it = loops_.find(loop);
    if (it == loops_.end()) {
      ccmd::LoopPathOptions o;
      o.radius_x -= 0.12 * (loop % 5);
      o.radius_y -= 0.1 * (loop % 5);
      o.height += 0.07 * (loop % 3 - 1);
      it = loops_.emplace(loop, ccmd::MakeLoopPath(480, 30.0, o)).first;
    }
    return it->second[(i % 48) * 10].T_world_cam;
  }

  // Where keyframe i is in the map: its room's place in the building.
  Pose MapPoseOf(int i) {
    Pose T = PoseOf(i);
    T.translation().x() += 12.0 * (i / 48);
    return T;
  }

  ccmd::RenderedFrame Render(int i) {
    ccmd::RenderOptions options;
    options.seed = ccmd::MixSeed(7, i);
    options.threads = 2;
    return ccmd::RenderFrame(scene_, camera_, PoseOf(i), options);
  }

 private:
  ccmd::SyntheticScene scene_;
  ccmd::PinholeCamera camera_;
  std::map<int, ccmd::Trajectory> loops_;
};

struct StoredKeyframe {
  GlobalKeyframeId id;
  Pose pose;
  ccmd::CameraCloud cloud;
};

// The reference: transform every keyframe cloud and voxel-filter everything.
double NaiveRebuildMs(const std::vector<StoredKeyframe>& keyframes, double voxel,
                      std::size_t* points) {
  ccmd::Stopwatch watch;
  std::size_t total = 0;
  for (const auto& k : keyframes) total += k.cloud.size();
  ccmd::PointCloud all;
  all.points.reserve(total);
  all.colors.reserve(total);
  all.labels.reserve(total);
  for (const auto& k : keyframes) {
    const Eigen::Matrix3f r = k.pose.linear().cast<float>();
    const Eigen::Vector3f t = k.pose.translation().cast<float>();
    const std::uint32_t label = *ccmd::EncodeLabel(k.id);
    for (std::size_t i = 0; i < k.cloud.size(); ++i) {
      all.points.push_back(r * k.cloud.points[i] + t);
      all.colors.push_back(k.cloud.colors[i]);
      all.labels.push_back(label);
    }
  }
  ccmd::VoxelFilterLargestLabel(&all, voxel);
  *points = all.size();
  return watch.ElapsedMillis();
}

Pose Nudged(const Pose& pose, std::uint64_t seed) {
  ccmd::Rng rng(seed);
  Pose delta = Pose::Identity();
  delta.translation() =
      Eigen::Vector3d(rng.Uniform(-0.01, 0.01), rng.Uniform(-0.01, 0.01), rng.Uniform(-0.01, 0.01));
  delta.linear() = ccmd::RotationFromAngleAxis(Eigen::Vector3d(
      rng.Uniform(-0.01, 0.01), rng.Uniform(-0.01, 0.01), rng.Uniform(-0.01, 0.01)));
  return pose * delta;
}

struct StoreRow {
  int width = 0, height = 0;
  ccmd::DenseMapStats stats;
  std::size_t added_points = 0;  // back-projected, before the store's filtering
  std::vector<double> update_ms, update_cpu_ms, update_cold_ms, update_cold_cpu_ms, refilter_ms,
      add_ms, add_cpu_ms;
  double load = 0;
  double rebuild_ms = 0;
  std::size_t rebuild_points = 0;
  double extract_ms = 0, export_ms = 0;
};

// One store of a given size and what the bench knows about it: its keyframes' clouds and
// current poses (for the naive rebuild) and the measurements.
struct Bench {
  std::unique_ptr<ccmd::DenseMap> store;
  std::vector<StoredKeyframe> keyframes;
  std::size_t target = 0;
  StoreRow row;
};

// Local BA: one keyframe's pose, then the window re-filter Maintain() runs when idle. Even
// trials move one of the 8 newest keyframes (what local BA moves: recently added, so in cache
// whatever the store's size); odd trials move a random keyframe after evicting the caches, so
// that small and large stores are compared in the same (cold) state.
ccmd::Status UpdateTrial(Bench* b, int t, std::vector<char>* evict) {
  const bool cold = t % 2 == 1;
  const std::size_t n = b->keyframes.size();
  const std::size_t index =
      cold ? (static_cast<std::size_t>(t) * 7919u) % n
           : n - 1 - (static_cast<std::size_t>(t / 2) % std::min<std::size_t>(n, 8));
  StoredKeyframe& k = b->keyframes[index];
  k.pose = Nudged(k.pose, 1000 + t);
  if (cold) std::fill(evict->begin(), evict->end(), static_cast<char>(t));
  ccmd::Stopwatch watch;
  const double cpu = ThreadCpuMillis();
  CCMD_RETURN_IF_ERROR(b->store->UpdateKeyframePose(k.id, k.pose));
  (cold ? b->row.update_cold_ms : b->row.update_ms).push_back(watch.ElapsedMillis());
  (cold ? b->row.update_cold_cpu_ms : b->row.update_cpu_ms).push_back(ThreadCpuMillis() - cpu);
  watch.Restart();
  b->store->Maintain();
  b->row.refilter_ms.push_back(watch.ElapsedMillis());
  return ccmd::Status::Ok();
}

// Adds the agent's next keyframe from its images, then removes it again (untimed) so that
// the store keeps its size.
ccmd::Status AddTrial(Bench* b, const ccmd::DenseKeyframe& keyframe) {
  ccmd::Stopwatch watch;
  const double cpu = ThreadCpuMillis();
  CCMD_RETURN_IF_ERROR(b->store->AddKeyframe(keyframe));
  b->row.add_ms.push_back(watch.ElapsedMillis());
  b->row.add_cpu_ms.push_back(ThreadCpuMillis() - cpu);
  return b->store->RemoveKeyframe(keyframe.id);
}

ccmd::Status MeasureReadsAndRebuild(Bench* b) {
  std::vector<double> rebuilds;
  for (int r = 0; r < 3; ++r) {
    rebuilds.push_back(
        NaiveRebuildMs(b->keyframes, b->store->options().voxel_size_m, &b->row.rebuild_points));
  }
  b->row.rebuild_ms = Median(rebuilds);
  ccmd::Stopwatch watch;
  CCMD_ASSIGN_OR_RETURN(
      const ccmd::PointCloud kept,
      b->store->Extract(ccmd::DenseSelection::Global(), ccmd::DenseFilter::kWindow));
  b->row.extract_ms = watch.ElapsedMillis();
  const std::string path =
      (std::filesystem::temp_directory_path() / "ccmd_dense_bench.ply").string();
  watch.Restart();
  CCMD_RETURN_IF_ERROR(b->store->ExportPly(path, ccmd::DenseSelection::Global()));
  b->row.export_ms = watch.ElapsedMillis();
  std::filesystem::remove(path);
  b->row.stats = b->store->Stats();
  b->row.load = LoadAverage();
  return ccmd::Status::Ok();
}

// Fills one store per target size with the same keyframe sequence, then measures them with
// their trials interleaved, so that other load on the machine affects every size alike.
ccmd::Status RunStoreSizes(int width, int height, const std::vector<std::size_t>& targets,
                           std::vector<StoreRow>* rows) {
  std::fprintf(stderr, "keyframes %dx%d: rendering and filling...\n", width, height);
  KeyframeSource source(width, height);
  std::vector<Bench> benches(targets.size());
  for (std::size_t i = 0; i < targets.size(); ++i) {
    CCMD_ASSIGN_OR_RETURN(benches[i].store, ccmd::DenseMap::Create({}));
    benches[i].target = targets[i];
    benches[i].row.width = width;
    benches[i].row.height = height;
  }
  const ccmd::BackProjectionOptions projection = benches[0].store->options().projection;
  // Each store is filled until it stores its target number of points.
  int next = 0;
  std::vector<char> full(benches.size(), 0);
  while (std::count(full.begin(), full.end(), 0) > 0) {
    const ccmd::RenderedFrame frame = source.Render(next);
    StoredKeyframe k;
    k.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(next))};
    k.pose = source.MapPoseOf(next);
    CCMD_ASSIGN_OR_RETURN(
        k.cloud, ccmd::BackProjectKeyframe(frame.depth_mm, frame.bgr, source.camera(), projection));
    for (std::size_t i = 0; i < benches.size(); ++i) {
      Bench& b = benches[i];
      if (full[i]) continue;
      CCMD_RETURN_IF_ERROR(b.store->AddKeyframeCloud(k.id, k.pose, k.cloud));
      b.row.added_points += k.cloud.size();
      b.keyframes.push_back(k);
      full[i] = b.store->Stats().points >= b.target;
    }
    ++next;
  }
  std::fprintf(stderr, "  measuring...\n");
  std::vector<char> evict(64 << 20);
  const int trials = 100, probes = 25;
  for (int t = 0; t < trials; ++t) {
    for (Bench& b : benches) CCMD_RETURN_IF_ERROR(UpdateTrial(&b, t, &evict));
  }
  for (int p = 0; p < probes; ++p) {
    // Each store gets the keyframe that follows its own last one.
    for (Bench& b : benches) {
      const int index = static_cast<int>(b.keyframes.size()) + p;
      const ccmd::RenderedFrame frame = source.Render(index);
      ccmd::DenseKeyframe k;
      k.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(index))};
      k.T_world_cam = source.MapPoseOf(index);
      k.depth_mm = frame.depth_mm;
      k.bgr = frame.bgr;
      k.camera = source.camera();
      CCMD_RETURN_IF_ERROR(AddTrial(&b, k));
    }
  }
  for (Bench& b : benches) {
    CCMD_RETURN_IF_ERROR(MeasureReadsAndRebuild(&b));
    std::fprintf(stderr, "  %zu points: update %.3f ms, rebuild %.1f ms\n", b.row.stats.points,
                 Median(b.row.update_ms), b.row.rebuild_ms);
    rows->push_back(std::move(b.row));
  }
  return ccmd::Status::Ok();
}

int RunStoreBench(const std::string& json_path, bool quick) {
  std::vector<StoreRow> rows;
  const std::vector<std::size_t> sizes = quick
                                             ? std::vector<std::size_t>{50'000, 500'000}
                                             : std::vector<std::size_t>{50'000, 500'000, 5'000'000};
  ccmd::Status s = RunStoreSizes(160, 120, sizes, &rows);
  if (!s.ok()) return Fail(s);
  s = RunStoreSizes(
      320, 240,
      quick ? std::vector<std::size_t>{500'000} : std::vector<std::size_t>{500'000, 5'000'000},
      &rows);
  if (!s.ok()) return Fail(s);

  std::printf(
      "| keyframe | points stored | points added | kept | keyframes (compacted) | update ms (cpu) "
      "| "
      "update cold ms (cpu) | rebuild ms | rebuild / update | refilter ms | add keyframe ms (cpu) "
      "| extract ms | "
      "export ms | bytes/stored point | load |\n"
      "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  ccmd::Json json = ccmd::Json::MakeArray();
  for (const StoreRow& r : rows) {
    const double update = Median(r.update_ms);
    const double bytes_per_point = static_cast<double>(r.stats.memory_bytes) / r.stats.points;
    std::printf(
        "| %dx%d | %zu | %zu | %zu | %zu (%zu) | %.3f (%.3f) | %.3f (%.3f) | %.1f | %.0f | %.2f | "
        "%.2f (%.2f) | "
        "%.1f | %.1f | %.1f | %.1f |\n",
        r.width, r.height, r.stats.points, r.added_points, r.stats.kept_points, r.stats.keyframes,
        r.stats.compact_keyframes, update, Median(r.update_cpu_ms), Median(r.update_cold_ms),
        Median(r.update_cold_cpu_ms), r.rebuild_ms, r.rebuild_ms / update, Median(r.refilter_ms),
        Median(r.add_ms), Median(r.add_cpu_ms), r.extract_ms, r.export_ms, bytes_per_point, r.load);
    ccmd::Json j;
    j["keyframe_width"] = r.width;
    j["keyframe_height"] = r.height;
    j["points"] = r.stats.points;
    j["added_points"] = r.added_points;
    j["kept_points"] = r.stats.kept_points;
    j["keyframes"] = r.stats.keyframes;
    j["compact_keyframes"] = r.stats.compact_keyframes;
    j["compact_points"] = r.stats.compact_points;
    j["held_bytes"] = r.stats.held_bytes;
    j["points_per_keyframe"] = static_cast<double>(r.stats.points) / r.stats.keyframes;
    j["update_ms"] = update;
    j["update_ms_max"] = Max(r.update_ms);
    j["update_cpu_ms"] = Median(r.update_cpu_ms);
    j["update_cold_ms"] = Median(r.update_cold_ms);
    j["update_cold_cpu_ms"] = Median(r.update_cold_cpu_ms);
    j["refilter_ms"] = Median(r.refilter_ms);
    j["rebuild_ms"] = r.rebuild_ms;
    j["rebuild_points"] = r.rebuild_points;
    j["rebuild_over_update"] = r.rebuild_ms / update;
    j["add_keyframe_ms"] = Median(r.add_ms);
    j["add_keyframe_ms_max"] = Max(r.add_ms);
    j["add_keyframe_cpu_ms"] = Median(r.add_cpu_ms);
    j["extract_ms"] = r.extract_ms;
    j["export_ms"] = r.export_ms;
    j["bytes_per_point"] = bytes_per_point;
    j["memory_mb"] = r.stats.memory_bytes / 1e6;
    j["load_average"] = r.load;
    json.Push(std::move(j));
  }
  if (!json_path.empty()) {
    const ccmd::Status w = ccmd::WriteJsonFile(json, json_path);
    if (!w.ok()) return Fail(w);
  }
  return 0;
}

// ---- reconstruction error ----------------------------------------------------------------------

// The keyframe codec's downsampling rules, by their names on the command line.
ccmd::DownsampleMethod DownsampleMethodNamed(const std::string& name) {
  if (name == "nearest") return ccmd::DownsampleMethod::kNearestValid;
  if (name == "topleft") return ccmd::DownsampleMethod::kTopLeft;
  return ccmd::DownsampleMethod::kMedianValid;
}

struct RemoveOnExit {
  std::filesystem::path path;
  ~RemoveOnExit() {
    std::error_code ignored;
    if (!path.empty()) std::filesystem::remove_all(path, ignored);
  }
};

struct ReconConfig {
  std::string sequence;
  int every = 10;
  double rate = 0.5;
  std::vector<double> voxels{0.01};
  std::vector<double> max_depths{3.0};
  std::vector<double> incidences{75.0};
  std::string downsample = "median";
  std::string out_ply;
  std::string json_path;
  int passes = 0;        // > 0: revisits instead of the voxel table
  double drift_deg = 0;  // with passes: also a loop that drifted this much, then corrected
};

int RunRecon(const ReconConfig& config) {
  const int factor = ccmd::DownsampleFactorForRate(config.rate);
  if (factor == 0) return Fail(ccmd::InvalidArgument("--rate must be 1, 0.5 or 0.25"));
  std::string folder = config.sequence;
  RemoveOnExit generated;
  if (folder.empty()) {
    generated.path =
        std::filesystem::temp_directory_path() / ("ccmd_dense_recon_" + std::to_string(::getpid()));
    std::fprintf(stderr, "generating the 600-frame synthetic sequence in %s...\n",
                 generated.path.c_str());
    ccmd::SyntheticSequenceOptions options;  // the defaults of ccmd_synth: 640x480, noise on
    auto summary = ccmd::WriteSyntheticSequence(generated.path.string(), options);
    if (!summary.ok()) return Fail(summary.status());
    folder = generated.path.string();
  }
  auto sequence = ccmd::TumSequence::Open(folder, std::nullopt);
  if (!sequence.ok()) return Fail(sequence.status());
  auto surface = ccmd::ReadPly(ccmd::JoinPath(folder, "surface.ply"));
  if (!surface.ok()) return Fail(surface.status());
  const ccmd::PinholeCamera camera = sequence->camera().Scaled(config.rate);

  std::vector<ccmd::DenseKeyframe> keyframes;
  for (std::size_t i = 0; i < sequence->size(); i += config.every) {
    auto frame = sequence->LoadFrame(i);
    if (!frame.ok()) return Fail(frame.status());
    if (!sequence->frame(i).T_world_cam_gt) continue;
    ccmd::DenseKeyframe k;
    k.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(keyframes.size()))};
    k.T_world_cam = *sequence->frame(i).T_world_cam_gt;
    auto depth =
        ccmd::DownsampleDepth(frame->depth_mm, factor, DownsampleMethodNamed(config.downsample));
    if (!depth.ok()) return Fail(depth.status());
    k.depth_mm = *std::move(depth);
    cv::resize(frame->bgr, k.bgr, k.depth_mm.size(), 0, 0, cv::INTER_AREA);
    k.camera = camera;
    keyframes.push_back(std::move(k));
  }

  if (config.passes > 0) {
    auto revisits = ccmd::dense_bench::RunRevisits(keyframes, *surface, config.voxels.front(),
                                                   config.passes, config.drift_deg);
    if (!revisits.ok()) return Fail(revisits.status());
    if (!config.json_path.empty()) {
      const ccmd::Status s = ccmd::WriteJsonFile(*revisits, config.json_path);
      if (!s.ok()) return Fail(s);
    }
    return 0;
  }
  ccmd::Json json = ccmd::Json::MakeArray();
  std::printf(
      "| voxel m | max depth m | max incidence deg | keyframes | points | mean mm | median mm | "
      "p95 mm | "
      "completeness 2 cm | add keyframe ms |\n|---|---|---|---|---|---|---|---|---|---|\n");
  for (const double voxel : config.voxels) {
    for (const double max_depth : config.max_depths) {
      for (const double incidence : config.incidences) {
        ccmd::DenseMapOptions options;
        options.voxel_size_m = voxel;
        options.projection.max_depth_m = max_depth;
        options.projection.max_incidence_deg = incidence;
        auto store = ccmd::DenseMap::Create(options);
        if (!store.ok()) return Fail(store.status());
        std::vector<double> add_ms;
        for (const auto& k : keyframes) {
          ccmd::Stopwatch watch;
          const ccmd::Status s = (*store)->AddKeyframe(k);
          add_ms.push_back(watch.ElapsedMillis());
          if (!s.ok()) return Fail(s);
        }
        auto cloud = (*store)->Extract(ccmd::DenseSelection::Global());
        if (!cloud.ok()) return Fail(cloud.status());
        auto error = ccmd::ComputeReconstructionError(*surface, *cloud);
        if (!error.ok()) return Fail(error.status());
        const double mean_add = std::accumulate(add_ms.begin(), add_ms.end(), 0.0) / add_ms.size();
        std::printf("| %.3f | %.1f | %.0f | %zu | %zu | %.2f | %.2f | %.2f | %.3f | %.2f |\n",
                    voxel, max_depth, incidence, keyframes.size(), cloud->size(), error->mean * 1e3,
                    error->median * 1e3, error->p95 * 1e3, error->completeness, mean_add);
        std::fflush(stdout);
        ccmd::Json j;
        j["voxel_size_m"] = voxel;
        j["max_depth_m"] = max_depth;
        j["max_incidence_deg"] = incidence;
        j["rate"] = config.rate;
        j["every"] = config.every;
        j["downsample"] = config.downsample;
        j["keyframes"] = keyframes.size();
        j["points"] = cloud->size();
        j["mean_m"] = error->mean;
        j["median_m"] = error->median;
        j["p95_m"] = error->p95;
        j["rmse_m"] = error->rmse;
        j["completeness"] = error->completeness;
        j["add_keyframe_ms_mean"] = mean_add;
        json.Push(std::move(j));
        if (!config.out_ply.empty()) {
          const ccmd::Status s = ccmd::WritePly(*cloud, config.out_ply);
          if (!s.ok()) return Fail(s);
        }
      }
    }
  }
  if (!config.json_path.empty()) {
    const ccmd::Status s = ccmd::WriteJsonFile(json, config.json_path);
    if (!s.ok()) return Fail(s);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Dense map store costs against a naive rebuild, and dense map accuracy"};
  std::string json_path;
  bool quick = false;
  app.add_option("--json", json_path, "Write the rows as a JSON list");
  app.add_flag("--quick", quick, "Skip the 5 M-point stores");
  CLI::App* recon = app.add_subcommand("recon", "Reconstruction error with ground-truth poses");
  ReconConfig config;
  recon->add_option("--sequence", config.sequence,
                    "TUM-layout folder with surface.ply (default: generate)");
  recon->add_option("--every", config.every, "Keyframe every N frames")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  recon->add_option("--rate", config.rate, "Sampling rate (1, 0.5, 0.25)")->capture_default_str();
  recon->add_option("--voxels", config.voxels, "Voxel sizes in metres")->delimiter(',');
  recon->add_option("--max-depths", config.max_depths, "Maximum depths in metres")->delimiter(',');
  recon
      ->add_option("--max-incidences", config.incidences,
                   "Maximum incidence angles in degrees (90: off)")
      ->delimiter(',');
  recon->add_option("--downsample", config.downsample, "median | nearest | topleft")
      ->check(CLI::IsMember({"median", "nearest", "topleft"}))
      ->capture_default_str();
  recon->add_option("--out", config.out_ply, "Write the (last) dense map as PLY");
  recon
      ->add_option(
          "--passes", config.passes,
          "Revisits: the keyframes added this many times, compacted and not (first voxel size)")
      ->check(CLI::Range(1, 100));
  recon
      ->add_option("--drift-deg", config.drift_deg,
                   "With --passes: also a loop drifted by this many degrees, then corrected")
      ->check(CLI::Range(0.0, 90.0));
  recon->add_option("--json", config.json_path, "Write the rows as a JSON list");
  CLI11_PARSE(app, argc, argv);
  if (recon->parsed()) return RunRecon(config);
  return RunStoreBench(json_path, quick);
}
