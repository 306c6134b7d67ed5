// New map points from keypoints without depth: epipolar matching between two keyframes and
// their triangulation in local mapping, on a scene whose points and views are known exactly.

#include <gtest/gtest.h>

#include <map>
#include <random>

#include "libccmd/tracking/local_mapper.h"
#include "libccmd/tracking/matching.h"

namespace ccmd {
namespace {

cv::KeyPoint KeypointAt(const Eigen::Vector2d& uv) {
  cv::KeyPoint kp;
  kp.pt = cv::Point2f(static_cast<float>(uv.x()), static_cast<float>(uv.y()));
  kp.octave = 0;
  kp.angle = 30.0f;
  kp.size = 31.0f;
  return kp;
}

// A descriptor `bits` bits away from `d` (distinct bits, from the generator).
Descriptor Flipped(const Descriptor& d, int bits, std::mt19937* rng) {
  Descriptor out = d;
  std::vector<int> order(256);
  for (int b = 0; b < 256; ++b) order[b] = b;
  std::shuffle(order.begin(), order.end(), *rng);
  for (int k = 0; k < bits; ++k)
    out[order[k] / 8] ^= static_cast<std::uint8_t>(1 << (order[k] % 8));
  return out;
}

// Two views of a scene. Points of the first kind ("depth") have a measured depth in both views,
// those of the second ("bare") in neither. For every bare point the second view also holds a
// decoy: a keypoint whose descriptor is closer to the first view's than the true one, 25 pixels
// off the epipolar line. The second camera is 0.3 m to the side, turned by 5 degrees.
struct Scene {
  PinholeCamera camera;
  Pose T_world_a = Pose::Identity(), T_world_b = Pose::Identity();
  std::vector<Eigen::Vector3d> depth_points, bare_points;
  FrameFeatures a, b;
  // Keypoint indices: view a then view b, per point; decoys in b.
  std::vector<std::pair<int, int>> depth_keypoints, bare_keypoints;
  std::vector<int> decoys;

  explicit Scene(double fy) {
    camera.fy = fy;
    T_world_b.translation() = Eigen::Vector3d(0.3, 0.02, 0.05);
    T_world_b.linear() = Eigen::AngleAxisd(-5.0 * M_PI / 180, Eigen::Vector3d::UnitY()).matrix();
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> x(-1.2, 1.2), y(-0.9, 0.9), z(1.5, 4.0);
    std::uniform_int_distribution<int> byte(0, 255);
    while (depth_points.size() < 200 || bare_points.size() < 120) {
      const Eigen::Vector3d p(x(rng), y(rng), z(rng));
      const Eigen::Vector3d pa = T_world_a.inverse() * p, pb = T_world_b.inverse() * p;
      const Eigen::Vector2d uva = camera.Project(pa), uvb = camera.Project(pb);
      if (!camera.InImage(uva, 40) || !camera.InImage(uvb, 40)) continue;
      Descriptor d;
      for (auto& v : d) v = static_cast<std::uint8_t>(byte(rng));
      const bool with_depth = depth_points.size() < 200;
      const int ia = Add(&a, uva, d, with_depth ? pa.z() : 0.0);
      const int ib = Add(&b, uvb, Flipped(d, 10, &rng), with_depth ? pb.z() : 0.0);
      if (with_depth) {
        depth_points.push_back(p);
        depth_keypoints.emplace_back(ia, ib);
        continue;
      }
      bare_points.push_back(p);
      bare_keypoints.emplace_back(ia, ib);
      // The decoy: moved across the epipolar line (the line's normal in b's image).
      const Eigen::Vector2d far = camera.Project(T_world_b.inverse() * (p * 1.5));
      const Eigen::Vector2d along = (far - uvb).normalized();
      const Eigen::Vector2d across(-along.y(), along.x());
      decoys.push_back(Add(&b, uvb + 25.0 * across, Flipped(d, 2, &rng), 0.0));
    }
  }

