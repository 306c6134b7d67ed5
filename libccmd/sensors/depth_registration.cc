#include "libccmd/sensors/depth_registration.h"

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

namespace ccmd {

StatusOr<cv::Mat> RegisterDepth(const cv::Mat& depth_mm, const DepthToColorCalibration& calibration,
                                const PinholeCamera& color_camera) {
  const PinholeCamera& depth = calibration.depth;
  if (depth_mm.cols != depth.width || depth_mm.rows != depth.height) {
    return InvalidArgument("depth image is " + std::to_string(depth_mm.cols) + "x" +
                           std::to_string(depth_mm.rows) + ", the config's Depth block describes " +
                           std::to_string(depth.width) + "x" + std::to_string(depth.height));
  }
  return RegisterDepthToColor(depth_mm, depth, color_camera, calibration.T_color_depth);
}

namespace {

// std::ceil / std::floor / std::lround are library calls on the baseline x86-64 target (no
// SSE4.1 rounding instruction), several per depth pixel. These are exact for |x| < 2^31;
// callers keep x within +-1e9.
int CeilToInt(float x) {
  const int i = static_cast<int>(x);  // towards zero
  return i + (static_cast<float>(i) < x);
}
int FloorToInt(float x) {
  const int i = static_cast<int>(x);
  return i - (static_cast<float>(i) > x);
}
int RoundToInt(float x) { return FloorToInt(x + 0.5f); }  // halves up
// A projected coordinate kept where the conversions are exact: a point just in front of the
// camera projects arbitrarily far out, and clamped it stays out of the image (as does a NaN,
// which a distortion model pushed past its range could give).
float Clamped(float x) { return std::max(-1e9f, std::min(x, 1e9f)); }

// The single-precision constants of one depth row: the rotated ray of its pixel 0 (r0) and the
// step per column (s), the rotated half pixel (h), the translation (t) and the colour
// intrinsics.
struct RowGeometry {
  float r0x, r0y, r0z, sx, sy, sz, hx, hy, hz, tx, ty, tz, fx, fy, cx, cy;
};

// Where each depth pixel of a row (depth in metres, 0: none) lands in the colour image: the two
// corners of its footprint (a, b), its centre (q), and the centre's depth in millimetres (0:
// nothing lands). Without branches, and with the arrays restrict-qualified, so that the
// compiler does four pixels at once.
void ProjectRow(const RowGeometry g, int n, const float* __restrict depth_m, float* __restrict ax,
                float* __restrict ay, float* __restrict bx, float* __restrict by,
                float* __restrict qx, float* __restrict qy, float* __restrict z_mm) {
  constexpr float kMinZ = 1e-6f;
  for (int u = 0; u < n; ++u) {
    const float z = depth_m[u];
    const float x = z * (g.r0x + u * g.sx) + g.tx;
    const float y = z * (g.r0y + u * g.sy) + g.ty;
    const float zc = z * (g.r0z + u * g.sz) + g.tz;
    const float dx = z * g.hx, dy = z * g.hy, dz = z * g.hz;
    const float az = zc - dz, bz = zc + dz;
    // A measured depth (1 mm at least), and the whole footprint in front of the camera.
    const bool in_front = std::min(std::min(z, zc), std::min(az, bz)) > kMinZ;
    // One division per point; for a pixel that is dropped, a harmless 1.
    const float ia = 1.0f / (in_front ? az : 1.0f);
    const float ib = 1.0f / (in_front ? bz : 1.0f);
    const float ic = 1.0f / (in_front ? zc : 1.0f);
    ax[u] = g.fx * (x - dx) * ia + g.cx;
    ay[u] = g.fy * (y - dy) * ia + g.cy;
    bx[u] = g.fx * (x + dx) * ib + g.cx;
    by[u] = g.fy * (y + dy) * ib + g.cy;
    qx[u] = g.fx * x * ic + g.cx;
    qy[u] = g.fy * y * ic + g.cy;
    z_mm[u] = in_front ? zc * 1e3f : 0.0f;
  }
}

// The colour pixels whose centres lie inside each footprint, x0..x1 by y0..y1 (at least the one
// under the projected centre: a footprint smaller than a pixel may hold no centre), and the
// depth they get (0: none). Branch-free too.
void CoverRow(int n, const float* __restrict ax, const float* __restrict ay,
              const float* __restrict bx, const float* __restrict by, const float* __restrict qx,
              const float* __restrict qy, const float* __restrict z_mm, int* __restrict x0,
              int* __restrict x1, int* __restrict y0, int* __restrict y1, int* __restrict value) {
  for (int u = 0; u < n; ++u) {
    const int left = CeilToInt(Clamped(std::min(ax[u], bx[u])));
    const int right = FloorToInt(Clamped(std::max(ax[u], bx[u])));
    const int top = CeilToInt(Clamped(std::min(ay[u], by[u])));
    const int bottom = FloorToInt(Clamped(std::max(ay[u], by[u])));
    const int column = RoundToInt(Clamped(qx[u])), line = RoundToInt(Clamped(qy[u]));
    x0[u] = right < left ? column : left;
    x1[u] = right < left ? column : right;
    y0[u] = bottom < top ? line : top;
    y1[u] = bottom < top ? line : bottom;
    value[u] = ((z_mm[u] >= 0.5f) & (z_mm[u] < 65535.5f)) ? RoundToInt(z_mm[u]) : 0;
  }
}

}  // namespace

cv::Mat RegisterDepthToColor(const cv::Mat& depth_mm, const PinholeCamera& depth_camera,
                             const PinholeCamera& color_camera, const Pose& T_color_depth,
                             int max_footprint) {
  cv::Mat out(color_camera.height, color_camera.width, CV_16UC1, cv::Scalar(0));
  // A depth pixel (u, v) at depth z is z * ray(u, v) in the depth frame, and its footprint's
  // corners are z * (ray -/+ half), half = (0.5 / fx, 0.5 / fy, 0). Rotated once here, the
  // per-pixel work is a few multiply-adds: R z (ray +- half) + t. Single precision keeps the
  // projected coordinates within about 1e-4 pixel.
  const Eigen::Matrix3d R = T_color_depth.linear();
  const Eigen::Vector3f t = T_color_depth.translation().cast<float>();
  const Eigen::Vector3f half =
      (R * Eigen::Vector3d(0.5 / depth_camera.fx, 0.5 / depth_camera.fy, 0)).cast<float>();
  const Eigen::Vector3f step = (R * Eigen::Vector3d(1.0 / depth_camera.fx, 0, 0)).cast<float>();
  RowGeometry g{};
  g.sx = step.x(), g.sy = step.y(), g.sz = step.z();
  g.hx = half.x(), g.hy = half.y(), g.hz = half.z();
  g.tx = t.x(), g.ty = t.y(), g.tz = t.z();
  g.fx = static_cast<float>(color_camera.fx), g.fy = static_cast<float>(color_camera.fy);
  g.cx = static_cast<float>(color_camera.cx), g.cy = static_cast<float>(color_camera.cy);
  const bool distorted = color_camera.HasDistortion();
  const int n = depth_mm.cols, out_w = out.cols, out_h = out.rows;
  std::vector<float> depth_m(n), ax(n), ay(n), bx(n), by(n), qx(n), qy(n), z_mm(n);
  std::vector<int> x0(n), x1(n), y0(n), y1(n), value(n);
  for (int v = 0; v < depth_mm.rows; ++v) {
    const std::uint16_t* row = depth_mm.ptr<std::uint16_t>(v);
    for (int u = 0; u < n; ++u) depth_m[u] = row[u] * 1e-3f;
    const Eigen::Vector3f r0 = (R * Eigen::Vector3d(-depth_camera.cx / depth_camera.fx,
                                                    (v - depth_camera.cy) / depth_camera.fy, 1.0))
                                   .cast<float>();
    g.r0x = r0.x(), g.r0y = r0.y(), g.r0z = r0.z();
    ProjectRow(g, n, depth_m.data(), ax.data(), ay.data(), bx.data(), by.data(), qx.data(),
               qy.data(), z_mm.data());
    if (distorted) {
      const auto distort = [&](float* x, float* y) {
        const Eigen::Vector2d raw = color_camera.DistortPixel(Eigen::Vector2d(*x, *y));
        *x = static_cast<float>(raw.x());
        *y = static_cast<float>(raw.y());
      };
      for (int u = 0; u < n; ++u) {
        if (z_mm[u] == 0) continue;
        distort(&ax[u], &ay[u]);
        distort(&bx[u], &by[u]);
        distort(&qx[u], &qy[u]);
      }
    }
    CoverRow(n, ax.data(), ay.data(), bx.data(), by.data(), qx.data(), qy.data(), z_mm.data(),
             x0.data(), x1.data(), y0.data(), y1.data(), value.data());
    for (int u = 0; u < n; ++u) {
      if (value[u] == 0 || x1[u] - x0[u] >= max_footprint || y1[u] - y0[u] >= max_footprint)
        continue;
      const auto depth = static_cast<std::uint16_t>(value[u]);
      for (int y = std::max(y0[u], 0); y <= std::min(y1[u], out_h - 1); ++y) {
        std::uint16_t* target = out.ptr<std::uint16_t>(y);
        for (int x = std::max(x0[u], 0); x <= std::min(x1[u], out_w - 1); ++x) {
          if (target[x] == 0 || depth < target[x]) target[x] = depth;  // nearest wins
        }
      }
    }
  }
  return out;
}

namespace {

// The input's depth (metres) at (x, y) of a `cols` x `rows` image whose rows are `step`
// values apart: bilinear where the four pixels around have depths within 1 cm + 3 % of each
// other (one surface: the keypoints' continuity test), else the nearest pixel's; 0 outside
// the image (beyond the outer pixels' half) or where the chosen pixel has none.
inline float SampleDepth(const std::uint16_t* depth, std::size_t step, int cols, int rows, float x,
                         float y) {
  if (!(x >= -0.5f && y >= -0.5f && x < cols - 0.5f && y < rows - 0.5f)) return 0;
  x = std::min(std::max(x, 0.0f), cols - 1.0f);
  y = std::min(std::max(y, 0.0f), rows - 1.0f);
  const int x0 = std::min(static_cast<int>(x), cols - 2);
  const int y0 = std::min(static_cast<int>(y), rows - 2);
  const float ax = x - x0, ay = y - y0;
  const std::uint16_t* r0 = depth + y0 * step + x0;
  const std::uint16_t* r1 = r0 + step;
  const int d00 = r0[0], d10 = r0[1], d01 = r1[0], d11 = r1[1];
  const int lo = std::min(std::min(d00, d10), std::min(d01, d11));
  const int hi = std::max(std::max(d00, d10), std::max(d01, d11));
  if (lo > 0 && hi - lo <= 10 + 0.03f * lo) {
    const float top = d00 + ax * (d10 - d00), bottom = d01 + ax * (d11 - d01);
    return 1e-3f * (top + ay * (bottom - top));
  }
  return 1e-3f * (ay < 0.5f ? (ax < 0.5f ? d00 : d10) : (ax < 0.5f ? d01 : d11));
}

}  // namespace

cv::Mat DepthFromNearbyPose(const cv::Mat& depth_mm, const PinholeCamera& camera,
                            const Pose& T_in_out) {
  cv::Mat out(depth_mm.size(), CV_16UC1, cv::Scalar(0));
  const Eigen::Matrix3d R = T_in_out.linear();
  const Eigen::Vector3f t = T_in_out.translation().cast<float>();
  const float fx = static_cast<float>(camera.fx), fy = static_cast<float>(camera.fy);
  const float cx = static_cast<float>(camera.cx), cy = static_cast<float>(camera.cy);
  // An input pixel (x, y) at depth z_in is, in the output frame, at depth
  // z_in * (bx * x + by * y + bc) + bt: the third row of T_in_out^-1 = (R^T, -R^T t) applied
  // to its back-projection.
  const Eigen::Vector3d col = R.col(2);
  const float bx = static_cast<float>(col.x() / camera.fx);
  const float by = static_cast<float>(col.y() / camera.fy);
  const float bc = static_cast<float>(col.z() - col.x() * camera.cx / camera.fx -
                                      col.y() * camera.cy / camera.fy);
  const float bt = -col.cast<float>().dot(t);
  // R times an output pixel's ray (u, v, 1) in normalised coordinates: r0 + u * ru per row.
  const Eigen::Vector3f ru = (R.col(0) / camera.fx).cast<float>();
  const auto* data = depth_mm.ptr<std::uint16_t>(0);
  const std::size_t step_values = depth_mm.step1();
  const int cols = depth_mm.cols, rows = depth_mm.rows;
  for (int v = 0; v < rows; ++v) {
    const std::uint16_t* in = depth_mm.ptr<std::uint16_t>(v);
    std::uint16_t* target = out.ptr<std::uint16_t>(v);
    const Eigen::Vector3f r0 =
        (R * Eigen::Vector3d(-camera.cx / camera.fx, (v - camera.cy) / camera.fy, 1.0))
            .cast<float>();
    for (int u = 0; u < cols; ++u) {
      if (in[u] == 0) continue;
      const float rx = r0.x() + u * ru.x(), ry = r0.y() + u * ru.y(), rz = r0.z() + u * ru.z();
      // The first guess is the depth measured at the same pixel; a second step only where the
      // point found is far from it (a depth edge crossed), since the guess enters only through
      // the few millimetres of the camera's translation.
      float z = in[u] * 1e-3f;
      for (int pass = 0; pass < 2; ++pass) {
        const float Yz = z * rz + t.z();
        if (!(Yz > 1e-3f)) {
          z = 0;
          break;
        }
        const float inv = 1.0f / Yz;
        const float x = fx * (z * rx + t.x()) * inv + cx;
        const float y = fy * (z * ry + t.y()) * inv + cy;
        const float z_in = SampleDepth(data, step_values, cols, rows, x, y);
        if (z_in <= 0) {
          z = 0;
          break;
        }
        const float z_out = z_in * (bx * x + by * y + bc) + bt;
        const bool settled = std::fabs(z_out - z) < 0.02f * z;
        z = z_out;
        if (settled) break;
      }
      const float mm = z * 1e3f;
      if (mm >= 0.5f && mm < 65535.5f) target[u] = static_cast<std::uint16_t>(mm + 0.5f);
    }
  }
  return out;
}

double EdgeAlignmentScore(const cv::Mat& bgr, const cv::Mat& depth_mm) {
  if (bgr.empty() || bgr.size() != depth_mm.size() || depth_mm.type() != CV_16UC1) return 0;
  cv::Mat gray, gx, gy, magnitude;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  cv::GaussianBlur(gray, gray, cv::Size(5, 5), 1.5);
  cv::Sobel(gray, gx, CV_32F, 1, 0, 3);
  cv::Sobel(gray, gy, CV_32F, 0, 1, 3);
  cv::magnitude(gx, gy, magnitude);
  double sum = 0;
  long count = 0;
  for (int y = 1; y + 1 < depth_mm.rows; ++y) {
    for (int x = 1; x + 1 < depth_mm.cols; ++x) {
      const int d = depth_mm.at<std::uint16_t>(y, x);
      if (d == 0) continue;
      const int neighbours[4] = {
          depth_mm.at<std::uint16_t>(y, x - 1), depth_mm.at<std::uint16_t>(y, x + 1),
          depth_mm.at<std::uint16_t>(y - 1, x), depth_mm.at<std::uint16_t>(y + 1, x)};
      bool edge = false;
      for (int n : neighbours) edge |= n == 0 || n - d > d / 20;
      if (!edge) continue;
      sum += magnitude.at<float>(y, x);
      ++count;
    }
  }
  return count ? sum / count : 0;
}

}  // namespace ccmd
