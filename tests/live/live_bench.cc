// ccmd_live_bench: per-frame cost of the live-camera path at 640x480 (and 1920x1080 colour),
// as a fraction of the 30 fps frame period and as a ratio to copying the same frame
// (cv::Mat::clone of colour + depth), measured in the same run.
//
//   build/bin/ccmd_live_bench [--repeat N] [--out DIR]

#include <CLI/CLI.hpp>
#include <cstdio>
#include <cstring>
#include <functional>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "libccmd/io/tum_recorder.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/sensors/pixel_formats.h"
#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/timer.h"

namespace {

// Median of `repeat` timings, in milliseconds.
double TimeMs(int repeat, const std::function<void()>& work) {
  std::vector<double> times;
  for (int i = 0; i < repeat; ++i) {
    ccmd::Stopwatch watch;
    work();
    times.push_back(watch.ElapsedMillis());
  }
  std::nth_element(times.begin(), times.begin() + times.size() / 2, times.end());
  return times[times.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Per-frame cost of camera format conversion, registration and recording"};
  int repeat = 30;
  std::string out = "/tmp/ccmd_live_bench";
  app.add_option("--repeat", repeat, "Timings per item (median reported)")
      ->check(CLI::Range(3, 10000));
  app.add_option("--out", out, "Scratch folder for the recorder (overwritten)");
  CLI11_PARSE(app, argc, argv);

  // A rendered frame with sensor noise: colour and depth as textured as a real room.
  auto spec = ccmd::ParseSyntheticSpec("frames=1,width=640,height=480");
  ccmd::SyntheticSource source(*spec);
  ccmd::RgbdFrame frame;
  if (!source.Read(&frame).ok()) return 1;

  // Device buffers made from it.
  cv::Mat yuv;
  cv::cvtColor(frame.bgr, yuv, cv::COLOR_BGR2YUV);
  std::vector<std::uint8_t> yuyv(640 * 480 * 2);
  for (int y = 0; y < 480; ++y) {
    for (int x = 0; x < 640; x += 2) {
      const cv::Vec3b a = yuv.at<cv::Vec3b>(y, x), b = yuv.at<cv::Vec3b>(y, x + 1);
      std::uint8_t* p = &yuyv[(y * 640 + x) * 2];
      p[0] = a[0], p[1] = a[1], p[2] = b[0], p[3] = a[2];
    }
  }
  std::vector<std::uint8_t> jpeg;
  cv::imencode(".jpg", frame.bgr, jpeg, {cv::IMWRITE_JPEG_QUALITY, 90});
  std::vector<std::uint8_t> z16(640 * 480 * 2);
  std::memcpy(z16.data(), frame.depth_mm.data, z16.size());
  cv::Mat hd;
  cv::resize(frame.bgr, hd, cv::Size(1920, 1080), 0, 0, cv::INTER_LINEAR);
  ccmd::PinholeCamera depth_camera = source.camera();
  depth_camera.fx = depth_camera.fy = 385;
  ccmd::PinholeCamera color_camera = source.camera();
  color_camera.fx = color_camera.fy = 615;
  ccmd::Pose T = ccmd::Pose::Identity();
  T.translation().x() = 0.015;

  cv::Mat sink_bgr, sink_depth;
  const double reference = TimeMs(repeat, [&] {
    sink_bgr = frame.bgr.clone();
    sink_depth = frame.depth_mm.clone();
  });
  struct Item {
    const char* name;
    double ms;
  };
  std::vector<Item> items;
  ccmd::MjpegDecoder decoder;
  items.push_back({"YUYV to BGR", TimeMs(repeat, [&] {
                     ccmd::ConvertYuyvToBgr(yuyv.data(), yuyv.size(), {640, 480, 1280}, &sink_bgr)
                         .IgnoreError();
                   })});
  items.push_back({"MJPEG decode (q90)", TimeMs(repeat, [&] {
                     decoder.Decode(jpeg.data(), jpeg.size(), 640, 480, &sink_bgr).IgnoreError();
                   })});
  items.push_back({"Z16 to mm (1 mm units)", TimeMs(repeat, [&] {
                     ccmd::ConvertZ16ToMillimetres(z16.data(), z16.size(), {640, 480, 1280}, 0.001,
                                                   &sink_depth)
                         .IgnoreError();
                   })});
  items.push_back({"Z16 to mm (100 um units)", TimeMs(repeat, [&] {
                     ccmd::ConvertZ16ToMillimetres(z16.data(), z16.size(), {640, 480, 1280}, 0.0001,
                                                   &sink_depth)
                         .IgnoreError();
                   })});
  items.push_back({"colour 1920x1080 to 640x480", TimeMs(repeat, [&] {
                     sink_bgr = ccmd::ResizeColorToDepth(hd, cv::Size(640, 480));
                   })});
  items.push_back({"depth registered to colour", TimeMs(repeat, [&] {
                     sink_depth =
                         ccmd::RegisterDepthToColor(frame.depth_mm, depth_camera, color_camera, T);
                   })});
  for (const int level : {0, 1}) {
    ccmd::TumRecorderOptions options;
    options.overwrite = true;
    options.png_compression = level;
    auto recorder = ccmd::TumRecorder::Create(out, source.camera(), options);
    if (!recorder.ok()) {
      std::fprintf(stderr, "%s\n", recorder.status().ToString().c_str());
      return 1;
    }
    double t = 0;
    const double ms = TimeMs(repeat, [&] {
      frame.timestamp = (t += 1);
      (*recorder)->Write(frame).IgnoreError();
    });
    items.push_back(
        {level == 0 ? "record a frame, PNG level 0" : "record a frame, PNG level 1", ms});
  }

  std::printf("reference: clone colour + depth 640x480 = %.3f ms; frame period 33.3 ms\n",
              reference);
  std::printf("| step | ms | x frame period | x clone |\n|---|---|---|---|\n");
  for (const Item& item : items) {
    std::printf("| %s | %.2f | %.3f | %.1f |\n", item.name, item.ms, item.ms / (1000.0 / 30),
                item.ms / reference);
  }
  return 0;
}