  int Add(FrameFeatures* f, const Eigen::Vector2d& uv, const Descriptor& d, double z) const {
    f->keypoints.push_back(KeypointAt(uv));
    cv::Mat row(1, 32, CV_8U);
    for (int k = 0; k < 32; ++k) row.at<std::uint8_t>(0, k) = d[k];
    f->descriptors.push_back(row);
    f->depth.push_back(static_cast<float>(z));
    f->depth_sigma.push_back(z > 0 ? 0.005f : 0.0f);
    f->u_right.push_back(z > 0 ? static_cast<float>(uv.x() - camera.bf / z) : -1.0f);
    return f->size() - 1;
  }
};

class TriangulationTest : public testing::TestWithParam<double> {};

TEST_P(TriangulationTest, EpipolarSearchPairsTheSamePointsAndSkipsDecoys) {
  const Scene scene(GetParam());
  const OrbExtractor orb;
  const Keyframe a(KeyframeId(0), 0.0, 0, scene.a, scene.T_world_a, 640, 480);
  const Keyframe b(KeyframeId(1), 0.1, 1, scene.b, scene.T_world_b, 640, 480);
  const auto pairs = SearchForTriangulation(a, b, orb, scene.camera);
  std::map<int, int> truth;
  for (const auto& [ia, ib] : scene.bare_keypoints) truth[ia] = ib;
  int correct = 0;
  for (const auto& [ia, ib] : pairs) {
    // Keypoints with depth at both ends are depth's to place; only bare ones are paired.
    ASSERT_TRUE(truth.count(ia)) << "keypoint " << ia << " of a has depth in both views";
    EXPECT_EQ(ib, truth[ia]) << "keypoint " << ia << " paired with the wrong keypoint of b";
    correct += ib == truth[ia];
  }
  EXPECT_GE(correct, 0.9 * static_cast<double>(scene.bare_points.size()));
}

TEST_P(TriangulationTest, LocalMappingPlacesPointsWithoutDepthWhereTheyAre) {
  const Scene scene(GetParam());
  const OrbExtractor orb;
  TrackingOptions options;
  options.synchronous_mapping = true;
  options.depth_alignment_weight = 0;  // the keyframes carry no depth images
  options.triangulation_neighbours = 10;
  LocalMap map;
  LocalMapper mapper(scene.camera, options, &map, &orb, nullptr);
  auto a =
      std::make_shared<Keyframe>(map.NextKeyframeId(), 0.0, 0, scene.a, scene.T_world_a, 640, 480);
  auto b =
      std::make_shared<Keyframe>(map.NextKeyframeId(), 0.1, 1, scene.b, scene.T_world_b, 640, 480);
  {
    const auto lock = map.Lock();
    map.AddKeyframe(a);
    map.AddKeyframe(b);
    // The points with depth, as tracking leaves them: seen by both keyframes.
    for (std::size_t k = 0; k < scene.depth_points.size(); ++k) {
      auto p = std::make_shared<MapPoint>(map.NextMapPointId(), scene.depth_points[k]);
      map.AddMapPoint(p);
      map.AddObservation(p, a.get(), scene.depth_keypoints[k].first);
      map.AddObservation(p, b.get(), scene.depth_keypoints[k].second);
      p->UpdateDescriptor();
      p->UpdateNormalAndDepth(orb);
    }
    map.UpdateConnections(a.get());
  }
  mapper.Insert(b);
  mapper.ProcessPending();
  const auto lock = map.Lock();
  int placed = 0;
  for (std::size_t k = 0; k < scene.bare_points.size(); ++k) {
    const MapPointPtr p = b->point(scene.bare_keypoints[k].second);
    if (!p) continue;
    EXPECT_EQ(p->KeypointIn(a.get()), scene.bare_keypoints[k].first);
    EXPECT_LT((p->position() - scene.bare_points[k]).norm(), 0.005)
        << "point " << k << " at " << p->position().transpose() << ", truly at "
        << scene.bare_points[k].transpose();
    ++placed;
  }
  EXPECT_GE(placed, 0.9 * static_cast<double>(scene.bare_points.size()));
  for (int decoy : scene.decoys) EXPECT_FALSE(b->point(decoy)) << "decoy " << decoy << " linked";
  EXPECT_EQ(mapper.stats().triangulated_points, placed);
}

TEST(TriangulationOptionsTest, OffByDefaultAndBoundsChecked) {
  TrackingOptions options;
  EXPECT_EQ(options.triangulation_neighbours, 0);
  options.triangulation_neighbours = 10;
  EXPECT_TRUE(options.Validate().ok());
  options.triangulation_neighbours = -1;
  EXPECT_FALSE(options.Validate().ok());
  options.triangulation_neighbours = 101;
  EXPECT_FALSE(options.Validate().ok());
}

// ICL-NUIM's convention (negative fy) must give the same points as the usual one.
INSTANTIATE_TEST_SUITE_P(FocalSigns, TriangulationTest, testing::Values(525.0, -525.0));

}  // namespace
}  // namespace ccmd
