#include "libccmd/synth/sequence.h"

#include <gtest/gtest.h>

#include <limits>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/io/config.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/tum_dataset.h"
#include "libccmd/sensors/synthetic_source.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

SyntheticSequenceOptions SmallOptions() {
  SyntheticSequenceOptions o;
  o.frames = 12;
  o.width = 160;
  o.height = 120;
  o.seed = 3;
  o.surface_spacing = 0.05;
  o.room.shapes_per_m2 = 40;
  return o;
}

TEST(SequenceTest, WrittenSequenceReadsBackWithExactGroundTruth) {
  testing::TempDir dir;
  const SyntheticSequenceOptions options = SmallOptions();
  auto summary = WriteSyntheticSequence(dir.path(), options);
  ASSERT_TRUE(summary.ok()) << summary.status().ToString();
  auto seq = TumSequence::Open(dir.path(), std::nullopt);  // camera from camera.yaml
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  ASSERT_EQ(seq->size(), 12u);
  EXPECT_EQ(seq->camera().width, 160);
  EXPECT_NEAR(seq->camera().fx, 525.0 / 4, 1e-6);
  const Trajectory path = MakeLoopPath(12, 30.0, options.path);
  for (std::size_t i = 0; i < seq->size(); ++i) {
    ASSERT_TRUE(seq->frame(i).T_world_cam_gt.has_value());
    EXPECT_LT(TranslationDistance(*seq->frame(i).T_world_cam_gt, path[i].T_world_cam), 1e-6);
    EXPECT_LT(RotationDistance(*seq->frame(i).T_world_cam_gt, path[i].T_world_cam), 1e-6);
  }
  // The on-the-fly source renders the same frames (depth bit-exact after the 5000/m file).
  SyntheticSource source(options);
  for (std::size_t i = 0; i < 3; ++i) {
    RgbdFrame live;
    ASSERT_TRUE(source.Read(&live).ok());
    auto stored = seq->LoadFrame(i);
    ASSERT_TRUE(stored.ok());
    EXPECT_EQ(cv::norm(live.depth_mm, stored->depth_mm, cv::NORM_INF), 0) << i;
    EXPECT_EQ(cv::norm(live.bgr, stored->bgr, cv::NORM_INF), 0) << i;
  }
}

// Rendered through a config's camera: its size, frame rate, depth scale, focal lengths (a
// negative fy) and colour order are those of the files, and camera.yaml describes them.
TEST(SequenceTest, ConfigCameraRecordsAsThatCameraWould) {
  testing::TempDir dir;
  SyntheticSequenceOptions options = SmallOptions();
  PinholeCamera camera = SyntheticCamera(200, 150);
  camera.fy = -camera.fy;
  camera.fps = 15;
  camera.depth_map_factor = 1000;
  camera.rgb = false;
  options.camera = camera;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("bgr"), options).ok());
  auto seq = TumSequence::Open(dir.File("bgr"), std::nullopt);
  ASSERT_TRUE(seq.ok()) << seq.status().ToString();
  EXPECT_EQ(seq->camera().width, 200);
  EXPECT_NEAR(seq->camera().fy, camera.fy, 1e-6);
  EXPECT_EQ(seq->camera().depth_map_factor, 1000);
  EXPECT_FALSE(seq->camera().rgb);
  EXPECT_NEAR(seq->frame(1).timestamp - seq->frame(0).timestamp, 1.0 / 15, 1e-6);

  // The same camera with the usual colour order: the files differ by the swap of red and blue,
  // and both read back to the same image.
  options.camera->rgb = true;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("rgb"), options).ok());
  auto usual = TumSequence::Open(dir.File("rgb"), std::nullopt);
  ASSERT_TRUE(usual.ok());
  const cv::Mat swapped_file = cv::imread(seq->frame(0).rgb_path, cv::IMREAD_COLOR);
  const cv::Mat usual_file = cv::imread(usual->frame(0).rgb_path, cv::IMREAD_COLOR);
  std::vector<cv::Mat> a, b;
  cv::split(swapped_file, a);
  cv::split(usual_file, b);
  EXPECT_EQ(cv::norm(a[0], b[2], cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(a[2], b[0], cv::NORM_INF), 0);
  EXPECT_GT(cv::norm(a[0], b[0], cv::NORM_L1), 0);
  auto read_swapped = seq->LoadFrame(0), read_usual = usual->LoadFrame(0);
  ASSERT_TRUE(read_swapped.ok() && read_usual.ok());
  EXPECT_EQ(cv::norm(read_swapped->bgr, read_usual->bgr, cv::NORM_INF), 0);
  // Depth files in millimetres (DepthMapFactor 1000), read back as the same millimetres.
  const cv::Mat depth_file = cv::imread(usual->frame(0).depth_path, cv::IMREAD_UNCHANGED);
  EXPECT_EQ(cv::norm(depth_file, read_usual->depth_mm, cv::NORM_INF), 0);
  EXPECT_GT(cv::countNonZero(depth_file), 100);
}

