#include "libccmd/synth/renderer.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <thread>

#include "libccmd/util/random.h"

namespace ccmd {

void DepthSensorModel::Describe(OptionsWriter* out) const {
  out->Add("sigma_0", sigma_0);
  out->Add("sigma_2", sigma_2);
  out->Add("min_range", min_range);
  out->Add("max_range", max_range);
  out->Add("grazing_cos_invalid", grazing_cos_invalid);
  out->Add("grazing_cos_valid", grazing_cos_valid);
  out->Add("edge_dropout", edge_dropout);
  out->Add("edge_jump", edge_jump);
  out->Add("random_dropout", random_dropout);
  out->Add("quantum_m", quantum_m);
}

Status RenderOptions::Validate() const {
  if (!(depth.min_range > 0 && depth.max_range > depth.min_range)) {
    return InvalidArgument("depth range must satisfy 0 < min < max");
  }
  if (!(color_sigma >= 0) || !(blur_sigma >= 0))
    return InvalidArgument("noise sigmas must be >= 0");
  if (threads < 1) return InvalidArgument("render threads must be at least 1");
  if (row_first < 0 || row_last < -1 || (row_last >= 0 && row_last < row_first))
    return InvalidArgument("rows to render must satisfy 0 <= first <= last (last -1: all)");
  return Status::Ok();
}

void RenderOptions::Describe(OptionsWriter* out) const {
  out->Add("noise", noise);
  out->Nested("depth", depth);
  out->Add("color_sigma", color_sigma);
  out->Add("blur_sigma", blur_sigma);
  out->Add("seed", seed);
  out->Add("threads", threads);
  out->Add("row_first", row_first);
  out->Add("row_last", row_last);
}

void VisibilityMarks::Init(const SyntheticScene& scene, double cell_spacing) {
  spacing = cell_spacing;
  cells.assign(scene.polygons().size(), {});
  for (std::size_t k = 0; k < cells.size(); ++k) {
    const auto grid = scene.VisibilityGrid(static_cast<int>(k), spacing);
    cells[k].assign(static_cast<std::size_t>(grid.cells_s) * grid.cells_t, 0);
  }
}

void VisibilityMarks::Merge(const VisibilityMarks& other) {
  for (std::size_t k = 0; k < cells.size() && k < other.cells.size(); ++k) {
    for (std::size_t i = 0; i < cells[k].size(); ++i) cells[k][i] |= other.cells[k][i];
  }
}

namespace {

// A table of standard normal samples indexed by random 16-bit numbers: per-pixel noise at
// a few nanoseconds, identical on every platform.
const std::vector<float>& GaussianTable() {
  static const std::vector<float> table = [] {
    std::vector<float> t(1 << 16);
    Rng rng(0x6a055);
    for (float& v : t) v = static_cast<float>(rng.Normal());
    return t;
  }();
  return table;
}

// Sutherland-Hodgman clip of a polygon against z >= near.
std::vector<Eigen::Vector3d> ClipNear(const std::vector<Eigen::Vector3d>& in, double near) {
  std::vector<Eigen::Vector3d> out;
  for (std::size_t i = 0; i < in.size(); ++i) {
    const Eigen::Vector3d& a = in[i];
    const Eigen::Vector3d& b = in[(i + 1) % in.size()];
    const bool a_in = a.z() >= near, b_in = b.z() >= near;
    if (a_in) out.push_back(a);
    if (a_in != b_in) {
      const double t = (near - a.z()) / (b.z() - a.z());
      out.push_back(a + t * (b - a));
    }
  }
  return out;
}

// log2 to about 0.01 (enough to pick mip levels), several times faster than std::log2.
inline float FastLog2(float x) {
  int exponent = 0;
  const float m = std::frexp(x, &exponent) * 2.0f - 1.0f;  // mantissa - 1, in [0, 1)
  return static_cast<float>(exponent - 1) + m * (1.3465f - 0.3465f * m);
}

// Bilinear texture lookup at continuous texel coordinates (u, v), clamped to the edge.
inline void SampleBilinear(const cv::Mat& level, float u, float v, float out[3]) {
  u = std::min(std::max(u, 0.0f), static_cast<float>(level.cols) - 1.001f);
  v = std::min(std::max(v, 0.0f), static_cast<float>(level.rows) - 1.001f);
  const int x = static_cast<int>(u), y = static_cast<int>(v);
  const float fx = u - x, fy = v - y;
  const uchar* r0 = level.ptr<uchar>(y) + 3 * x;
  const uchar* r1 = r0 + level.step[0];
  const float w00 = (1 - fx) * (1 - fy), w01 = fx * (1 - fy), w10 = (1 - fx) * fy, w11 = fx * fy;
  for (int c = 0; c < 3; ++c) {
    out[c] = w00 * r0[c] + w01 * r0[3 + c] + w10 * r1[c] + w11 * r1[3 + c];
  }
}

}  // namespace

namespace {

// Everything about one polygon that the per-pixel passes need, in camera coordinates.
struct FramePolygon {
  Eigen::Vector3d n;  // plane n . x = d (front side towards the camera: d < 0)
  double d = 0;
  std::vector<Eigen::Vector2d> uv;  // clipped, projected outline
  int row_first = 0, row_last = -1;
  // Shading data in float.
  Eigen::Vector3f nf, origin, axis_s, axis_t;
  const MipTexture* texture = nullptr;
  float max_level = 0;
};

// Runs fn(first_row, last_row) over `threads` bands of rows and waits for all.
template <typename Fn>
void ForRowBands(int rows, int threads, Fn&& fn) {
  threads = std::clamp(threads, 1, 16);
  if (threads == 1) {
    fn(0, rows - 1);
    return;
  }
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) {
    const int first = rows * t / threads, last = rows * (t + 1) / threads - 1;
    pool.emplace_back([&fn, first, last] { fn(first, last); });
  }
  for (auto& th : pool) th.join();
}

// Polygons in camera coordinates, clipped to the near plane and projected with `camera`
// (a pinhole camera: the rasterisation grid).
std::vector<FramePolygon> PreparePolygons(const SyntheticScene& scene, const PinholeCamera& camera,
                                          const Pose& T_cam_world, double near) {
  const Eigen::Matrix3d R_cw = T_cam_world.linear();
  const auto& polygons = scene.polygons();
  const auto& textures = scene.textures();
  std::vector<FramePolygon> frame_polygons(polygons.size());
  for (std::size_t k = 0; k < polygons.size(); ++k) {
    const ScenePolygon& p = polygons[k];
    FramePolygon& c = frame_polygons[k];
    c.n = R_cw * p.normal;
    const Eigen::Vector3d origin = T_cam_world * p.origin;
    c.d = c.n.dot(origin);
    c.nf = c.n.cast<float>();
    c.origin = origin.cast<float>();
    c.axis_s = (R_cw * p.axis_s).cast<float>();
    c.axis_t = (R_cw * p.axis_t).cast<float>();
    c.texture = &textures[p.texture];
    c.max_level = static_cast<float>(c.texture->levels.size() - 1);
    if (c.d >= -1e-9) continue;  // seen from behind or edge-on
    std::vector<Eigen::Vector3d> v;
    v.reserve(p.vertices.size());
    for (const auto& x : p.vertices) v.push_back(T_cam_world * x);
    v = ClipNear(v, near);
    if (v.size() < 3) continue;
    double vmin = 1e300, vmax = -1e300;
    for (const auto& x : v) {
      c.uv.push_back(camera.Project(x));
      vmin = std::min(vmin, c.uv.back().y());
      vmax = std::max(vmax, c.uv.back().y());
    }
    c.row_first = std::max(0, static_cast<int>(std::ceil(vmin)));
    c.row_last = std::min(camera.height - 1, static_cast<int>(std::floor(vmax)));
  }
  return frame_polygons;
}

// Z-buffer rasterisation of rows [band_first, band_last] of `camera`'s pinhole image:
// the nearest polygon's index and depth per pixel.
void RasterizeBand(const std::vector<FramePolygon>& frame_polygons, const PinholeCamera& camera,
                   double near, int band_first, int band_last, cv::Mat* zbuf, cv::Mat* ids) {
  const int W = camera.width;
  for (std::size_t k = 0; k < frame_polygons.size(); ++k) {
    const FramePolygon& c = frame_polygons[k];
    const int y0 = std::max(c.row_first, band_first), y1 = std::min(c.row_last, band_last);
    const double a = c.n.x() / camera.fx;
    for (int y = y0; y <= y1; ++y) {
      double xl = 1e300, xr = -1e300;
      for (std::size_t i = 0; i < c.uv.size(); ++i) {
        const Eigen::Vector2d& p0 = c.uv[i];
        const Eigen::Vector2d& p1 = c.uv[(i + 1) % c.uv.size()];
        const double lo = std::min(p0.y(), p1.y()), hi = std::max(p0.y(), p1.y());
        if (y < lo || y > hi) continue;
        if (hi - lo < 1e-12) {
          xl = std::min({xl, p0.x(), p1.x()});
          xr = std::max({xr, p0.x(), p1.x()});
          continue;
        }
        const double x = p0.x() + (y - p0.y()) * (p1.x() - p0.x()) / (p1.y() - p0.y());
        xl = std::min(xl, x);
        xr = std::max(xr, x);
      }
      const int x0 = std::max(0, static_cast<int>(std::ceil(xl)));
      const int x1 = std::min(W - 1, static_cast<int>(std::floor(xr)));
      const double ry = (y - camera.cy) / camera.fy;
      const double b = -c.n.x() * camera.cx / camera.fx + c.n.y() * ry + c.n.z();
      float* zrow = zbuf->ptr<float>(y);
      int* idrow = ids->ptr<int>(y);
      for (int x = x0; x <= x1; ++x) {
        // z = d / den with d < 0 and den < 0: test z < zrow[x] as d > zrow[x] * den, keeping
        // the division out of the overdrawn loop.
        const double den = a * x + b;
        if (den >= -1e-12 || !(c.d > zrow[x] * den)) continue;
        const double z = c.d / den;
        if (z < near) continue;
        zrow[x] = static_cast<float>(z);
        idrow[x] = static_cast<int>(k);
      }
    }
  }
}

// The pinhole grid that covers every undistorted ray of a distorted camera's image: same
// focal lengths, the principal point moved so that the grid starts at the smallest ideal
// pixel (with a margin of two pixels).
PinholeCamera CoveringPinhole(const PinholeCamera& camera) {
  double u_min = 1e300, u_max = -1e300, v_min = 1e300, v_max = -1e300;
  auto extend = [&](double u, double v) {
    const Eigen::Vector2d ideal = camera.UndistortPixel({u, v});
    u_min = std::min(u_min, ideal.x());
    u_max = std::max(u_max, ideal.x());
    v_min = std::min(v_min, ideal.y());
    v_max = std::max(v_max, ideal.y());
  };
  for (int u = 0; u < camera.width; ++u) extend(u, 0), extend(u, camera.height - 1);
  for (int v = 0; v < camera.height; ++v) extend(0, v), extend(camera.width - 1, v);
  PinholeCamera grid = camera;
  grid.distortion = {0, 0, 0, 0, 0};
  const double left = std::floor(u_min) - 2, top = std::floor(v_min) - 2;
  grid.cx = camera.cx - left;
  grid.cy = camera.cy - top;
  grid.width = static_cast<int>(std::ceil(u_max) - left) + 3;
  grid.height = static_cast<int>(std::ceil(v_max) - top) + 3;
  return grid;
}

// Rows of the viewing rays (x, y, 1) of the output image: computed for a pinhole camera as
// the rasteriser does, from a PixelRays table with distortion.
class OutputRays {
 public:
  explicit OutputRays(const PinholeCamera& camera) : camera_(camera), ray_x_(camera.width) {
    for (int x = 0; x < camera.width; ++x)
      ray_x_[x] = static_cast<float>((x - camera.cx) / camera.fx);
    if (camera.HasDistortion()) table_.emplace(camera, /*exact=*/true);
  }
  // Fills `y_fill` (width values) when the rows are separable.
  std::pair<const float*, const float*> Row(int y, std::vector<float>* y_fill) const {
    if (table_) return {table_->x_row(y), table_->y_row(y)};
    y_fill->assign(camera_.width, static_cast<float>((y - camera_.cy) / camera_.fy));
    return {ray_x_.data(), y_fill->data()};
  }

