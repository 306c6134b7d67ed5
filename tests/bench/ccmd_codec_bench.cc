// ccmd_codec_bench: depth codecs on real frames, side by side with the paper's stages and
// the usual peers, all measured in one run on the same frames.
//
//   ccmd_codec_bench [--dataset DIR]... [--frames N] [--json OUT] [--recon-frames N]
//
// Frames come from the given TUM-layout folders, else from ../shared/datasets (7-Scenes and
// TUM excerpts) when present, else from a generated synthetic sequence. Each frame is coded
// at its full 640x480 and at 320x240 (depth-aware downsampling by 2, as the agent sends it).
// Times are thread CPU time, medians over frames (each frame coded 3 times, fastest kept). The last
// part codes a synthetic sequence with exact ground truth, back-projects the decoded depth at the
// true poses and measures the reconstruction error against the true surface, to show what
// each mode's error does to the dense map.

#include <lz4.h>
#include <zstd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "libccmd/codec/colour_codec.h"
#include "libccmd/codec/depth_codec.h"
#include "libccmd/codec/depth_downsample.h"
#include "libccmd/codec/depth_quantizer.h"
#include "libccmd/codec/lz77.h"
#include "libccmd/codec/rle.h"
#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"
#include "tests/bench/rvl.h"

namespace ccmd::bench {
namespace {

using Bytes = std::vector<std::uint8_t>;

struct Frame {
  std::string dataset;
  cv::Mat depth;  // CV_16UC1 mm
  cv::Mat bgr;    // CV_8UC3
};

struct Codec {
  std::string name;
  bool lossless = true;
  std::function<Bytes(const cv::Mat&)> encode;
  std::function<cv::Mat(const Bytes&, int width, int height)> decode;
};

std::span<const std::uint8_t> RawBytes(const cv::Mat& m) {
  return {m.ptr<std::uint8_t>(0), m.total() * m.elemSize()};
}

Codec OurMode(DepthMode mode, int bound_e4 = kDefaultBoundE4) {
  Codec c;
  c.name = DepthModeName(mode);
  if (mode == DepthMode::kBounded && bound_e4 != kDefaultBoundE4) {
    c.name += " " + std::to_string(bound_e4 / 100.0).substr(0, 3) + "%";
  }
  c.lossless = DepthModeIsLossless(mode);
  c.encode = [mode, bound_e4](const cv::Mat& d) {
    DepthEncodeOptions o;
    o.mode = mode;
    o.bound_e4 = bound_e4;
    auto bytes = EncodeDepth(d, o);
    CCMD_CHECK(bytes.ok()) << bytes.status().ToString();
    return std::move(bytes).value();
  };
  c.decode = [](const Bytes& b, int, int) {
    auto image = DecodeDepth(b);
    CCMD_CHECK(image.ok()) << image.status().ToString();
    return std::move(image).value();
  };
  return c;
}

Codec Png(int level) {
  Codec c;
  c.name = "png" + std::to_string(level);
  c.encode = [level](const cv::Mat& d) {
    Bytes out;
    cv::imencode(".png", d, out, {cv::IMWRITE_PNG_COMPRESSION, level});
    return out;
  };
  c.decode = [](const Bytes& b, int, int) { return cv::imdecode(b, cv::IMREAD_UNCHANGED); };
  return c;
}

Codec Zstd(int level) {
  Codec c;
  c.name = "zstd" + std::to_string(level);
  c.encode = [level](const cv::Mat& d) {
    const auto raw = RawBytes(d);
    Bytes out(ZSTD_compressBound(raw.size()));
    out.resize(ZSTD_compress(out.data(), out.size(), raw.data(), raw.size(), level));
    return out;
  };
  c.decode = [](const Bytes& b, int w, int h) {
    cv::Mat d(h, w, CV_16UC1);
    const std::size_t n = ZSTD_decompress(d.data, d.total() * 2, b.data(), b.size());
    CCMD_CHECK(n == d.total() * 2);
    return d;
  };
  return c;
}

Codec Lz4() {
  Codec c;
  c.name = "lz4";
  c.encode = [](const cv::Mat& d) {
    const auto raw = RawBytes(d);
    Bytes out(LZ4_compressBound(static_cast<int>(raw.size())));
    out.resize(LZ4_compress_default(reinterpret_cast<const char*>(raw.data()),
                                    reinterpret_cast<char*>(out.data()),
                                    static_cast<int>(raw.size()), static_cast<int>(out.size())));
    return out;
  };
  c.decode = [](const Bytes& b, int w, int h) {
    cv::Mat d(h, w, CV_16UC1);
    const int n = LZ4_decompress_safe(reinterpret_cast<const char*>(b.data()),
                                      reinterpret_cast<char*>(d.data), static_cast<int>(b.size()),
                                      static_cast<int>(d.total() * 2));
    CCMD_CHECK(n == static_cast<int>(d.total() * 2));
    return d;
  };
  return c;
}

// zstd-3 on the eq. 6 quantiser's codes: the reference for ccmd-quantised's size.
Codec QuantisedZstd3() {
  Codec c;
  c.name = "qt+zstd3";
  c.lossless = false;
  c.encode = [](const cv::Mat& d) {
    std::vector<std::uint16_t> codes(d.total());
    const std::uint16_t* p = d.ptr<std::uint16_t>(0);
    for (std::size_t i = 0; i < codes.size(); ++i) codes[i] = QuantizeEq6(p[i]);
    Bytes out(ZSTD_compressBound(codes.size() * 2));
    out.resize(ZSTD_compress(out.data(), out.size(), codes.data(), codes.size() * 2, 3));
    return out;
  };
  c.decode = [](const Bytes& b, int w, int h) {
    cv::Mat d(h, w, CV_16UC1);
    const std::size_t n = ZSTD_decompress(d.data, d.total() * 2, b.data(), b.size());
    CCMD_CHECK(n == d.total() * 2);
    std::uint16_t* p = d.ptr<std::uint16_t>(0);
    for (std::size_t i = 0; i < d.total(); ++i) p[i] = DequantizeEq6(p[i]);
    return d;
  };
  return c;
}

// Our LZ77 alone on the raw buffer: comparable with lz4, and the LZ77 throughput figure.
Codec OurLz77() {
  Codec c;
  c.name = "lz77";
  c.encode = [](const cv::Mat& d) {
    Bytes out;
    Lz77Compress(RawBytes(d), &out);
    return out;
  };
  c.decode = [](const Bytes& b, int w, int h) {
    Bytes raw;
    CCMD_CHECK(Lz77Decompress(b, std::size_t{1} << 28, &raw).ok());
    cv::Mat d(h, w, CV_16UC1);
    CCMD_CHECK(raw.size() == d.total() * 2);
    std::memcpy(d.data, raw.data(), raw.size());
    return d;
  };
  return c;
}

Codec Rvl() {
  Codec c;
  c.name = "rvl";
  c.encode = [](const cv::Mat& d) { return RvlEncode({d.ptr<std::uint16_t>(0), d.total()}); };
  c.decode = [](const Bytes& b, int w, int h) {
    cv::Mat d(h, w, CV_16UC1);
    CCMD_CHECK(RvlDecode(b, {d.ptr<std::uint16_t>(0), d.total()}));
    return d;
  };
  return c;
}

std::vector<Codec> AllCodecs() {
  return {OurMode(DepthMode::kRaw), OurMode(DepthMode::kRle), OurMode(DepthMode::kRleLz77),
          OurMode(DepthMode::kEq6Rle), OurMode(DepthMode::kEq6RleLz77),
          OurMode(DepthMode::kLossless), OurMode(DepthMode::kQuantised),
          OurMode(DepthMode::kBounded), Png(1), Png(3), Zstd(1), Zstd(3), Lz4(), Rvl(), OurLz77(),
          QuantisedZstd3(),
          // Other bounds, for the choice of the agent's default.
          OurMode(DepthMode::kBounded, 50), OurMode(DepthMode::kBounded, 200)};
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

struct Row {
  std::string dataset, codec;
  int width = 0, height = 0;
  bool lossless = true;
  std::vector<double> bytes, encode_ms, decode_ms;
  double max_abs_error_mm = 0, max_rel_error = 0;
  std::uint64_t dropped = 0, invented = 0, valid = 0;

  Json ToJson() const {
    Json j;
    const double raw = 2.0 * width * height;
    double mean = 0;
    for (double b : bytes) mean += b;
    mean /= std::max<std::size_t>(1, bytes.size());
    j["dataset"] = dataset;
    j["codec"] = codec;
    j["width"] = width;
    j["height"] = height;
    j["frames"] = bytes.size();
    j["bytes_mean"] = mean;
    j["ratio"] = mean > 0 ? raw / mean : 0.0;
    j["encode_ms"] = Median(encode_ms);
    j["decode_ms"] = Median(decode_ms);
    j["decode_mb_s"] = Median(decode_ms) > 0 ? raw / (Median(decode_ms) * 1e3) : 0.0;
    j["lossless"] = lossless;
    j["max_abs_error_mm"] = max_abs_error_mm;
    j["max_rel_error"] = max_rel_error;
    j["dropped_pixels"] = dropped;
    j["invented_pixels"] = invented;
    return j;
  }
};

// Thread CPU time: on a shared machine wall time also counts the time other processes held
// the core; every codec, ours and the peers, is timed the same way.
double ThreadCpuMillis() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

void Measure(const Codec& codec, const cv::Mat& depth, Row* row) {
  Bytes bytes;
  double best_encode = 1e30, best_decode = 1e30;
  cv::Mat decoded;
  for (int k = 0; k < 3; ++k) {
    const double t0 = ThreadCpuMillis();
    bytes = codec.encode(depth);
    const double t1 = ThreadCpuMillis();
    decoded = codec.decode(bytes, depth.cols, depth.rows);
    const double t2 = ThreadCpuMillis();
    best_encode = std::min(best_encode, t1 - t0);
    best_decode = std::min(best_decode, t2 - t1);
  }
  CCMD_CHECK(decoded.size() == depth.size() && decoded.type() == CV_16UC1) << codec.name;
  row->bytes.push_back(static_cast<double>(bytes.size()));
  row->encode_ms.push_back(best_encode);
  row->decode_ms.push_back(best_decode);
  for (int y = 0; y < depth.rows; ++y) {
    const std::uint16_t* a = depth.ptr<std::uint16_t>(y);
    const std::uint16_t* b = decoded.ptr<std::uint16_t>(y);
    for (int x = 0; x < depth.cols; ++x) {
      if (a[x] == 0) {
        row->invented += b[x] != 0;
        continue;
      }
      ++row->valid;
      if (b[x] == 0) {
        ++row->dropped;
        continue;
      }
      const double err = std::abs(static_cast<double>(a[x]) - b[x]);
      row->max_abs_error_mm = std::max(row->max_abs_error_mm, err);
      row->max_rel_error = std::max(row->max_rel_error, err / a[x]);
    }
  }
}

StatusOr<std::vector<Frame>> LoadFrames(const std::string& folder, int count) {
  PinholeCamera camera;  // only the depth scale matters here: 5000 per metre
  TumOptions options;
  options.depth_map_factor = 5000.0;
  CCMD_ASSIGN_OR_RETURN(TumSequence seq, TumSequence::Open(folder, camera, options));
  std::vector<Frame> frames;
  const std::string name = folder.substr(folder.find_last_of('/') + 1);
  const std::size_t n = std::min<std::size_t>(count, seq.size());
  for (std::size_t k = 0; k < n; ++k) {
    const std::size_t i = n > 1 ? k * (seq.size() - 1) / (n - 1) : 0;  // spread over the sequence
    CCMD_ASSIGN_OR_RETURN(RgbdFrame f, seq.LoadFrame(i));
    frames.push_back({name, f.depth_mm, f.bgr});
  }
  return frames;
}

void PrintRow(const Json& j) {
  std::printf("%-28s %-15s %4dx%-4d %9.0f %7.2f %8.3f %8.3f %7.0f %s %7.1f %8.4f\n",
              j.Get("dataset")->string().c_str(), j.Get("codec")->string().c_str(),
              static_cast<int>(j.Get("width")->number()),
              static_cast<int>(j.Get("height")->number()), j.Get("bytes_mean")->number(),
              j.Get("ratio")->number(), j.Get("encode_ms")->number(), j.Get("decode_ms")->number(),
              j.Get("decode_mb_s")->number(), j.Get("lossless")->boolean() ? "yes" : " no",
              j.Get("max_abs_error_mm")->number(), j.Get("max_rel_error")->number());
}

const Json* FindRow(const Json& rows, const std::string& dataset, const std::string& codec,
                    int width) {
  for (const Json& r : rows.array()) {
    if (r.Get("dataset")->string() == dataset && r.Get("codec")->string() == codec &&
        static_cast<int>(r.Get("width")->number()) == width) {
      return &r;
    }
  }
  return nullptr;
}

// The targets of the codec issue, as ratios to references measured in this run.
void PrintTargets(const Json& rows, const std::string& dataset, Json* summary) {
  const Json* lossless = FindRow(rows, dataset, "ccmd-lossless", 320);
  const Json* quantised = FindRow(rows, dataset, "ccmd-quantised", 320);
  const Json* bounded = FindRow(rows, dataset, "ccmd-bounded", 320);
  const Json* zstd3 = FindRow(rows, dataset, "zstd3", 320);
  const Json* qt_zstd3 = FindRow(rows, dataset, "qt+zstd3", 320);
  const Json* png1 = FindRow(rows, dataset, "png1", 320);
  const Json* png3 = FindRow(rows, dataset, "png3", 320);
  const Json* rvl = FindRow(rows, dataset, "rvl", 320);
  if (!lossless || !zstd3 || !png1 || !rvl || !bounded || !quantised || !png3 || !qt_zstd3) {
    return;
  }
  auto bytes = [](const Json* r) { return r->Get("bytes_mean")->number(); };
  auto total_ms = [](const Json* r) {
    return r->Get("encode_ms")->number() + r->Get("decode_ms")->number();
  };
  const double lossless_vs_zstd3 = bytes(lossless) / bytes(zstd3);
  const double speedup_vs_png1 = total_ms(png1) / total_ms(lossless);
  Json s;
  s["dataset"] = dataset;
  s["lossless_bytes_vs_zstd3"] = lossless_vs_zstd3;
  s["lossless_bytes_vs_png1"] = bytes(lossless) / bytes(png1);
  s["lossless_bytes_vs_png3"] = bytes(lossless) / bytes(png3);
  s["lossless_bytes_vs_rvl"] = bytes(lossless) / bytes(rvl);
  s["lossless_speedup_vs_png1"] = speedup_vs_png1;
  s["bounded_bytes"] = bytes(bounded);
  s["bounded_max_rel_error"] = bounded->Get("max_rel_error")->number();
  s["quantised_bytes"] = bytes(quantised);
  s["quantised_bytes_vs_qt_zstd3"] = bytes(quantised) / bytes(qt_zstd3);
  s["quantised_max_abs_error_mm"] = quantised->Get("max_abs_error_mm")->number();
  std::printf(
      "\n[%s, 320x240] ccmd-lossless: %.3fx zstd3 bytes (target <= 0.85), %.3fx png1, "
      "%.3fx png3, %.3fx rvl (targets < 1); encode+decode %.1fx faster than png1 (target >= 3)\n"
      "  ccmd-bounded: %.0f bytes (target <= 5359), max relative error %.5f (bound 0.01)\n"
      "  ccmd-quantised: %.0f bytes, %.3fx quantiser + zstd3 (target <= 1), max error %.1f mm "
      "(bound 4)\n",
      dataset.c_str(), lossless_vs_zstd3, bytes(lossless) / bytes(png1),
      bytes(lossless) / bytes(png3), bytes(lossless) / bytes(rvl), speedup_vs_png1, bytes(bounded),
      bounded->Get("max_rel_error")->number(), bytes(quantised), bytes(quantised) / bytes(qt_zstd3),
      quantised->Get("max_abs_error_mm")->number());
  summary->Push(s);
}

// --- Reconstruction error of each mode on a synthetic sequence with exact ground truth.

struct ReconConfig {
  std::string name;
  DepthMode mode;
  int bound_e4;
};

Status RunReconstruction(int frames, int downsample, Json* out) {
  char pattern[] = "/tmp/ccmd_codec_bench_XXXXXX";
  const char* dir = mkdtemp(pattern);
  if (!dir) return IoError("cannot create a temporary folder");
  const std::string folder = dir;
  SyntheticSequenceOptions so;
  so.frames = frames;
  so.fps = frames / so.path.loop_period_s;  // one loop around the room
  so.seed = 5;
  std::fflush(stdout);  // keep the log line out of the tables above
  CCMD_LOG(INFO) << "rendering a " << frames << "-frame synthetic sequence into " << folder;
  CCMD_RETURN_IF_ERROR(WriteSyntheticSequence(folder, so).status());
  CCMD_ASSIGN_OR_RETURN(TumSequence seq, TumSequence::Open(folder, std::nullopt));
  CCMD_ASSIGN_OR_RETURN(PointCloud reference, ReadPly(JoinPath(folder, "surface.ply")));
  const PinholeCamera camera = seq.camera().Scaled(1.0 / downsample);

  const std::vector<ReconConfig> configs = {
      {"ccmd-lossless", DepthMode::kLossless, 0},     {"ccmd-quantised", DepthMode::kQuantised, 0},
      {"ccmd-bounded 0.5%", DepthMode::kBounded, 50}, {"ccmd-bounded 1%", DepthMode::kBounded, 100},
      {"ccmd-bounded 2%", DepthMode::kBounded, 200},  {"ccmd-bounded 5%", DepthMode::kBounded, 500},
  };
  std::printf("\nReconstruction error, synthetic room, %d frames at r = 1/%d (%dx%d), true poses\n",
              frames, downsample, camera.width, camera.height);
  std::printf("%-20s %9s %9s %9s %9s %9s %9s %10s\n", "mode", "bytes", "mean_mm", "median_mm",
              "rmse_mm", "p95_mm", "max_mm", "points");
  for (const ReconConfig& config : configs) {
    PointCloud cloud;
    double bytes = 0;
    for (std::size_t i = 0; i < seq.size(); ++i) {
      CCMD_ASSIGN_OR_RETURN(RgbdFrame f, seq.LoadFrame(i));
      const TumFrameInfo& info = seq.frame(i);
      if (!info.T_world_cam_gt) return Internal("synthetic frame without ground truth");
      DepthEncodeOptions o;
      o.mode = config.mode;
      o.downsample = downsample;
      if (config.bound_e4) o.bound_e4 = config.bound_e4;
      CCMD_ASSIGN_OR_RETURN(Bytes coded, EncodeDepth(f.depth_mm, o));
      bytes += coded.size();
      CCMD_ASSIGN_OR_RETURN(cv::Mat depth, DecodeDepth(coded));
      const Pose& T = *info.T_world_cam_gt;
      for (int y = 0; y < depth.rows; ++y) {
        const std::uint16_t* row = depth.ptr<std::uint16_t>(y);
        for (int x = 0; x < depth.cols; ++x) {
          if (!row[x]) continue;
          const Eigen::Vector3d p = T * camera.BackProject(x, y, row[x] * 1e-3);
          cloud.points.push_back(p.cast<float>());
        }
      }
    }
    CCMD_ASSIGN_OR_RETURN(ReconstructionError e, ComputeReconstructionError(reference, cloud));
    std::printf("%-20s %9.0f %9.2f %9.2f %9.2f %9.2f %9.1f %10zu\n", config.name.c_str(),
                bytes / seq.size(), e.mean * 1e3, e.median * 1e3, e.rmse * 1e3, e.p95 * 1e3,
                e.max * 1e3, cloud.size());
    Json j;
    j["mode"] = config.name;
    j["downsample"] = downsample;
    j["width"] = camera.width;
    j["height"] = camera.height;
    j["frames"] = frames;
    j["bytes_mean"] = bytes / seq.size();
    j["mean_mm"] = e.mean * 1e3;
    j["median_mm"] = e.median * 1e3;
    j["rmse_mm"] = e.rmse * 1e3;
    j["p95_mm"] = e.p95 * 1e3;
    j["max_mm"] = e.max * 1e3;
    j["completeness"] = e.completeness;
    out->Push(j);
  }
  std::error_code ignored;
  std::filesystem::remove_all(folder, ignored);
  return Status::Ok();
}

int Main(int argc, char** argv) {
  CLI::App app{"Depth codec benchmark: the paper's stages, ccmd modes and peers on real frames."};
  std::vector<std::string> datasets;
  int frames = 30;
  int recon_frames = 32;
  std::string json_path;
  app.add_option("--dataset", datasets, "TUM-layout folder(s) (default: ../shared/datasets)");
  app.add_option("--frames", frames, "Frames per dataset, spread over the sequence")
      ->check(CLI::Range(1, 100000));
  app.add_option("--json", json_path, "Write the rows as JSON");
  app.add_option("--recon-frames", recon_frames,
                 "Synthetic frames for the reconstruction-error part (0: skip)")
      ->check(CLI::Range(0, 10000));
  CLI11_PARSE(app, argc, argv);

  if (datasets.empty()) {
    for (const char* name : {"7scenes_redkitchen_0000_0599", "tum_fr1_desk_9"}) {
      const std::string path = std::string(CCMD_SHARED_DATASETS) + "/" + name;
      if (IsDirectory(path)) datasets.push_back(path);
    }
  }
  std::vector<Frame> all;
  std::string synthetic_dir;
  if (datasets.empty()) {
    char pattern[] = "/tmp/ccmd_codec_frames_XXXXXX";
    const char* dir = mkdtemp(pattern);
    CCMD_CHECK(dir != nullptr);
    synthetic_dir = dir;
    std::fprintf(stderr, "no real datasets found: using a synthetic sequence in %s\n", dir);
    SyntheticSequenceOptions so;
    so.frames = frames;
    so.fps = frames / so.path.loop_period_s;
    auto written = WriteSyntheticSequence(synthetic_dir, so);
    if (!written.ok()) {
      std::fprintf(stderr, "%s\n", written.status().ToString().c_str());
      return 1;
    }
    datasets.push_back(synthetic_dir);
  }
  std::vector<std::string> names;
  for (const std::string& d : datasets) {
    auto loaded = LoadFrames(d, frames);
    if (!loaded.ok()) {
      std::fprintf(stderr, "%s: %s\n", d.c_str(), loaded.status().ToString().c_str());
      return 1;
    }
    names.push_back(loaded->front().dataset);
    all.insert(all.end(), loaded->begin(), loaded->end());
  }
  if (names.size() > 1) names.push_back("all");

  const std::vector<Codec> codecs = AllCodecs();
  Json rows = Json::MakeArray();
  std::printf("%-28s %-15s %9s %9s %7s %8s %8s %7s %s %7s %8s\n", "dataset", "codec", "size",
              "bytes", "ratio", "enc_ms", "dec_ms", "dec_MBs", "lossless", "max_mm", "max_rel");
  Json summary = Json::MakeArray();
  for (int factor : {1, 2}) {
    // Downsampling once per frame (depth-aware, as the agent does), timed separately.
    std::vector<cv::Mat> images;
    std::vector<double> downsample_ms;
    for (const Frame& f : all) {
      Stopwatch s;
      auto d = DownsampleDepth(f.depth, factor);
      downsample_ms.push_back(s.ElapsedMillis());
      images.push_back(*d);
    }
    for (const std::string& name : names) {
      std::vector<cv::Mat> subset;
      for (std::size_t i = 0; i < all.size(); ++i) {
        if (name == "all" || all[i].dataset == name) subset.push_back(images[i]);
      }
      for (const Codec& codec : codecs) {
        Row row;
        row.dataset = name;
        row.codec = codec.name;
        row.width = subset.front().cols;
        row.height = subset.front().rows;
        row.lossless = codec.lossless;
        for (const cv::Mat& image : subset) Measure(codec, image, &row);
        Json j = row.ToJson();
        PrintRow(j);
        rows.Push(j);
      }
    }
    std::printf("downsampling by %d (depth-aware median): %.3f ms per frame (median)\n\n", factor,
                Median(downsample_ms));
  }
  for (const std::string& name : names) PrintTargets(rows, name, &summary);

  // Colour: the keyframe's JPEG at each sampling rate (after matching the depth size).
  Json colour = Json::MakeArray();
  std::printf("\nColour JPEG (libjpeg-turbo, 4:2:0), all frames\n%-10s %9s %9s %9s %9s %9s\n",
              "size", "quality", "bytes", "enc_ms", "dec_ms", "psnr_db");
  for (int factor : {1, 2, 4}) {
    for (int quality : {50, 75, 90}) {
      std::vector<double> bytes, encode_ms, decode_ms, psnr;
      cv::Size size;
      for (const Frame& f : all) {
        auto prepared = PrepareColour(f.bgr, f.depth.size(), factor);
        CCMD_CHECK(prepared.ok());
        size = prepared->size();
        ColourEncodeOptions o;
        o.quality = quality;
        o.downsample = factor;
        const double t0 = ThreadCpuMillis();
        auto jpeg = EncodeColour(f.bgr, f.depth.size(), o);
        const double t1 = ThreadCpuMillis();
        CCMD_CHECK(jpeg.ok()) << jpeg.status().ToString();
        auto decoded = DecodeColour(*jpeg);
        const double t2 = ThreadCpuMillis();
        CCMD_CHECK(decoded.ok());
        bytes.push_back(static_cast<double>(jpeg->size()));
        encode_ms.push_back(t1 - t0);
        decode_ms.push_back(t2 - t1);
        psnr.push_back(cv::PSNR(*decoded, *prepared));
      }
      double mean_bytes = 0, mean_psnr = 0;
      for (double b : bytes) mean_bytes += b / bytes.size();
      for (double p : psnr) mean_psnr += p / psnr.size();
      std::printf("%4dx%-5d %9d %9.0f %9.3f %9.3f %9.2f\n", size.width, size.height, quality,
                  mean_bytes, Median(encode_ms), Median(decode_ms), mean_psnr);
      Json j;
      j["width"] = size.width;
      j["height"] = size.height;
      j["quality"] = quality;
      j["bytes_mean"] = mean_bytes;
      j["encode_ms"] = Median(encode_ms);
      j["decode_ms"] = Median(decode_ms);
      j["psnr_db"] = mean_psnr;
      colour.Push(j);
    }
  }

  Json recon = Json::MakeArray();
  if (recon_frames > 0) {
    for (int factor : {2}) {
      const Status s = RunReconstruction(recon_frames, factor, &recon);
      if (!s.ok()) {
        std::fprintf(stderr, "reconstruction part failed: %s\n", s.ToString().c_str());
        return 1;
      }
    }
  }
  if (!synthetic_dir.empty()) {
    std::error_code ignored;
    std::filesystem::remove_all(synthetic_dir, ignored);
  }
  if (!json_path.empty()) {
    Json doc = rows;
    // The required list of rows stays the top-level value; the summaries go alongside.
    const Status s = WriteJsonFile(doc, json_path);
    const Status s2 =
        WriteJsonFile(Json(Json::Object{{"targets", summary}, {"reconstruction", recon}}),
                      json_path.substr(0, json_path.find_last_of('.')) + ".summary.json");
    if (!s.ok() || !s2.ok()) {
      std::fprintf(stderr, "cannot write %s\n", json_path.c_str());
      return 1;
    }
  }
  return 0;
}

}  // namespace
}  // namespace ccmd::bench

int main(int argc, char** argv) { return ccmd::bench::Main(argc, argv); }
