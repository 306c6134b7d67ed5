#include "libccmd/geometry/camera.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <cstdio>

namespace ccmd {

void PinholeCamera::Describe(OptionsWriter* out) const {
  out->Add("width", width);
  out->Add("height", height);
  out->Add("fx", fx);
  out->Add("fy", fy);
  out->Add("cx", cx);
  out->Add("cy", cy);
  out->Add("fps", fps);
  out->Add("depth_map_factor", depth_map_factor);
  out->Add("bf", bf);
  out->Add("far_depth_m", far_depth_m);
  out->Add("distortion", std::vector<double>(distortion.begin(), distortion.end()));
  out->Add("rgb", rgb);
}
namespace {

// The distortion model and its Jacobian at normalised coordinates (x, y).
struct DistortionAt {
  Eigen::Vector2d value;
  Eigen::Matrix2d jacobian;
};

DistortionAt EvaluateDistortion(const std::array<double, 5>& d, const Eigen::Vector2d& xy) {
  const double k1 = d[0], k2 = d[1], p1 = d[2], p2 = d[3], k3 = d[4];
  const double x = xy.x(), y = xy.y();
  const double r2 = x * x + y * y;
  const double radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
  const double dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2);  // d radial / d r2
  DistortionAt out;
  out.value = {x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
               y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y};
  out.jacobian << radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x,
      2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y,  //
      2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y,
      radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x;
  return out;
}

// Newton's method from `start`; false if it does not converge (the model folds or is
// singular there).
bool SolveUndistort(const std::array<double, 5>& d, const Eigen::Vector2d& target,
                    Eigen::Vector2d* xy) {
  for (int i = 0; i < 30; ++i) {
    const DistortionAt at = EvaluateDistortion(d, *xy);
    const Eigen::Vector2d residual = at.value - target;
    if (residual.squaredNorm() < 1e-26) return true;
    const double det = at.jacobian.determinant();
    if (!(std::fabs(det) > 1e-12)) return false;
    *xy -= at.jacobian.inverse() * residual;
    if (!xy->allFinite()) return false;
  }
  return (EvaluateDistortion(d, *xy).value - target).squaredNorm() < 1e-20;
}

}  // namespace

Status PinholeCamera::Validate() const {
  auto fail = [](const char* reason) { return InvalidArgument(reason); };
  if (width <= 0 || height <= 0) return fail("image size must be positive");
  if (width > 16384 || height > 16384) return fail("image size above 16384");
  // fy may be negative: ICL-NUIM's TUM-format release flips the y axis that way.
  if (!(std::fabs(fx) > 0) || !(std::fabs(fy) > 0) || !std::isfinite(fx) || !std::isfinite(fy)) {
    return fail("focal lengths must be finite and non-zero");
  }
  if (!std::isfinite(cx) || !std::isfinite(cy)) return fail("principal point must be finite");
  for (const double k : distortion) {
    if (!std::isfinite(k)) return fail("distortion coefficients must be finite");
  }
  if (!(depth_map_factor > 0) || !std::isfinite(depth_map_factor)) {
    return fail("DepthMapFactor must be positive and finite");
  }
  if (!(fps > 0) || !std::isfinite(fps)) return fail("fps must be positive and finite");
  return Status::Ok();
}

Status PinholeCamera::ValidateInvertible() const {
  CCMD_RETURN_IF_ERROR(Validate());
  if (!HasDistortion()) return Status::Ok();
  // Every pixel on a 16-pixel grid (borders included) must undistort, and the model must
  // keep its orientation there: a fold inside the image would make two rays share a pixel.
  for (int v = 0;; v = std::min(v + 16, height - 1)) {
    for (int u = 0;; u = std::min(u + 16, width - 1)) {
      const Eigen::Vector2d distorted((u - cx) / fx, (v - cy) / fy);
      Eigen::Vector2d xy = distorted;
      if (!SolveUndistort(distortion, distorted, &xy) ||
          !(EvaluateDistortion(distortion, xy).jacobian.determinant() > 0)) {
        return InvalidArgument("distortion coefficients cannot be inverted at pixel (" +
                               std::to_string(u) + ", " + std::to_string(v) +
                               "): the model folds inside the image");
      }
      if (u == width - 1) break;
    }
    if (v == height - 1) break;
  }
  return Status::Ok();
}

Eigen::Vector2d PinholeCamera::Distort(const Eigen::Vector2d& xy) const {
  return EvaluateDistortion(distortion, xy).value;
}

Eigen::Vector2d PinholeCamera::Undistort(const Eigen::Vector2d& xy_distorted) const {
  Eigen::Vector2d xy = xy_distorted;
  if (!HasDistortion()) return xy;
  // Outside the invertible region (ValidateInvertible) there is no right answer: keep the input.
  if (!SolveUndistort(distortion, xy_distorted, &xy)) return xy_distorted;
  return xy;
}

Eigen::Vector2d PinholeCamera::UndistortPixel(const Eigen::Vector2d& raw) const {
  if (!HasDistortion()) return raw;
  const Eigen::Vector2d xy = Undistort({(raw.x() - cx) / fx, (raw.y() - cy) / fy});
  return {fx * xy.x() + cx, fy * xy.y() + cy};
}