// Mean |noisy - exact| depth (mm) of a sequence's first frame over pixels valid in both.
double MeanDepthNoiseMm(const TumSequence& noisy, const TumSequence& exact) {
  auto a = noisy.LoadFrame(0), b = exact.LoadFrame(0);
  EXPECT_TRUE(a.ok() && b.ok());
  double sum = 0;
  int n = 0;
  for (int v = 0; v < a->depth_mm.rows; ++v) {
    for (int u = 0; u < a->depth_mm.cols; ++u) {
      const int za = a->depth_mm.at<std::uint16_t>(v, u), zb = b->depth_mm.at<std::uint16_t>(v, u);
      if (za == 0 || zb == 0) continue;
      sum += std::abs(za - zb);
      ++n;
    }
  }
  EXPECT_GT(n, 1000);
  return sum / std::max(n, 1);
}

// A camera's own depth noise (a config's DepthNoise keys) is what its depth carries, and
// camera.yaml keeps it for the agents that read it; the default model needs no keys.
TEST(SequenceTest, ACamerasDepthNoiseIsRenderedAndKeptInItsConfig) {
  testing::TempDir dir;
  SyntheticSequenceOptions options = SmallOptions();
  options.frames = 1;
  options.noise = false;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("exact"), options).ok());
  options.noise = true;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("default"), options).ok());
  options.depth_sigma_0 = 0.002;
  options.depth_sigma_2 = 0.008;  // over five times the default at 2 m
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("stereo"), options).ok());
  auto exact = TumSequence::Open(dir.File("exact"), std::nullopt);
  auto kinect = TumSequence::Open(dir.File("default"), std::nullopt);
  auto stereo = TumSequence::Open(dir.File("stereo"), std::nullopt);
  ASSERT_TRUE(exact.ok() && kinect.ok() && stereo.ok());
  const double kinect_mm = MeanDepthNoiseMm(*kinect, *exact);
  const double stereo_mm = MeanDepthNoiseMm(*stereo, *exact);
  EXPECT_GT(kinect_mm, 0.5);
  EXPECT_GT(stereo_mm, 4 * kinect_mm) << kinect_mm;

  auto with_keys = ConfigFile::Open(dir.File("stereo/camera.yaml"));
  ASSERT_TRUE(with_keys.ok());
  EXPECT_NEAR(*with_keys->GetDouble("DepthNoise.sigma0", 0), 0.002, 1e-12);
  EXPECT_NEAR(*with_keys->GetDouble("DepthNoise.sigma2", 0), 0.008, 1e-12);
  auto without = ConfigFile::Open(dir.File("default/camera.yaml"));
  ASSERT_TRUE(without.ok());
  EXPECT_FALSE(without->Has("DepthNoise.sigma0"));
  EXPECT_FALSE(without->Has("DepthNoise.sigma2"));
}

