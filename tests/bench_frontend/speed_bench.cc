#include "tests/bench_frontend/speed_bench.h"

#include <algorithm>
#include <cstdio>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

#include "libccmd/util/timer.h"

namespace ccmd::bench {
namespace {

struct Pass {
  double ms = 0, cpu_ms = 0, keypoints = 0;
};

template <typename Extract>
Pass TimePass(const std::vector<cv::Mat>& grays, const Extract& extract) {
  Pass pass;
  const Stopwatch wall;
  const ThreadCpuStopwatch cpu;
  std::size_t keypoints = 0;
  for (const cv::Mat& gray : grays) keypoints += extract(gray);
  const double n = static_cast<double>(std::max<std::size_t>(1, grays.size()));
  pass.ms = wall.ElapsedMillis() / n;
  pass.cpu_ms = cpu.ElapsedMillis() / n;
  pass.keypoints = static_cast<double>(keypoints) / n;
  return pass;
}

void KeepFaster(const Pass& pass, Pass* best) {
  if (best->ms == 0 || pass.ms < best->ms) *best = pass;
}

}  // namespace

ExtractionSpeed MeasureExtraction(const std::vector<RgbdFrame>& frames, const OrbOptions& options,
                                  int passes, bool reference) {
  std::vector<cv::Mat> grays(frames.size());
  for (std::size_t i = 0; i < frames.size(); ++i)
    cv::cvtColor(frames[i].bgr, grays[i], cv::COLOR_BGR2GRAY);
  const OrbExtractor ours(options);
  // OpenCV's ORB with the same budget, pyramid and preferred FAST threshold (its edge
  // threshold is also the border it keeps).
  const cv::Ptr<cv::ORB> opencv =
      cv::ORB::create(options.features, options.scale_factor, options.levels, options.edge, 0, 2,
                      cv::ORB::HARRIS_SCORE, 31, options.fast_threshold);
  Pass best_ours, best_opencv;
  for (int p = 0; p < std::max(1, passes); ++p) {
    KeepFaster(TimePass(grays, [&](const cv::Mat& g) { return ours.Extract(g).keypoints.size(); }),
               &best_ours);
    if (!reference) continue;
    KeepFaster(TimePass(grays,
                        [&](const cv::Mat& g) {
                          std::vector<cv::KeyPoint> keypoints;
                          cv::Mat descriptors;
                          opencv->detectAndCompute(g, cv::noArray(), keypoints, descriptors);
                          return keypoints.size();
                        }),
               &best_opencv);
  }
  ExtractionSpeed speed;
  speed.frames = static_cast<int>(frames.size());
  speed.passes = std::max(1, passes);
  speed.ours_ms = best_ours.ms;
  speed.ours_cpu_ms = best_ours.cpu_ms;
  speed.ours_keypoints = best_ours.keypoints;
  speed.opencv_ms = best_opencv.ms;
  speed.opencv_cpu_ms = best_opencv.cpu_ms;
  speed.opencv_keypoints = best_opencv.keypoints;
  return speed;
}

Json ToJson(const ExtractionSpeed& s) {
  Json j;
  j["frames"] = s.frames;
  j["passes"] = s.passes;
  j["ms_per_frame"] = s.ours_ms;
  j["cpu_ms_per_frame"] = s.ours_cpu_ms;
  j["keypoints_per_frame"] = s.ours_keypoints;
  if (s.opencv_ms > 0) {
    j["opencv_orb_ms_per_frame"] = s.opencv_ms;
    j["opencv_orb_cpu_ms_per_frame"] = s.opencv_cpu_ms;
    j["opencv_orb_keypoints_per_frame"] = s.opencv_keypoints;
    j["ratio_to_opencv_orb"] = s.ours_ms / s.opencv_ms;
  }
  return j;
}

void Print(const ExtractionSpeed& s) {
  std::printf(
      "ORB extraction alone (%d frames, %s): %.2f ms/frame (CPU %.2f ms), %.0f keypoints\n",
      s.frames,
      s.passes > 1 ? ("fastest of " + std::to_string(s.passes) + " passes").c_str() : "one pass",
      s.ours_ms, s.ours_cpu_ms, s.ours_keypoints);
  if (s.opencv_ms > 0) {
    std::printf(
        "  OpenCV ORB detect+compute: %.2f ms/frame (CPU %.2f ms), %.0f keypoints; ratio "
        "ours/OpenCV %.2f\n",
        s.opencv_ms, s.opencv_cpu_ms, s.opencv_keypoints, s.ours_ms / s.opencv_ms);
  }
}

void ReportStages(const FrontendStats& s, Json* result) {
  const MappingStats& m = s.mapping;
  const double frames = std::max(1, s.frames), keyframes = std::max(1, m.keyframes);
  const double runs = std::max(1, m.local_ba_runs);
  Json& r = *result;
  r["extract_cpu_ms_mean"] = s.extract_cpu_ms_total / frames;
  r["track_cpu_ms_mean"] = s.track_cpu_ms_total / frames;
  r["mapping_cpu_ms_mean"] = m.mapping_cpu_ms_total / keyframes;
  r["local_ba_cpu_ms_mean"] = m.local_ba_cpu_ms_total / runs;
  r["mapping_keyframes"] = m.keyframes;
  r["local_ba_runs"] = m.local_ba_runs;
  r["local_ba_aborted"] = m.local_ba_aborted;
  r["local_ba_reduced"] = m.local_ba_reduced;
  r["local_ba_skipped_waiting"] = m.local_ba_skipped_waiting;
  r["local_ba_skipped_budget"] = m.local_ba_skipped_budget;
  r["local_ba_iterations_mean"] = m.local_ba_iterations / runs;
  std::printf(
      "  CPU per frame: extraction %.2f ms, tracking %.2f ms; per keyframe: mapping %.1f ms "
      "(local BA %.1f ms per run)\n",
      r["extract_cpu_ms_mean"].number(), r["track_cpu_ms_mean"].number(),
      r["mapping_cpu_ms_mean"].number(), r["local_ba_cpu_ms_mean"].number());
  std::printf(
      "  local BA: %d runs (%.1f iterations each), %d stopped early, %d reduced and %d skipped for "
      "the CPU "
      "budget, %d skipped for a waiting keyframe\n",
      m.local_ba_runs, r["local_ba_iterations_mean"].number(), m.local_ba_aborted,
      m.local_ba_reduced, m.local_ba_skipped_budget, m.local_ba_skipped_waiting);
}

}  // namespace ccmd::bench