 private:
  const PinholeCamera& camera_;
  std::vector<float> ray_x_;
  std::optional<PixelRays> table_;
};

// With distortion: each output pixel takes the polygon seen at its ray's cell of the covering
// pinhole grid, and the exact depth of that polygon along the ray.
void ResampleBand(const std::vector<FramePolygon>& frame_polygons, const PinholeCamera& grid,
                  const cv::Mat& grid_ids, const OutputRays& rays, double near, int band_first,
                  int band_last, cv::Mat* zbuf, cv::Mat* ids) {
  std::vector<float> y_fill;
  for (int y = band_first; y <= band_last; ++y) {
    const auto [xs, ys] = rays.Row(y, &y_fill);
    float* zrow = zbuf->ptr<float>(y);
    int* idrow = ids->ptr<int>(y);
    for (int x = 0; x < zbuf->cols; ++x) {
      const int gu = static_cast<int>(std::lround(grid.fx * xs[x] + grid.cx));
      const int gv = static_cast<int>(std::lround(grid.fy * ys[x] + grid.cy));
      if (gu < 0 || gv < 0 || gu >= grid.width || gv >= grid.height) continue;
      const int k = grid_ids.at<int>(gv, gu);
      if (k < 0) continue;
      const FramePolygon& c = frame_polygons[k];
      const double den = c.n.x() * xs[x] + c.n.y() * ys[x] + c.n.z();
      if (den >= -1e-12) continue;
      const double z = c.d / den;
      if (z < near) continue;
      zrow[x] = static_cast<float>(z);
      idrow[x] = k;
    }
  }
}

struct ShadeInputs {
  const SyntheticScene* scene = nullptr;
  const std::vector<FramePolygon>* polygons = nullptr;
  const OutputRays* rays = nullptr;
  Eigen::Vector3f light;
  float inv_texel = 0, inv_f = 0;
  const DepthSensorModel* depth_model = nullptr;
  VisibilityMarks* marks = nullptr;
};

// Texture, light and visibility marks for rows [band_first, band_last] of the output image.
void ShadeBand(const ShadeInputs& in, const cv::Mat& zbuf, const cv::Mat& ids, int band_first,
               int band_last, RenderedFrame* out, cv::Mat* cos_angle, cv::Mat* shaded) {
  const DepthSensorModel& dm = *in.depth_model;
  std::vector<float> y_fill;
  for (int y = band_first; y <= band_last; ++y) {
    const int* idrow = ids.ptr<int>(y);
    const float* zrow = zbuf.ptr<float>(y);
    float* true_row = out->depth_true.ptr<float>(y);
    float* cos_row = cos_angle->ptr<float>(y);
    uchar* color_row = shaded->ptr<uchar>(y);
    const auto [xs, ys] = in.rays->Row(y, &y_fill);
    for (int x = 0; x < zbuf.cols; ++x) {
      const int k = idrow[x];
      if (k < 0) continue;
      const FramePolygon& c = (*in.polygons)[k];
      const float z = zrow[x];
      const Eigen::Vector3f ray(xs[x], ys[x], 1.0f);
      const Eigen::Vector3f P = z * ray;
      const float ray_norm = ray.norm();
      const float cos_t = std::abs(c.nf.dot(ray)) / ray_norm;
      true_row[x] = z;
      cos_row[x] = cos_t;
      const Eigen::Vector3f rel = P - c.origin;
      const float s = rel.dot(c.axis_s), t = rel.dot(c.axis_t);

      // Trilinear mip-mapping: the texture level whose texel matches the pixel footprint.
      const float footprint = z * ray_norm * in.inv_f / std::max(cos_t, 0.2f);
      const float level =
          std::min(std::max(FastLog2(footprint * in.inv_texel + 1e-9f), 0.0f), c.max_level);
      const int l0 = static_cast<int>(level);
      const float w1 = level - l0;
      const float scale0 = in.inv_texel / static_cast<float>(1 << l0);
      float color[3];
      SampleBilinear(c.texture->levels[l0], s * scale0 - 0.5f, t * scale0 - 0.5f, color);
      if (w1 > 0.02f) {
        float coarse[3];
        SampleBilinear(c.texture->levels[l0 + 1], s * scale0 * 0.5f - 0.5f,
                       t * scale0 * 0.5f - 0.5f, coarse);
        for (int ch = 0; ch < 3; ++ch) color[ch] += w1 * (coarse[ch] - color[ch]);
      }
      // Lambertian point light: view-independent, like a matte indoor scene.
      const Eigen::Vector3f to_light = in.light - P;
      const float dist2 = to_light.squaredNorm();
      const float diffuse = std::max(0.0f, c.nf.dot(to_light)) / std::sqrt(dist2);
      const float intensity = 0.55f + 0.65f * diffuse / (1.0f + 0.05f * dist2);
      for (int ch = 0; ch < 3; ++ch) {
        const float v = color[ch] * intensity + 0.5f;
        color_row[3 * x + ch] = static_cast<uchar>(v > 255.0f ? 255.0f : v);
      }

      // Cells count as seen wherever the sensor can return depth (even only sometimes).
      if (in.marks && z >= dm.min_range && z <= dm.max_range && cos_t >= dm.grazing_cos_invalid) {
        const auto grid = in.scene->VisibilityGrid(k, in.marks->spacing);
        const int cs = static_cast<int>(s / in.marks->spacing);
        const int ct = static_cast<int>(t / in.marks->spacing);
        if (cs >= 0 && ct >= 0 && cs < grid.cells_s && ct < grid.cells_t) {
          in.marks->cells[k][static_cast<std::size_t>(ct) * grid.cells_s + cs] = 1;
        }
      }
    }
  }
}

}  // namespace