TEST(SequenceTest, SurfaceSamplesLieOnTheScenePolygons) {
  testing::TempDir dir;
  SyntheticSequenceOptions options = SmallOptions();
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), options).ok());
  auto surface = ReadPly(dir.File("surface.ply"));
  ASSERT_TRUE(surface.ok());
  ASSERT_GT(surface->size(), 100u);
  ASSERT_TRUE(surface->HasNormals());
  RoomSceneOptions room = options.room;
  room.seed = options.seed;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  for (std::size_t i = 0; i < surface->size(); i += 7) {
    const Eigen::Vector3d p = surface->points[i].cast<double>();
    double best = 1e9;
    for (const auto& poly : scene.polygons()) {
      const double d = std::abs(poly.normal.dot(p) - poly.offset);
      if (d < best && poly.ContainsSt(poly.TextureCoordinates(p))) best = d;
    }
    ASSERT_LT(best, 1e-5) << "sample " << i;
  }
}

TEST(SequenceTest, PathRevisitsItsStartAfterOneLoop) {
  const LoopPathOptions options;
  const int per_loop = static_cast<int>(options.loop_period_s * 30);
  const Trajectory path = MakeLoopPath(per_loop + 1, 30.0, options);
  EXPECT_LT(TranslationDistance(path.front().T_world_cam, path.back().T_world_cam), 1e-9);
  EXPECT_LT(RotationDistance(path.front().T_world_cam, path.back().T_world_cam), 1e-9);
  // Hand-held speed: under 3 cm and 1.5 degrees per frame.
  for (std::size_t i = 1; i < path.size(); ++i) {
    EXPECT_LT(TranslationDistance(path[i - 1].T_world_cam, path[i].T_world_cam), 0.03);
    EXPECT_LT(RotationDistance(path[i - 1].T_world_cam, path[i].T_world_cam), 1.5 * M_PI / 180);
  }
}

// Frames of a sequence written with `options`, and of the same with a 20 ms exposure.
struct SharpAndBlurred {
  std::vector<RgbdFrame> sharp, blurred;
  std::vector<Pose> sharp_truth, blurred_truth;
};
void RenderSharpAndBlurred(const testing::TempDir& dir, const std::string& name,
                           const SyntheticSequenceOptions& options, SharpAndBlurred* out) {
  SyntheticSequenceOptions blurred = options;
  blurred.exposure_s = 0.02;
  for (const auto& [suffix, o, frames, truth] :
       {std::tuple{"_sharp", options, &out->sharp, &out->sharp_truth},
        std::tuple{"_blurred", blurred, &out->blurred, &out->blurred_truth}}) {
    ASSERT_TRUE(WriteSyntheticSequence(dir.File(name + suffix), o).ok());
    auto sequence = TumSequence::Open(dir.File(name + suffix), std::nullopt);
    ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
    for (std::size_t i = 0; i < sequence->size(); ++i) {
      auto frame = sequence->LoadFrame(i);
      ASSERT_TRUE(frame.ok()) << frame.status().ToString();
      frames->push_back(*frame);
      truth->push_back(*sequence->frame(i).T_world_cam_gt);
    }
  }
}

// Motion blur: a colour image exposed while the camera turns is the mean of the views over
// the exposure. Against the sharp sequence it loses contrast along the motion (fewer strong
// gradients), while the depth and the ground truth stay those of the frame's time.
TEST(SequenceTest, AnExposureBlursColourByTheMotionOnly) {
  testing::TempDir dir;
  SyntheticSequenceOptions moving = SmallOptions();
  moving.frames = 3;
  moving.width = 320;
  moving.height = 240;
  moving.path.loop_period_s = 5;  // 72 degrees a second: 1.4 degrees in a 20 ms exposure
  SharpAndBlurred r;
  RenderSharpAndBlurred(dir, "moving", moving, &r);
  ASSERT_FALSE(HasFatalFailure());
  // The mean absolute image gradient: blur lowers it.
  const auto gradient = [](const cv::Mat& bgr) {
    cv::Mat grey, gx, gy;
    cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
    grey.convertTo(grey, CV_32F);
    cv::Sobel(grey, gx, CV_32F, 1, 0);
    cv::Sobel(grey, gy, CV_32F, 0, 1);
    return cv::mean(cv::abs(gx) + cv::abs(gy))[0];
  };
  ASSERT_EQ(r.blurred.size(), 3u);
  for (std::size_t i = 0; i < 3; ++i) {
    const RgbdFrame &a = r.sharp[i], &b = r.blurred[i];
    EXPECT_EQ(cv::norm(a.depth_mm, b.depth_mm, cv::NORM_INF), 0) << i;
    EXPECT_LT(TranslationDistance(r.sharp_truth[i], r.blurred_truth[i]), 1e-9);
    EXPECT_GT(cv::norm(a.bgr, b.bgr, cv::NORM_L1) / a.bgr.total(), 3.0) << i;
    EXPECT_LT(gradient(b.bgr), 0.8 * gradient(a.bgr)) << i;
  }
  // A still camera gives the sharp image whatever the exposure.
  SyntheticSequenceOptions still = moving;
  still.frames = 1;
  still.path.loop_period_s = 1e9;
  SharpAndBlurred s;
  RenderSharpAndBlurred(dir, "still", still, &s);
  ASSERT_FALSE(HasFatalFailure());
  ASSERT_EQ(s.blurred.size(), 1u);
  EXPECT_LE(cv::norm(s.sharp[0].bgr, s.blurred[0].bgr, cv::NORM_INF), 1);
}

