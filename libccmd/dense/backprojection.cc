#include "libccmd/dense/backprojection.h"

#include <algorithm>
#include <cmath>
#include <optional>

#include <opencv2/core.hpp>

namespace ccmd {

Status BackProjectionOptions::Validate() const {
  if (!std::isfinite(min_depth_m) || !std::isfinite(max_depth_m) || min_depth_m < 0 ||
      max_depth_m <= min_depth_m) {
    return InvalidArgument("depth range must satisfy 0 <= min_depth_m < max_depth_m (got " +
                           std::to_string(min_depth_m) + ", " + std::to_string(max_depth_m) + ")");
  }
  if (!(max_incidence_deg > 0 && max_incidence_deg <= 90)) {
    return InvalidArgument("max_incidence_deg must be within (0, 90]");
  }
  return Status::Ok();
}

void BackProjectionOptions::Describe(OptionsWriter* out) const {
  out->Add("min_depth_m", min_depth_m);
  out->Add("max_depth_m", max_depth_m);
  out->Add("max_incidence_deg", max_incidence_deg);
}

namespace {

std::string SizeText(int width, int height) {
  return std::to_string(width) + "x" + std::to_string(height);
}

}  // namespace

Status CheckRgbdImages(const cv::Mat& depth_mm, const cv::Mat& bgr, const PinholeCamera& camera) {
  CCMD_RETURN_IF_ERROR(camera.Validate().WithContext("camera"));
  if (depth_mm.empty()) return InvalidArgument("depth image is empty");
  if (depth_mm.dims != 2 || depth_mm.type() != CV_16UC1) {
    return InvalidArgument("depth image must be CV_16UC1 millimetres (type " +
                           std::to_string(depth_mm.type()) + ")");
  }
  if (bgr.empty()) return InvalidArgument("colour image is empty");
  if (bgr.dims != 2 || bgr.type() != CV_8UC3) {
    return InvalidArgument("colour image must be CV_8UC3 BGR (type " + std::to_string(bgr.type()) +
                           ")");
  }
  if (depth_mm.cols != camera.width || depth_mm.rows != camera.height) {
    return InvalidArgument("depth image is " + SizeText(depth_mm.cols, depth_mm.rows) +
                           " but the camera is " + SizeText(camera.width, camera.height));
  }
  if (bgr.cols != depth_mm.cols || bgr.rows != depth_mm.rows) {
    return InvalidArgument("colour image is " + SizeText(bgr.cols, bgr.rows) +
                           " but the depth image is " + SizeText(depth_mm.cols, depth_mm.rows));
  }
  return Status::Ok();
}

StatusOr<CameraCloud> BackProjectKeyframe(const cv::Mat& depth_mm, const cv::Mat& bgr,
                                          const PinholeCamera& camera,
                                          const BackProjectionOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  CCMD_RETURN_IF_ERROR(CheckRgbdImages(depth_mm, bgr, camera));
  // Integer millimetre bounds: a depth d (mm) is used iff lo <= d <= hi.
  const double lo_mm = std::max(1.0, std::ceil(options.min_depth_m * 1000.0 - 1e-9));
  const double hi_mm = std::min(65535.0, std::floor(options.max_depth_m * 1000.0 + 1e-9));
  if (hi_mm < lo_mm) return CameraCloud{};
  const auto lo = static_cast<std::uint16_t>(lo_mm);
  const auto hi = static_cast<std::uint16_t>(hi_mm);
  const int width = camera.width, height = camera.height;

  // The ray (x, y, 1) of each pixel: separable without distortion, a table with it (the
  // undistorted ray of every pixel as recorded).
  std::vector<float> x_of_u(width), y_of_v(height), y_fill(width);
  for (int u = 0; u < width; ++u) x_of_u[u] = static_cast<float>((u - camera.cx) / camera.fx);
  for (int v = 0; v < height; ++v) y_of_v[v] = static_cast<float>((v - camera.cy) / camera.fy);
  std::optional<PixelRays> rays;
  if (camera.HasDistortion()) rays.emplace(camera);
  const auto ray_rows = [&](int v) -> std::pair<const float*, const float*> {
    if (rays) return {rays->x_row(v), rays->y_row(v)};
    std::fill(y_fill.begin(), y_fill.end(), y_of_v[v]);
    return {x_of_u.data(), y_fill.data()};
  };
  const auto usable = [&](std::uint16_t d) {
    return static_cast<std::uint16_t>(d - lo) <= static_cast<std::uint16_t>(hi - lo);
  };
  const bool check_incidence = options.max_incidence_deg < 90.0;
  const float cos_min = static_cast<float>(std::cos(options.max_incidence_deg * M_PI / 180.0));
  const float cos_min2 = cos_min * cos_min;

  const auto fx = static_cast<float>(camera.fx), fy = static_cast<float>(camera.fy);
  constexpr int kNone = 1 << 20;  // depth step to a neighbour that is unusable or outside

  // Pass 1: which pixels become points (counting first sizes the vectors exactly, and the
  // store keeps them for the whole run). The loop body has no branches, so that the compiler
  // can vectorise it: image borders read a zero row or the zero padding of `centre`.
  std::vector<std::uint8_t> use(static_cast<std::size_t>(width) * height, 0);
  std::vector<std::uint16_t> centre(width + 2, 0), zeros(width, 0);
  std::size_t count = 0;
  for (int v = 0; v < height; ++v) {
    const auto* d = depth_mm.ptr<std::uint16_t>(v);
    std::copy(d, d + width, centre.begin() + 1);
    const std::uint16_t* up = v > 0 ? depth_mm.ptr<std::uint16_t>(v - 1) : zeros.data();
    const std::uint16_t* down = v + 1 < height ? depth_mm.ptr<std::uint16_t>(v + 1) : zeros.data();
    const std::uint16_t* row = centre.data();
    std::uint8_t* row_use = use.data() + static_cast<std::size_t>(v) * width;
    const auto [xs, ys] = ray_rows(v);
    for (int u = 0; u < width; ++u) {
      const int c = row[u + 1];
      const auto step = [&](int other) {
        return usable(static_cast<std::uint16_t>(other)) ? other - c : kNone;
      };
      const int left = step(row[u]), right = step(row[u + 2]);
      const int above = step(up[u]), below = step(down[u]);
      // Per axis, the step (per pixel, towards increasing index) to the neighbour closer in
      // depth: the same surface when the pixel is on an edge.
      const int du = std::abs(left) <= std::abs(right) ? -left : right;
      const int dv = std::abs(above) <= std::abs(below) ? -above : below;
      // For X = z (x, y, 1) with x = (u - cx) / fx, y = (v - cy) / fy, the normal
      // dX/du x dX/dv is parallel to n = (-gu, -gv, gu x + gv y + z) with gu = fx dz/du and
      // gv = fy dz/dv, and n . (x, y, 1) = z: cos(incidence) = z / (|n| |(x, y, 1)|).
      // With distortion (x, y) is the pixel's undistorted ray and fx, fy stand for the local
      // scale, which distortion changes by a few percent: good enough for a 75 degree cut.
      const float x = xs[u], y = ys[u], z = static_cast<float>(c);
      const float gu = fx * static_cast<float>(du), gv = fy * static_cast<float>(dv);
      const float nz = gu * x + gv * y + z;
      const float n2 = gu * gu + gv * gv + nz * nz;
      const bool measurable = (std::abs(du) < kNone) & (std::abs(dv) < kNone);
      const bool oblique =
          check_incidence & measurable & (z * z < cos_min2 * n2 * (x * x + y * y + 1.0f));
      row_use[u] = static_cast<std::uint8_t>(usable(static_cast<std::uint16_t>(c)) & !oblique);
      count += row_use[u];
    }
  }
  CameraCloud cloud;
  cloud.points.resize(count);
  cloud.colors.resize(count);
  std::size_t i = 0;
  for (int v = 0; v < height; ++v) {
    const auto* d = depth_mm.ptr<std::uint16_t>(v);
    const auto* c = bgr.ptr<std::uint8_t>(v);
    const std::uint8_t* row_use = use.data() + static_cast<std::size_t>(v) * width;
    const auto [xs, ys] = ray_rows(v);
    for (int u = 0; u < width; ++u) {
      if (!row_use[u]) continue;
      const float z = d[u] * 0.001f;
      cloud.points[i] = Eigen::Vector3f(xs[u] * z, ys[u] * z, z);
      cloud.colors[i] = {c[3 * u + 2], c[3 * u + 1], c[3 * u]};
      ++i;
    }
  }
  return cloud;
}

}  // namespace ccmd
