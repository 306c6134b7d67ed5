#pragma once

// Synthetic indoor scenes for the demo and for tests: a room with furniture-like boxes,
// columns, shelves and pictures, every surface a convex planar polygon carrying its own
// procedurally generated texture (random multi-scale shapes, so ORB finds thousands of
// well-spread corners and no two places look alike). Everything is a function of the seed.

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>

#include "libccmd/io/ply.h"
#include "libccmd/util/options_writer.h"

namespace ccmd {

// A textured texture pyramid: levels[0] is full resolution, each next level half the size.
struct MipTexture {
  std::vector<cv::Mat> levels;  // CV_8UC3, BGR
};

// A convex planar polygon. Its front side (the side it is seen from) is where
// normal . x > offset. Texture coordinates (s, t) in metres are measured from `origin`
// along `axis_s` and `axis_t` (unit, in-plane, orthogonal); the texture covers
// [0, extent_s] x [0, extent_t].
struct ScenePolygon {
  std::vector<Eigen::Vector3d> vertices;  // world, counter-clockwise seen from the front
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  double offset = 0.0;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis_s = Eigen::Vector3d::UnitX();
  Eigen::Vector3d axis_t = Eigen::Vector3d::UnitY();
  double extent_s = 0.0;
  double extent_t = 0.0;
  std::vector<Eigen::Vector2d> vertices_st;  // vertices in texture coordinates
  int texture = -1;

  // (s, t) of a world point on the plane.
  Eigen::Vector2d TextureCoordinates(const Eigen::Vector3d& p) const {
    const Eigen::Vector3d d = p - origin;
    return {d.dot(axis_s), d.dot(axis_t)};
  }
  // Point in the (convex) polygon, at least `margin` metres inside its edges.
  bool ContainsSt(const Eigen::Vector2d& st, double margin = 0.0) const;
  double Area() const;
};

struct RoomSceneOptions {
  std::uint64_t seed = 1;
  double size_x = 5.0;           // metres, room extent along x (centred on the origin)
  double size_y = 4.5;           // along y
  double height = 2.6;           // floor at z = 0, ceiling at z = height (world z points up)
  double texel_m = 0.004;        // texture resolution
  double shapes_per_m2 = 260.0;  // texture density
  // Objects keep out of this ellipse around the room centre, where cameras move.
  double free_radius_x = 1.75;
  double free_radius_y = 1.5;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

class SyntheticScene {
 public:
  // Builds the room. Takes about a second (texture generation).
  static SyntheticScene MakeRoom(const RoomSceneOptions& options);

  // A scene of explicit polygons with flat grey textures: for tests that need known geometry.
  static SyntheticScene FromPolygons(std::vector<ScenePolygon> polygons, double texel_m = 0.01);

  const std::vector<ScenePolygon>& polygons() const { return polygons_; }
  const std::vector<MipTexture>& textures() const { return textures_; }
  double texel_m() const { return texel_m_; }
  // A point light near the ceiling, for view-independent (Lambertian) shading.
  const Eigen::Vector3d& light() const { return light_; }

  // The texture colour (BGR) at texture coordinates (s, t) of polygon `index`, level 0.
  cv::Vec3b ColorAt(int index, const Eigen::Vector2d& st) const;

  // Samples every polygon on a grid of `spacing` metres. If `visible` is given it holds,
  // per polygon, one flag per grid cell (see VisibilityGrid); only flagged cells are kept.
  // The cloud has normals and colours (RGB).
  PointCloud SampleSurface(double spacing,
                           const std::vector<std::vector<std::uint8_t>>* visible = nullptr) const;

  // Grid used by SampleSurface and by the renderer's visibility marks.
  struct GridSize {
    int cells_s = 0, cells_t = 0;
  };
  GridSize VisibilityGrid(int polygon, double spacing) const;

  // Adds a polygon given by world vertices (counter-clockwise seen from the front).
  // Public for scene builders and tests; `texture` < 0 generates a new texture.
  void AddPolygon(const std::vector<Eigen::Vector3d>& vertices, int texture = -1);

 private:
  std::vector<ScenePolygon> polygons_;
  std::vector<MipTexture> textures_;
  double texel_m_ = 0.004;
  double shapes_per_m2_ = 260.0;
  std::uint64_t texture_seed_ = 1;
  Eigen::Vector3d light_ = Eigen::Vector3d(0, 0, 2.4);
  bool flat_textures_ = false;
};

// Builds a texture of the given size (texels) filled with random shapes; deterministic.
MipTexture MakeProceduralTexture(int width, int height, double texel_m, double shapes_per_m2,
                                 std::uint64_t seed);

}  // namespace ccmd
