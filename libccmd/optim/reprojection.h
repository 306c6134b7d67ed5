#pragma once

// Residuals shared by the optimisers (pose, bundle adjustment): a map point seen by a camera at
// pixel (u, v) and, for RGB-D, with a measured depth. Each part is divided by its own standard
// deviation, so chi-square tests combine them: pixels by the keypoint octave's sigma, depth by the
// depth sensor's sigma at that depth (which grows with depth squared). This weighs depth by what
// the sensor delivers, unlike ORB-SLAM's virtual right-image coordinate (u - bf / z), whose
// one-pixel sigma corresponds to ~12 cm of depth at 2.5 m and so mostly ignores depth.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <string>

#include "libccmd/geometry/pose.h"
#include "libccmd/io/config.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct Intrinsics {
  double fx = 525, fy = 525, cx = 319.5, cy = 239.5;
};

// Residual of one observation: 2 values (u, v) or 3 with depth.
// Parameters: camera rotation q_cw (Eigen order x, y, z, w), translation t_cw, point p_w.
struct ReprojectionResidual {
  // `depth` <= 0: no depth measurement. `sqrt_info_px` = 1 / pixel sigma,
  // `sqrt_info_depth` = 1 / depth sigma (1/m).
  ReprojectionResidual(const Intrinsics& k, const Eigen::Vector2d& uv, double depth,
                       double sqrt_info_px, double sqrt_info_depth)
      : k_(k), uv_(uv), depth_(depth), w_(sqrt_info_px), w_depth_(sqrt_info_depth) {}

  template <typename T>
  bool operator()(const T* q_cw, const T* t_cw, const T* p_w, T* residual) const {
    const Eigen::Map<const Eigen::Quaternion<T>> q(q_cw);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> t(t_cw);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> p(p_w);
    const Eigen::Matrix<T, 3, 1> pc = q * p + t;
    const T inv_z = T(1) / pc.z();
    residual[0] = T(w_) * (T(k_.fx) * pc.x() * inv_z + T(k_.cx) - T(uv_.x()));
    residual[1] = T(w_) * (T(k_.fy) * pc.y() * inv_z + T(k_.cy) - T(uv_.y()));
    if (depth_ > 0) residual[2] = T(w_depth_) * (pc.z() - T(depth_));
    return true;
  }

  // The same residual, three rows (the third zero without depth), with its Jacobians written
  // out: row-major 3x4 (q_cw's four coordinates), 3x3 (t_cw) and 3x3 (p_w), each skipped when
  // null. They are the derivatives of the formula the template evaluates (Eigen's rotation of
  // a vector by q, unit or not), so they equal automatic differentiation's to rounding at a
  // fraction of its cost (Jets of ten derivatives per observation in every BA iteration).
  void Evaluate(const double* q_cw, const double* t_cw, const double* p_w, double* residual,
                double* J_q, double* J_t, double* J_p) const;

  bool has_depth() const { return depth_ > 0; }

 private:
  Intrinsics k_;
  Eigen::Vector2d uv_;
  double depth_;
  double w_, w_depth_;
};

// Residual of a measured relative pose T_b_a between two cameras (a BaRelativePose):
// sqrt_information * (rotation vector, translation) of T_b_a_estimate * T_b_a^-1.
// Parameters: q_a, t_a, q_b, t_b (T_cam_world of each camera, quaternions x y z w).
struct RelativePoseResidual {
  RelativePoseResidual(const Pose& T_b_a, const Eigen::Matrix<double, 6, 6>& sqrt_information)
      : q_m_(T_b_a.linear()), t_m_(T_b_a.translation()), sqrt_information_(sqrt_information) {}

  template <typename T>
  bool operator()(const T* qa_, const T* ta_, const T* qb_, const T* tb_, T* residual) const {
    using Vec3 = Eigen::Matrix<T, 3, 1>;
    const Eigen::Map<const Eigen::Quaternion<T>> qa(qa_), qb(qb_);
    const Eigen::Map<const Vec3> ta(ta_), tb(tb_);
    // Estimate T_b_a = T_b * T_a^-1, error E = T_b_a * T_measured^-1.
    const Eigen::Quaternion<T> q_ba = qb * qa.conjugate();
    const Vec3 t_ba = tb - q_ba * ta;
    Eigen::Quaternion<T> q_e = q_ba * q_m_.conjugate().cast<T>();
    if (q_e.w() < T(0)) q_e.coeffs() = -q_e.coeffs();
    const Vec3 t_e = t_ba - q_e * t_m_.cast<T>();
    Eigen::Matrix<T, 6, 1> xi;
    xi << T(2) * q_e.vec(), t_e;
    Eigen::Map<Eigen::Matrix<T, 6, 1>> out(residual);
    out = sqrt_information_.cast<T>() * xi;
    return true;
  }

 private:
  Eigen::Quaterniond q_m_;
  Eigen::Vector3d t_m_;
  Eigen::Matrix<double, 6, 6> sqrt_information_;
};

// The same residual evaluated in plain doubles as a chi-square value (sum of squared
// normalised parts), used to classify outliers. Large for points behind the camera.
double ReprojectionChi2(const Intrinsics& k, const Eigen::Isometry3d& T_cam_world,
                        const Eigen::Vector3d& p_w, const Eigen::Vector2d& uv, double depth,
                        double info_px, double info_depth);

// Depth sensor noise: sigma(z) = sigma_0 + sigma_2 * z^2 (metres). A property of the sensor:
// the default is a Kinect v1's axial noise (the published structured-light model
// 1.2 mm + 1.9 mm * (z - 0.4 m)^2 per m^2, as sigma_0 + sigma_2 z^2 over 0.5-3 m: 2 mm at 1 m,
// 6.5 mm at 2 m, 14 mm at 3 m); a config gives its own (rendered ICL-NUIM depth: its 1 mm
// rounding at every range). The agent weighs its keypoints' depth with it and announces it to
// the server, which weighs that agent's keyframes with it.
struct DepthNoise {
  double sigma_0 = 0.0005;
  double sigma_2 = 0.0015;
  // How far a keypoint may be from where its depth is read, in its octave's pixel sigmas: the
  // depth slope there times this distance adds to a keypoint's depth sigma (0: sensor only).
  double keypoint_offset = 1.0;
  double Sigma(double z) const { return sigma_0 + sigma_2 * z * z; }
  double Information(double z) const { return 1.0 / (Sigma(z) * Sigma(z)); }
  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// Reads DepthNoise.sigma0, DepthNoise.sigma2 and DepthNoise.keypointOffset; absent keys keep
// `defaults`. Invalid values are errors naming the file.
StatusOr<DepthNoise> ReadDepthNoise(const ConfigFile& config, DepthNoise defaults = {});

// The config lines ReadDepthNoise reads back as `noise`, exactly.
std::string DepthNoiseConfigKeys(const DepthNoise& noise);

// Chi-square thresholds at 95%: 2 and 3 degrees of freedom.
constexpr double kChi2Mono = 5.991;
constexpr double kChi2Stereo = 7.815;

// Ceres' HuberLoss(sqrt(b)) of a squared residual norm s: the loss rho(s) and its derivative
// rho'(s), which weighs the residual in the normal equations (b <= 0: no kernel, rho = s).
struct RobustValue {
  double rho, derivative;
};
inline RobustValue Huber(double s, double b) {
  if (b <= 0 || s <= b) return {s, 1.0};
  const double r = std::sqrt(s), a = std::sqrt(b);
  return {2 * a * r - b, a / r};
}

}  // namespace ccmd
