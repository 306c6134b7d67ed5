#pragma once

// Cameras with the conventions the shipped configs use, for tests: TUM fr1's colour camera
// with its strong lens distortion, ICL-NUIM's camera with a negative fy.

#include "libccmd/geometry/camera.h"

namespace ccmd::testing {

inline PinholeCamera TumFr1Camera() {
  PinholeCamera c;
  c.fx = 517.306408;
  c.fy = 516.469215;
  c.cx = 318.643040;
  c.cy = 255.313989;
  c.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  return c;
}

inline PinholeCamera IclNuimCamera() {
  PinholeCamera c;
  c.fx = 481.2;
  c.fy = -480.0;
  c.cx = 319.5;
  c.cy = 239.5;
  return c;
}

}  // namespace ccmd::testing