RenderedFrame RenderFrame(const SyntheticScene& scene, const PinholeCamera& camera,
                          const Pose& T_world_cam, const RenderOptions& options,
                          VisibilityMarks* marks) {
  const int W = camera.width, H = camera.height;
  const Pose T_cam_world = T_world_cam.inverse();
  constexpr double kNear = 0.02;
  // Marks are written without locks: keep one thread when they are requested.
  const int threads = marks ? 1 : options.threads;

  // A distorted camera is rasterised on the pinhole grid that covers its rays, then
  // resampled along each output pixel's ray; a pinhole camera is rasterised directly.
  const bool distorted = camera.HasDistortion();
  const PinholeCamera grid = distorted ? CoveringPinhole(camera) : camera;
  const std::vector<FramePolygon> frame_polygons = PreparePolygons(scene, grid, T_cam_world, kNear);
  const OutputRays rays(camera);

  RenderedFrame out;
  out.depth_true = cv::Mat(H, W, CV_32FC1, cv::Scalar(0));
  out.polygon = cv::Mat(H, W, CV_32SC1, cv::Scalar(-1));
  out.depth_mm = cv::Mat(H, W, CV_16UC1, cv::Scalar(0));
  const float infinity = std::numeric_limits<float>::infinity();
  cv::Mat zbuf(H, W, CV_32FC1, cv::Scalar(infinity));
  cv::Mat cos_angle(H, W, CV_32FC1, cv::Scalar(0));
  cv::Mat shaded(H, W, CV_8UC3, cv::Scalar(0, 0, 0));
  cv::Mat grid_z, grid_ids;
  if (distorted) {
    grid_z = cv::Mat(grid.height, grid.width, CV_32FC1, cv::Scalar(infinity));
    grid_ids = cv::Mat(grid.height, grid.width, CV_32SC1, cv::Scalar(-1));
    ForRowBands(grid.height, threads, [&](int first, int last) {
      RasterizeBand(frame_polygons, grid, kNear, first, last, &grid_z, &grid_ids);
    });
  }
  ShadeInputs shade;
  shade.scene = &scene;
  shade.polygons = &frame_polygons;
  shade.rays = &rays;
  shade.light = (T_cam_world * scene.light()).cast<float>();
  shade.inv_texel = static_cast<float>(1.0 / scene.texel_m());
  shade.inv_f = static_cast<float>(2.0 / (std::abs(camera.fx) + std::abs(camera.fy)));
  shade.depth_model = &options.depth;
  shade.marks = marks;
  const DepthSensorModel& dm = options.depth;
  // The rows rendered: those asked for and the neighbours their depth edges and optical blur
  // read. Noise is seeded per row, so the rows asked for are those of the whole image.
  const int margin = 2 + static_cast<int>(std::ceil(4 * options.blur_sigma));
  const int y_first = std::clamp(options.row_first - margin, 0, H - 1);
  const int y_last = options.row_last < 0 ? H - 1 : std::min(H - 1, options.row_last + margin);
  const auto for_rows = [&](auto&& fn) {
    ForRowBands(y_last - y_first + 1, threads,
                [&](int first, int last) { fn(first + y_first, last + y_first); });
  };

  // Pass 1: visible polygon and depth per pixel, then shading, by bands of rows.
  for_rows([&](int band_first, int band_last) {
    if (distorted) {
      ResampleBand(frame_polygons, grid, grid_ids, rays, kNear, band_first, band_last, &zbuf,
                   &out.polygon);
    } else {
      RasterizeBand(frame_polygons, camera, kNear, band_first, band_last, &zbuf, &out.polygon);
    }
    ShadeBand(shade, zbuf, out.polygon, band_first, band_last, &out, &cos_angle, &shaded);
  });

  // Pass 2: the depth sensor model (needs neighbouring rows' true depth for the edge test).
  // Random numbers are seeded per row, so the result does not depend on the thread count.
  const std::vector<float>& gauss = GaussianTable();
  for_rows([&](int band_first, int band_last) {
    for (int y = band_first; y <= band_last; ++y) {
      Rng rng(MixSeed(options.seed, static_cast<std::uint64_t>(y)));
      const float* zrow = out.depth_true.ptr<float>(y);
      const float* cos_row = cos_angle.ptr<float>(y);
      std::uint16_t* mm_row = out.depth_mm.ptr<std::uint16_t>(y);
      for (int x = 0; x < W; ++x) {
        const double z = zrow[x];
        if (z <= 0 || z < dm.min_range || z > dm.max_range) continue;
        double measured = z;
        if (options.noise) {
          const double cos_t = cos_row[x];
          if (cos_t < dm.grazing_cos_invalid) continue;
          if (cos_t < dm.grazing_cos_valid &&
              rng.Uniform() > (cos_t - dm.grazing_cos_invalid) /
                                  (dm.grazing_cos_valid - dm.grazing_cos_invalid)) {
            continue;
          }
          if (rng.Uniform() < dm.random_dropout) continue;
          bool edge = false;
          const int nx[4] = {x - 1, x + 1, x, x};
          const int ny[4] = {y, y, y - 1, y + 1};
          for (int i = 0; i < 4 && !edge; ++i) {
            if (nx[i] < 0 || ny[i] < 0 || nx[i] >= W || ny[i] >= H) continue;
            const double zn = out.depth_true.at<float>(ny[i], nx[i]);
            edge = zn <= 0 || std::abs(zn - z) > dm.edge_jump * z;
          }
          if (edge && rng.Uniform() < dm.edge_dropout) continue;
          const double sigma = dm.sigma_0 + dm.sigma_2 * z * z;
          measured = z + sigma * gauss[rng.Next() >> 48];
          if (dm.quantum_m > 0) measured = std::nearbyint(measured / dm.quantum_m) * dm.quantum_m;
        }
        const double mm = std::nearbyint(measured * 1000.0);
        mm_row[x] = static_cast<std::uint16_t>(std::clamp(mm, 1.0, 65535.0));
      }
    }
  });

  // Colour: slight optical blur, then sensor noise.
  if (options.noise && options.blur_sigma > 0) {
    cv::GaussianBlur(shaded, out.bgr, cv::Size(0, 0), options.blur_sigma);
  } else {
    out.bgr = shaded;
  }
  if (options.noise && options.color_sigma > 0) {
    const float sigma = static_cast<float>(options.color_sigma);
    for_rows([&](int band_first, int band_last) {
      for (int y = band_first; y <= band_last; ++y) {
        Rng rng(MixSeed(options.seed ^ 0xc0105, static_cast<std::uint64_t>(y)));
        uchar* row = out.bgr.ptr<uchar>(y);
        for (int i = 0; i < W * 3; ++i) {
          row[i] = cv::saturate_cast<uchar>(row[i] + sigma * gauss[rng.Next() >> 48]);
        }
      }
    });
  }
  return out;
}

}  // namespace ccmd
