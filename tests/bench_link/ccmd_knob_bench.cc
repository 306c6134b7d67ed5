// ccmd_knob_bench: what each RGB-D knob of the bandwidth budget saves and what it costs the
// dense map, free of tracking noise. Keyframes are every k-th frame of a dataset at its
// ground-truth poses; the RGB-D of every m-th keyframe (the selection's share, from replays)
// is coded with the setting, decoded, and fused into a dense map as the server does; the map
// is compared with the reference cloud the replay report uses. One row per setting: RGB-D
// bytes per keyframe, map points, mean error, completeness, colour PSNR, and the cost per kB
// saved against the agents' defaults. The budget's ladder (DefaultBudgetLadder) gives way in
// the order of these costs (docs/benchmarks/link.md).
//
//   ccmd_knob_bench --dataset ../shared/datasets/7scenes_redkitchen_0000_0599 [--json out.json]

#include <CLI/CLI.hpp>
#include <cmath>
#include <cstdio>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/codec/colour_codec.h"
#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/io/config.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/source_factory.h"
#include "libccmd/system/replay_report.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"

namespace {

using namespace ccmd;

struct Setting {
  std::string name;
  int rgbd_every = 4;  // every m-th keyframe carries RGB-D (the selection's share)
  RgbdEncodeOptions encode;
};

struct Row {
  Setting setting;
  double rgbd_bytes_per_keyframe = 0, psnr_db = 0;
  std::size_t map_points = 0;
  ReconstructionError error;
};

int Fail(const std::string& what) {
  std::fprintf(stderr, "ccmd_knob_bench: %s\n", what.c_str());
  return 1;
}

// The frames the bench uses, loaded once: depth registered as the agents register it.
struct Keyframe {
  Pose T_world_cam;
  cv::Mat bgr, depth_mm;
};

StatusOr<Row> Measure(const Setting& setting, const std::vector<Keyframe>& keyframes,
                      const PinholeCamera& camera, const PointCloud& reference) {
  CCMD_ASSIGN_OR_RETURN(auto dense, DenseMap::Create(DenseMapOptions{}));
  Row row;
  row.setting = setting;
  double bytes = 0, psnr = 0;
  int coded = 0;
  for (std::size_t i = 0; i < keyframes.size(); i += setting.rgbd_every) {
    const Keyframe& k = keyframes[i];
    RgbdFrame frame;
    frame.bgr = k.bgr;
    frame.depth_mm = k.depth_mm;
    CCMD_ASSIGN_OR_RETURN(const RgbdPayload payload, EncodeRgbdPayload(frame, setting.encode));
    bytes += payload.colour_jpeg.size() + payload.depth.size();
    CCMD_ASSIGN_OR_RETURN(const DecodedRgbd decoded, DecodeRgbdPayload(payload));
    CCMD_ASSIGN_OR_RETURN(const cv::Mat prepared,
                          PrepareColour(k.bgr, k.depth_mm.size(), setting.encode.downsample));
    psnr += cv::PSNR(decoded.bgr, prepared);
    DenseKeyframe kf;
    kf.id = {AgentId(1), KeyframeId(static_cast<std::uint32_t>(i))};
    kf.T_world_cam = k.T_world_cam;
    kf.depth_mm = decoded.depth_mm;
    kf.bgr = decoded.bgr;
    kf.camera = camera.Resized(decoded.depth_mm.cols, decoded.depth_mm.rows);
    CCMD_RETURN_IF_ERROR(dense->AddKeyframe(kf));
    ++coded;
  }
  CCMD_ASSIGN_OR_RETURN(const PointCloud map, dense->Extract(DenseSelection::Global()));
  CCMD_ASSIGN_OR_RETURN(row.error, ComputeReconstructionError(reference, map));
  row.map_points = map.size();
  row.rgbd_bytes_per_keyframe = bytes / keyframes.size();
  row.psnr_db = coded ? psnr / coded : 0.0;
  return row;
}

std::vector<Setting> Settings(int rgbd_every) {
  const RgbdEncodeOptions base;
  auto with = [&](std::string name, int every, int downsample, int quality, int bound) {
    Setting s{std::move(name), every, base};
    s.encode.downsample = downsample;
    s.encode.jpeg_quality = quality;
    s.encode.bound_e4 = bound;
    return s;
  };
  // The selection's share of RGB-D keyframes per S_min scale, from the 7-Scenes replays of
  // `ccmd_replay --knob-costs` (docs/benchmarks/link.md): 25 % at the default, 15 % at x0.7,
  // 12 % at x0.5, 57 % at x1.5.
  const int m = rgbd_every;
  return {with("agent defaults", m, 2, 75, 50),
          with("JPEG quality 50", m, 2, 50, 50),
          with("JPEG quality 35", m, 2, 35, 50),
          with("depth bound 1 %", m, 2, 75, 100),
          with("depth bound 2 %", m, 2, 75, 200),
          with("r = 1/4", m, 4, 75, 50),
          with("S_min x0.7 (1 in 7)", m * 7 / 4, 2, 75, 50),
          with("S_min x0.5 (1 in 8)", m * 2, 2, 75, 50),
          with("JPEG 90, depth bound 0.25 %", m, 2, 90, 25),
          with("r = 1", m, 1, 75, 50),
          with("S_min x1.5 (1 in 2)", std::max(1, m / 2), 2, 75, 50),
          with("every keyframe", 1, 2, 75, 50)};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "What each RGB-D knob of the bandwidth budget costs the dense map, at ground-truth poses"};
  std::string dataset, config, json_path;
  int keyframe_every = 6, rgbd_every = 4, max_keyframes = 0;
  app.add_option("--dataset", dataset, "TUM-layout folder with ground truth")->required();
  app.add_option("--config", config,
                 "Camera config (default: the dataset's camera.yaml or a guess)");
  app.add_option("--keyframe-every", keyframe_every,
                 "A keyframe every k frames (replays: about 5 to 6)")
      ->capture_default_str();
  app.add_option("--rgbd-every", rgbd_every,
                 "The default selection's share: every m-th keyframe carries RGB-D")
      ->capture_default_str();
  app.add_option("--max-keyframes", max_keyframes, "Use at most this many keyframes (0: all)");
  app.add_option("--json", json_path, "Write the rows as JSON");
  CLI11_PARSE(app, argc, argv);