// A sensor whose depth comes after its colour (a Kinect v1's, 10-15 ms): the depth image is the
// view at the later time and depth.txt gives that time, while colour and ground truth stay the
// frame's. A third of a frame interval late, frame i's depth is frame 3i+1's of the same path at
// three times the frame rate.
TEST(SequenceTest, ALateDepthIsTheViewAtItsOwnTime) {
  testing::TempDir dir;
  SyntheticSequenceOptions on_time = SmallOptions();
  on_time.frames = 3;
  on_time.noise = false;
  on_time.path.loop_period_s = 5;  // 72 degrees a second: 0.8 degrees in 1/90 s
  SyntheticSequenceOptions late = on_time;
  late.depth_lag_s = 1.0 / 90;
  SyntheticSequenceOptions tripled = on_time;
  tripled.frames = 9;
  tripled.fps = 90;
  std::map<std::string, std::vector<RgbdFrame>> frames;
  for (const auto& [name, options] :
       {std::pair{"on_time", on_time}, std::pair{"late", late}, std::pair{"tripled", tripled}}) {
    ASSERT_TRUE(WriteSyntheticSequence(dir.File(name), options).ok()) << name;
    auto sequence = TumSequence::Open(dir.File(name), std::nullopt);
    ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
    for (std::size_t i = 0; i < sequence->size(); ++i) {
      auto frame = sequence->LoadFrame(i);
      ASSERT_TRUE(frame.ok()) << frame.status().ToString();
      if (std::string(name) == "late") {
        EXPECT_NEAR(sequence->frame(i).depth_timestamp - sequence->frame(i).timestamp, 1.0 / 90,
                    1e-6);
        EXPECT_NEAR(frame->depth_time_offset, 1.0 / 90, 1e-6);
      } else {
        EXPECT_EQ(frame->depth_time_offset, 0);
      }
      frames[name].push_back(*frame);
    }
  }
  ASSERT_EQ(frames["late"].size(), 3u);
  for (std::size_t i = 0; i < 3; ++i) {
    const RgbdFrame &a = frames["on_time"][i], &b = frames["late"][i];
    EXPECT_EQ(cv::norm(a.bgr, b.bgr, cv::NORM_INF), 0) << i;
    // (the same times summed in another order: a millimetre's rounding may differ)
    EXPECT_LE(cv::norm(b.depth_mm, frames["tripled"][3 * i + 1].depth_mm, cv::NORM_INF), 1) << i;
    EXPECT_GT(cv::norm(a.depth_mm, b.depth_mm, cv::NORM_L1) / a.depth_mm.total(), 5.0) << i;
  }
  SyntheticSequenceOptions too_late = SmallOptions();
  too_late.depth_lag_s = 1.0 / 60;  // half a frame at 30 Hz: which colour image is its?
  EXPECT_FALSE(too_late.Validate().ok());
}