Eigen::Vector2d PinholeCamera::DistortPixel(const Eigen::Vector2d& ideal) const {
  if (!HasDistortion()) return ideal;
  const Eigen::Vector2d xy = Distort({(ideal.x() - cx) / fx, (ideal.y() - cy) / fy});
  return {fx * xy.x() + cx, fy * xy.y() + cy};
}

PixelRays::PixelRays(const PinholeCamera& camera, bool exact)
    : width_(camera.width), height_(camera.height) {
  const std::size_t n = static_cast<std::size_t>(width_) * height_;
  x_.resize(n);
  y_.resize(n);
  const double fx = camera.fx, fy = camera.fy, cx = camera.cx, cy = camera.cy;
  if (!camera.HasDistortion()) {
    for (int v = 0; v < height_; ++v) {
      for (int u = 0; u < width_; ++u) {
        x_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>((u - cx) / fx);
        y_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>((v - cy) / fy);
      }
    }
    return;
  }
  if (exact) {
    for (int v = 0; v < height_; ++v) {
      // Newton from the neighbour's solution converges in one or two steps.
      Eigen::Vector2d xy = camera.Undistort({-cx / fx, (v - cy) / fy});
      for (int u = 0; u < width_; ++u) {
        const Eigen::Vector2d target((u - cx) / fx, (v - cy) / fy);
        if (!SolveUndistort(camera.distortion, target, &xy)) xy = camera.Undistort(target);
        x_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>(xy.x());
        y_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>(xy.y());
      }
    }
    return;
  }
  // Exact undistortion on a grid of kStep pixels (the last row and column included), then the
  // correction (undistorted - distorted), which varies slowly, interpolated bilinearly between
  // the nodes: 1/16 of the solves, within 0.02 pixels for TUM fr1's strong lens (0.1 mm at
  // 2 m, far below depth noise).
  constexpr int kStep = 4;
  auto node = [&](int i, int size) { return std::min(i * kStep, size - 1); };
  const int nu = (width_ - 1 + kStep - 1) / kStep + 1, nv = (height_ - 1 + kStep - 1) / kStep + 1;
  std::vector<Eigen::Vector2d> correction(static_cast<std::size_t>(nu) * nv);
  for (int j = 0; j < nv; ++j) {
    for (int i = 0; i < nu; ++i) {
      const Eigen::Vector2d distorted((node(i, width_) - cx) / fx, (node(j, height_) - cy) / fy);
      correction[static_cast<std::size_t>(j) * nu + i] = camera.Undistort(distorted) - distorted;
    }
  }
  for (int v = 0; v < height_; ++v) {
    const int j = std::min(v / kStep, nv - 2);
    const double b =
        static_cast<double>(v - node(j, height_)) / (node(j + 1, height_) - node(j, height_));
    for (int u = 0; u < width_; ++u) {
      const int i = std::min(u / kStep, nu - 2);
      const double a =
          static_cast<double>(u - node(i, width_)) / (node(i + 1, width_) - node(i, width_));
      const Eigen::Vector2d* c = &correction[static_cast<std::size_t>(j) * nu + i];
      const Eigen::Vector2d delta =
          (1 - b) * ((1 - a) * c[0] + a * c[1]) + b * ((1 - a) * c[nu] + a * c[nu + 1]);
      x_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>((u - cx) / fx + delta.x());
      y_[static_cast<std::size_t>(v) * width_ + u] = static_cast<float>((v - cy) / fy + delta.y());
    }
  }
}

Eigen::Matrix3d PinholeCamera::K() const {
  Eigen::Matrix3d k;
  k << fx, 0, cx, 0, fy, cy, 0, 0, 1;
  return k;
}

PinholeCamera PinholeCamera::Scaled(double factor) const {
  return Resized(static_cast<int>(std::lround(width * factor)),
                 static_cast<int>(std::lround(height * factor)));
}

PinholeCamera PinholeCamera::Resized(int new_width, int new_height) const {
  PinholeCamera c = *this;
  const double sx = static_cast<double>(new_width) / width;
  const double sy = static_cast<double>(new_height) / height;
  c.width = new_width;
  c.height = new_height;
  c.fx = fx * sx;
  c.fy = fy * sy;
  c.bf = bf * sx;  // the baseline is physical; bf scales with fx
  c.cx = (cx + 0.5) * sx - 0.5;
  c.cy = (cy + 0.5) * sy - 0.5;
  return c;
}

std::string PinholeCamera::ToString() const {
  char text[256];
  std::snprintf(text, sizeof(text),
                "%dx%d fx=%.3f fy=%.3f cx=%.3f cy=%.3f fps=%.1f depth_factor=%.1f far=%.2fm", width,
                height, fx, fy, cx, cy, fps, depth_map_factor, far_depth_m);
  std::string out = text;
  if (HasDistortion()) {
    std::snprintf(text, sizeof(text), " k1=%.6f k2=%.6f p1=%.6f p2=%.6f k3=%.6f", distortion[0],
                  distortion[1], distortion[2], distortion[3], distortion[4]);
    out += text;
  }
  if (!rgb) out += " colour files BGR (Camera.RGB 0)";
  return out;
}

}  // namespace ccmd
