#include "libccmd/geometry/camera.h"

#include <cmath>
#include <cstdio>

namespace ccmd {

bool PinholeCamera::IsValid(std::string* why) const {
  auto fail = [&](const char* reason) {
    if (why) *why = reason;
    return false;
  };
  if (width <= 0 || height <= 0) return fail("image size must be positive");
  if (width > 16384 || height > 16384) return fail("image size above 16384");
  // fy may be negative: ICL-NUIM's TUM-format release flips the y axis that way.
  if (!(std::fabs(fx) > 0) || !(std::fabs(fy) > 0) || !std::isfinite(fx) || !std::isfinite(fy)) {
    return fail("focal lengths must be finite and non-zero");
  }
  if (!std::isfinite(cx) || !std::isfinite(cy)) return fail("principal point must be finite");
  if (!(depth_map_factor > 0) || !std::isfinite(depth_map_factor)) {
    return fail("DepthMapFactor must be positive");
  }
  if (!(fps > 0)) return fail("fps must be positive");
  return true;
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
                "%dx%d fx=%.3f fy=%.3f cx=%.3f cy=%.3f fps=%.1f depth_factor=%.1f far=%.2fm",
                width, height, fx, fy, cx, cy, fps, depth_map_factor, far_depth_m);
  return text;
}

}  // namespace ccmd