// A rolling shutter's rows are read one after another: the image's first band of rows is the
// view of 31/64 of the readout before the frame's time, its last band the view as long after
// (32 bands, each at its middle row's time), and the depth is the frame's time's. With that
// readout set to 64/31 of 1/90 s, the bands are frames of the same path rendered at 90 Hz.
TEST(SequenceTest, ARollingShutterReadsEachBandOfRowsAtItsOwnTime) {
  testing::TempDir dir;
  SyntheticSequenceOptions global = SmallOptions();
  global.frames = 3;
  global.height = 128;  // 32 bands of 4 rows
  global.noise = false;
  global.path.loop_period_s = 5;
  SyntheticSequenceOptions rolling = global;
  rolling.rolling_shutter_s = 64.0 / 31 / 90;
  SyntheticSequenceOptions tripled = global;
  tripled.frames = 9;
  tripled.fps = 90;
  std::map<std::string, std::vector<RgbdFrame>> frames;
  for (const auto& [name, options] : {std::pair{"global", global}, std::pair{"rolling", rolling},
                                      std::pair{"tripled", tripled}}) {
    ASSERT_TRUE(WriteSyntheticSequence(dir.File(name), options).ok()) << name;
    auto sequence = TumSequence::Open(dir.File(name), std::nullopt);
    ASSERT_TRUE(sequence.ok()) << sequence.status().ToString();
    for (std::size_t i = 0; i < sequence->size(); ++i) {
      auto frame = sequence->LoadFrame(i);
      ASSERT_TRUE(frame.ok()) << frame.status().ToString();
      frames[name].push_back(*frame);
    }
  }
  auto camera_yaml = ConfigFile::Open(dir.File("rolling") + "/camera.yaml");
  ASSERT_TRUE(camera_yaml.ok());
  EXPECT_NEAR(camera_yaml->GetDouble("Camera.rollingShutterReadout", 0).value(),
              rolling.rolling_shutter_s, 1e-6);
  // Mean absolute difference of two images' rows [first, last).
  const auto differ = [](const cv::Mat& a, const cv::Mat& b, int first, int last) {
    return cv::norm(a.rowRange(first, last), b.rowRange(first, last), cv::NORM_L1) /
           static_cast<double>(a.cols * (last - first) * a.channels());
  };
  const int h = global.height, band = h / 32;
  for (std::size_t i = 1; i < 3; ++i) {
    const cv::Mat& image = frames["rolling"][i].bgr;
    // (the same times summed in another order: a few edge pixels may round the other way)
    EXPECT_LT(differ(image, frames["tripled"][3 * i - 1].bgr, 0, band), 0.5) << i;
    EXPECT_LT(differ(image, frames["tripled"][3 * i + 1].bgr, h - band, h), 0.5) << i;
    EXPECT_GT(differ(image, frames["global"][i].bgr, 0, band), 3.0) << i;
    EXPECT_GT(differ(image, frames["global"][i].bgr, h - band, h), 3.0) << i;
    EXPECT_EQ(cv::norm(frames["rolling"][i].depth_mm, frames["global"][i].depth_mm, cv::NORM_INF),
              0)
        << i;
  }
  SyntheticSequenceOptions too_slow = SmallOptions();
  too_slow.rolling_shutter_s = 0.04;  // longer than a frame at 30 Hz
  EXPECT_FALSE(too_slow.Validate().ok());
}

TEST(SequenceTest, BadOptionsAreRefused) {
  testing::TempDir dir;
  SyntheticSequenceOptions o = SmallOptions();
  o.frames = 0;
  EXPECT_FALSE(WriteSyntheticSequence(dir.path(), o).ok());
  for (double sigma : {-0.001, std::numeric_limits<double>::quiet_NaN()}) {
    SyntheticSequenceOptions noisy = SmallOptions();
    noisy.depth_sigma_2 = sigma;
    EXPECT_FALSE(noisy.Validate().ok()) << sigma;
  }
  SyntheticSequenceOptions long_exposure = SmallOptions();
  long_exposure.exposure_s = 0.05;  // longer than a frame at 30 Hz
  EXPECT_FALSE(long_exposure.Validate().ok());
  EXPECT_FALSE(ParseSyntheticSpec("frames=10,colour=2").ok());
  EXPECT_EQ(ParseSyntheticSpec("frames=10,seed=4")->seed, 4u);
}

}  // namespace
}  // namespace ccmd
