#include "libccmd/optim/reprojection.h"

#include <ceres/ceres.h>
#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

// The template residual, three rows as the bundle adjuster uses it, for Ceres' automatic
// differentiation.
struct ThreeRows {
  ReprojectionResidual residual;
  template <typename T>
  bool operator()(const T* q, const T* t, const T* p, T* out) const {
    out[2] = T(0);
    return residual(q, t, p, out);
  }
};

// The written-out Jacobians against automatic differentiation of the template, at random
// cameras and points, with and without depth, for unit quaternions and ones that are not (the
// solver evaluates the formula wherever its steps take the parameters).
TEST(ReprojectionResidualTest, WrittenOutJacobiansEqualAutomaticDifferentiation) {
  Rng rng(7);
  const Intrinsics k{525, 520, 319.5, 239.5};
  for (int trial = 0; trial < 200; ++trial) {
    const bool with_depth = trial % 2 == 0;
    const bool unit = trial % 4 < 2;
    Eigen::Vector4d q(rng.Uniform(-1, 1), rng.Uniform(-1, 1), rng.Uniform(-1, 1),
                      rng.Uniform(0.2, 1));
    if (unit) q.normalize();
    const Eigen::Vector3d t(rng.Uniform(-1, 1), rng.Uniform(-1, 1), rng.Uniform(-1, 1));
    // A point in front of the camera: placed in the camera frame, moved to the world with the
    // inverse of the (normalised) pose.
    const Eigen::Quaterniond rotation(q[3], q[0], q[1], q[2]);
    const Eigen::Vector3d pc(rng.Uniform(-1, 1), rng.Uniform(-1, 1), rng.Uniform(1, 4));
    const Eigen::Vector3d p = rotation.normalized().inverse() * (pc - t);
    const ReprojectionResidual residual(k,
                                        Eigen::Vector2d(rng.Uniform(0, 640), rng.Uniform(0, 480)),
                                        with_depth ? rng.Uniform(1, 4) : 0.0, 1.7, 240.0);

    ceres::AutoDiffCostFunction<ThreeRows, 3, 4, 3, 3> automatic(new ThreeRows{residual});
    const double* parameters[3] = {q.data(), t.data(), p.data()};
    double expected[3], expected_q[12], expected_t[9], expected_p[9];
    double* expected_jacobians[3] = {expected_q, expected_t, expected_p};
    ASSERT_TRUE(automatic.Evaluate(parameters, expected, expected_jacobians));

    double actual[3], actual_q[12], actual_t[9], actual_p[9];
    residual.Evaluate(q.data(), t.data(), p.data(), actual, actual_q, actual_t, actual_p);
    auto near = [](double a, double b) { return std::abs(a - b) <= 1e-9 * (1 + std::abs(b)); };
    for (int i = 0; i < 3; ++i) EXPECT_TRUE(near(actual[i], expected[i])) << trial << " r" << i;
    for (int i = 0; i < 12; ++i) {
      EXPECT_TRUE(near(actual_q[i], expected_q[i]))
          << trial << " dq" << i << ": " << actual_q[i] << " vs " << expected_q[i];
    }
    for (int i = 0; i < 9; ++i) {
      EXPECT_TRUE(near(actual_t[i], expected_t[i])) << trial << " dt" << i;
      EXPECT_TRUE(near(actual_p[i], expected_p[i])) << trial << " dp" << i;
    }
    // Without Jacobians only the residual is written.
    double only[3];
    residual.Evaluate(q.data(), t.data(), p.data(), only, nullptr, nullptr, nullptr);
    for (int i = 0; i < 3; ++i) EXPECT_EQ(only[i], actual[i]);
  }
}

}  // namespace
}  // namespace ccmd
