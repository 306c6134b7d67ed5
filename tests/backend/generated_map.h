#pragma once

// Generated server maps for the back-end's unit tests: a camera walking a circle inside a
// ring of textured walls. Every wall point has its own random descriptor; a keyframe sees the
// points in front of it (pixels and depths with small noise, descriptors with a few flipped
// bits), and the first keyframe that sees a point anchors it.

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <optional>
#include <vector>

#include "libccmd/backend/server_map.h"
#include "libccmd/util/random.h"

namespace ccmd::testing {

inline PinholeCamera TestCamera() {
  PinholeCamera c;
  c.fx = c.fy = 525;
  c.cx = 319.5;
  c.cy = 239.5;
  c.width = 640;
  c.height = 480;
  return c;
}

inline Descriptor RandomDescriptor(Rng* rng) {
  Descriptor d;
  for (auto& b : d) b = static_cast<std::uint8_t>(rng->Next());
  return d;
}

inline Descriptor FlipBits(Descriptor d, int bits, Rng* rng) {
  for (int i = 0; i < bits; ++i) {
    const int bit = rng->UniformInt(0, 255);
    d[bit / 8] ^= static_cast<std::uint8_t>(1 << (bit % 8));
  }
  return d;
}

// The true pose of step `i` of `steps` around a circle of radius 1 m at height 0, the camera
// looking outwards (z axis along the radius, y down).
inline Pose CirclePose(int i, int steps) {
  const double a = 2 * M_PI * i / steps;
  const Eigen::Vector3d z(std::cos(a), std::sin(a), 0), y(0, 0, -1);
  Pose T = Pose::Identity();
  T.linear().col(0) = y.cross(z);
  T.linear().col(1) = y;
  T.linear().col(2) = z;
  T.translation() = 1.0 * z;
  return T;
}

// A ring wall of radius 3.5 m, 2 m high: points with descriptors.
struct GeneratedWorld {
  std::vector<Eigen::Vector3d> points;
  std::vector<Descriptor> descriptors;
};

inline GeneratedWorld MakeRingWorld(int points, Rng* rng) {
  GeneratedWorld world;
  for (int j = 0; j < points; ++j) {
    const double a = rng->Uniform(0, 2 * M_PI);
    world.points.emplace_back(3.5 * std::cos(a), 3.5 * std::sin(a), rng->Uniform(-1.0, 1.0));
    world.descriptors.push_back(RandomDescriptor(rng));
  }
  return world;
}

// Map point ids of points an agent makes again where it has been before (it does not know).
inline constexpr std::uint32_t kRevisitPointIds = 100000;

// Adds a keyframe of `agent` with id `id` that sees `world` from `T_true`, placed in the map at
// `T_map_cam`. A wall point j is map point j (linked if it exists, else anchored here), except
// for a revisit (`local_window` set): as an agent's tracking would, it links only the points
// the keyframes from `*local_window` on observe, and makes the others again as new points
// (kRevisitPointIds + j).
inline ServerKeyframe* AddGeneratedKeyframe(
    ServerMap* map, const GeneratedWorld& world, AgentId agent, std::uint32_t id,
    const Pose& T_true, const Pose& T_map_cam, Rng* rng,
    std::optional<std::uint32_t> local_window = std::nullopt) {
  const PinholeCamera camera = TestCamera();
  auto kf = std::make_unique<ServerKeyframe>();
  kf->id = {agent, KeyframeId(id)};
  kf->timestamp = id;
  kf->T_map_cam = T_map_cam;
  kf->T_agent_cam = T_map_cam;
  if (id > 0) kf->parent = KeyframeId(id - 1);
  std::vector<int> seen;
  for (std::size_t j = 0; j < world.points.size(); ++j) {
    const Eigen::Vector3d pc = T_true.inverse() * world.points[j];
    if (pc.z() < 0.5) continue;
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv, 8)) continue;
    kf->AppendKeypoint({cv::Point2f(static_cast<float>(uv.x() + 0.3 * rng->Normal()),
                                    static_cast<float>(uv.y() + 0.3 * rng->Normal())),
                        0, static_cast<float>(pc.z() + 0.002 * rng->Normal())},
                       FlipBits(world.descriptors[j], 6, rng));
    seen.push_back(static_cast<int>(j));
  }
  ServerKeyframe* raw = map->AddKeyframe(std::move(kf));
  for (std::size_t k = 0; k < seen.size(); ++k) {
    const auto j = static_cast<std::uint32_t>(seen[k]);
    GlobalMapPointId pid{agent, MapPointId(j)};
    ServerMapPoint* p = map->point(pid);
    if (local_window) {
      const bool tracked =
          p && std::any_of(p->observations.begin(), p->observations.end(), [&](const auto& o) {
            return o.keyframe->id.keyframe.value() >= *local_window;
          });
      if (!tracked) {
        pid.point = MapPointId(kRevisitPointIds + j);
        p = map->point(pid);
      }
    }
    if (!p) {
      // Measured in the anchor's camera frame: it moves with the anchor's map pose.
      p = map->AddPoint(std::make_unique<ServerMapPoint>(
          pid, raw, T_true.inverse() * world.points[seen[k]], world.descriptors[seen[k]]));
    }
    map->AddObservation(p, raw, static_cast<int>(k));
  }
  // Covisibility with every keyframe that shares points, weighted by how many.
  std::map<ServerKeyframe*, int> shared;
  for (ServerMapPoint* p : raw->points) {
    for (const auto& o : p->observations) {
      if (o.keyframe != raw) shared[o.keyframe]++;
    }
  }
  for (const auto& [other, weight] : shared) map->AddCovisibility(raw, other, weight);
  return raw;
}

}  // namespace ccmd::testing
