#pragma once

// CPU renderer for SyntheticScene: scanline rasterisation of the convex polygons with a
// z-buffer, depth from the exact ray-plane intersection, trilinear mip-mapped textures,
// Lambertian light, and a sensor model for depth (depth-dependent Gaussian noise, range
// limits, invalid pixels at grazing angles and depth edges, random dropouts, quantisation)
// and colour (Gaussian noise, slight optical blur).

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/synth/scene.h"
#include "libccmd/util/options_writer.h"

namespace ccmd {

struct DepthSensorModel {
  // sigma(z) = sigma_0 + sigma_2 * z^2 (metres), the quadratic growth of structured-light
  // and stereo sensors (Khoshelham and Elberink 2012 measured ~1.5 mm at 1 m for Kinect v1).
  double sigma_0 = 0.0005;
  double sigma_2 = 0.0015;
  double min_range = 0.3;
  double max_range = 6.0;
  double grazing_cos_invalid = 0.12;  // below: always invalid
  double grazing_cos_valid = 0.3;     // above: always valid; linear ramp in between
  double edge_dropout = 0.35;         // chance to lose a pixel at a depth discontinuity
  double edge_jump = 0.05;            // relative depth jump that counts as a discontinuity
  double random_dropout = 0.003;
  double quantum_m = 0.001;  // sensor output resolution (1 mm)

  void Describe(OptionsWriter* out) const;
};

struct RenderOptions {
  bool noise = true;  // false: exact depth and colour (for ground truth and tests)
  DepthSensorModel depth;
  double color_sigma = 2.0;  // grey levels
  double blur_sigma = 0.5;   // pixels; 0 disables
  std::uint64_t seed = 0;    // noise seed (mix in the frame index)
  int threads = 1;           // bands of rows rendered in parallel (same image for any count)
  // Only rows [row_first, row_last] are needed (-1: to the last row); the others may be left
  // blank. A rolling shutter renders each band of rows from its own pose.
  int row_first = 0;
  int row_last = -1;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct RenderedFrame {
  cv::Mat bgr;         // CV_8UC3
  cv::Mat depth_mm;    // CV_16UC1, sensor model applied
  cv::Mat depth_true;  // CV_32FC1 metres, exact z of the visible surface, 0 where none
  cv::Mat polygon;     // CV_32SC1 index of the visible polygon, -1 where none
};

// Per polygon, one flag per cell of the grid of SyntheticScene::VisibilityGrid(spacing):
// set when the cell was seen with valid depth. Used to build the ground-truth surface.
struct VisibilityMarks {
  double spacing = 0.01;
  std::vector<std::vector<std::uint8_t>> cells;
  void Init(const SyntheticScene& scene, double cell_spacing);
  void Merge(const VisibilityMarks& other);
};

// Renders the scene from T_world_cam. `marks`, if given (and initialised), is updated.
RenderedFrame RenderFrame(const SyntheticScene& scene, const PinholeCamera& camera,
                          const Pose& T_world_cam, const RenderOptions& options,
                          VisibilityMarks* marks = nullptr);

}  // namespace ccmd