  SourceOptions source_options;
  source_options.camera_config = config;
  source_options.configs_dir = CCMD_CONFIG_DIR;
  config = DatasetConfigPath(dataset, source_options);
  std::optional<PinholeCamera> camera;
  if (!config.empty()) {
    auto loaded = LoadCameraConfig(config);
    if (!loaded.ok()) return Fail(loaded.status().ToString());
    camera = *loaded;
  }
  auto sequence = TumSequence::Open(dataset, camera);
  if (!sequence.ok()) return Fail(sequence.status().ToString());
  ReferenceOptions reference_options;
  if (const Status s = ReadReferenceCamera(config, &reference_options); !s.ok())
    return Fail(s.ToString());
  std::string reference_source;
  auto reference = LoadOrBuildReference(*sequence, reference_options, &reference_source);
  if (!reference.ok()) return Fail(reference.status().ToString());

  std::vector<Keyframe> keyframes;
  for (std::size_t i = 0; i < sequence->size(); i += std::max(1, keyframe_every)) {
    if (!sequence->frame(i).T_world_cam_gt) continue;
    auto frame = sequence->LoadFrame(i);
    if (!frame.ok()) return Fail(frame.status().ToString());
    cv::Mat depth = frame->depth_mm;
    if (reference_options.registration) {
      auto registered = RegisterDepth(depth, *reference_options.registration, sequence->camera());
      if (!registered.ok()) return Fail(registered.status().ToString());
      depth = *registered;
    }
    keyframes.push_back({*sequence->frame(i).T_world_cam_gt, frame->bgr, depth});
    if (max_keyframes > 0 && static_cast<int>(keyframes.size()) >= max_keyframes) break;
  }
  if (keyframes.empty()) return Fail("no frames with ground truth");
  std::printf("%s: %zu keyframes (every %d frames), RGB-D on every %d; reference %s\n\n",
              dataset.c_str(), keyframes.size(), keyframe_every, rgbd_every,
              reference_source.c_str());
  std::printf(
      "| setting | RGB-D kB/keyframe | saved kB | map points | mean mm | completeness | colour "
      "PSNR dB | "
      "completeness pp per kB | mean mm per kB | PSNR dB per kB "
      "|\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
  std::vector<Row> rows;
  Json list = Json::MakeArray();
  for (const Setting& s : Settings(rgbd_every)) {
    auto row = Measure(s, keyframes, sequence->camera(), *reference);
    if (!row.ok()) return Fail(s.name + ": " + row.status().ToString());
    rows.push_back(*row);
    const Row& base = rows.front();
    const double saved_kB = (base.rgbd_bytes_per_keyframe - row->rgbd_bytes_per_keyframe) / 1e3;
    const double d_completeness = 100 * (base.error.completeness - row->error.completeness);
    const double d_mean = 1e3 * (row->error.mean - base.error.mean);
    const double d_psnr = base.psnr_db - row->psnr_db;
    const bool has_cost = std::fabs(saved_kB) > 0.01;
    auto per_kB = [&](double v) {
      char text[32];
      std::snprintf(text, sizeof(text), "%+.3f", v / saved_kB);
      return has_cost ? std::string(text) : std::string("-");
    };
    std::printf("| %s | %.2f | %+.2f | %zu | %.2f | %.1f%% | %.2f | %s | %s | %s |\n",
                s.name.c_str(), row->rgbd_bytes_per_keyframe / 1e3, saved_kB, row->map_points,
                1e3 * row->error.mean, 100 * row->error.completeness, row->psnr_db,
                per_kB(d_completeness).c_str(), per_kB(d_mean).c_str(), per_kB(d_psnr).c_str());
    std::fflush(stdout);
    Json e;
    e["setting"] = s.name;
    e["rgbd_bytes_per_keyframe"] = row->rgbd_bytes_per_keyframe;
    e["map_points"] = row->map_points;
    e["recon_mean_m"] = row->error.mean;
    e["recon_completeness"] = row->error.completeness;
    e["colour_psnr_db"] = row->psnr_db;
    list.Push(e);
  }
  if (!json_path.empty()) {
    const Status s = WriteJsonFile(list, json_path);
    if (!s.ok()) return Fail(s.ToString());
  }
  return 0;
}
