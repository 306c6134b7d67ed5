#include "libccmd/synth/scene.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "libccmd/util/logging.h"
#include "libccmd/util/random.h"

namespace ccmd {

Status RoomSceneOptions::Validate() const {
  if (!(size_x > 1 && size_y > 1 && height > 1))
    return InvalidArgument("room must be over 1 m each way");
  if (!(texel_m > 0) || !(shapes_per_m2 > 0))
    return InvalidArgument("texture must have size and density");
  if (!(free_radius_x > 0 && free_radius_y > 0))
    return InvalidArgument("free radii must be positive");
  return Status::Ok();
}

void RoomSceneOptions::Describe(OptionsWriter* out) const {
  out->Add("seed", seed);
  out->Add("size_x", size_x);
  out->Add("size_y", size_y);
  out->Add("height", height);
  out->Add("texel_m", texel_m);
  out->Add("shapes_per_m2", shapes_per_m2);
  out->Add("free_radius_x", free_radius_x);
  out->Add("free_radius_y", free_radius_y);
}

bool ScenePolygon::ContainsSt(const Eigen::Vector2d& st, double margin) const {
  const std::size_t n = vertices_st.size();
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector2d& a = vertices_st[i];
    const Eigen::Vector2d& b = vertices_st[(i + 1) % n];
    const double cross = (b.x() - a.x()) * (st.y() - a.y()) - (b.y() - a.y()) * (st.x() - a.x());
    // cross / |b - a| is the signed distance from the edge, positive inside.
    if (cross < margin * (b - a).norm() - 1e-12) return false;
  }
  return true;
}

double ScenePolygon::Area() const {
  double twice = 0.0;
  for (std::size_t i = 0; i < vertices_st.size(); ++i) {
    const Eigen::Vector2d& a = vertices_st[i];
    const Eigen::Vector2d& b = vertices_st[(i + 1) % vertices_st.size()];
    twice += a.x() * b.y() - b.x() * a.y();
  }
  return std::abs(twice) / 2.0;
}

MipTexture MakeProceduralTexture(int width, int height, double texel_m, double shapes_per_m2,
                                 std::uint64_t seed) {
  Rng rng(seed);
  width = std::max(width, 4);
  height = std::max(height, 4);
  // Base colour with slow variation, so large areas are not flat.
  const cv::Scalar base(rng.Uniform(60, 200), rng.Uniform(60, 200), rng.Uniform(60, 200));
  cv::Mat low(std::max(2, height / 48), std::max(2, width / 48), CV_32FC3);
  for (int y = 0; y < low.rows; ++y) {
    for (int x = 0; x < low.cols; ++x) {
      low.at<cv::Vec3f>(y, x) =
          cv::Vec3f(rng.Uniform(-45, 45), rng.Uniform(-45, 45), rng.Uniform(-45, 45));
    }
  }
  cv::Mat variation;
  cv::resize(low, variation, cv::Size(width, height), 0, 0, cv::INTER_CUBIC);
  cv::Mat texture_f(height, width, CV_32FC3, base);
  texture_f += variation;
  cv::Mat texture;
  texture_f.convertTo(texture, CV_8UC3);

  // Random shapes from 1.2 cm to 25 cm (log-uniform), largest first so small detail sits
  // on top: corners at every scale the camera sees.
  const double area_m2 = width * height * texel_m * texel_m;
  const int count = static_cast<int>(area_m2 * shapes_per_m2);
  std::vector<double> sizes(count);
  const double lo = std::log(0.012 / texel_m), hi = std::log(0.25 / texel_m);
  for (double& s : sizes) s = std::exp(rng.Uniform(lo, hi));
  std::sort(sizes.rbegin(), sizes.rend());
  const int shift = 4;  // sub-pixel precision of OpenCV drawing
  const double scale = 1 << shift;
  for (double size : sizes) {
    const cv::Point2d c(rng.Uniform(0, width), rng.Uniform(0, height));
    const cv::Scalar color(rng.Uniform(10, 245), rng.Uniform(10, 245), rng.Uniform(10, 245));
    const double angle = rng.Uniform(0, M_PI);
    const int kind = rng.UniformInt(0, 5);
    auto P = [&](double x, double y) {
      return cv::Point(static_cast<int>(std::lround(x * scale)),
                       static_cast<int>(std::lround(y * scale)));
    };
    const double ca = std::cos(angle), sa = std::sin(angle);
    switch (kind) {
      case 0: {  // rotated rectangle
        const double a = size / 2, b = size / 2 * rng.Uniform(0.3, 1.0);
        cv::Point pts[4] = {P(c.x + ca * a - sa * b, c.y + sa * a + ca * b),
                            P(c.x - ca * a - sa * b, c.y - sa * a + ca * b),
                            P(c.x - ca * a + sa * b, c.y - sa * a - ca * b),
                            P(c.x + ca * a + sa * b, c.y + sa * a - ca * b)};
        cv::fillConvexPoly(texture, pts, 4, color, cv::LINE_AA, shift);
        break;
      }
      case 1:
        cv::circle(texture, P(c.x, c.y), static_cast<int>(size / 2 * scale), color, cv::FILLED,
                   cv::LINE_AA, shift);
        break;
      case 2:
        cv::ellipse(texture, P(c.x, c.y),
                    cv::Size(static_cast<int>(size / 2 * scale),
                             static_cast<int>(size / 2 * rng.Uniform(0.25, 0.8) * scale)),
                    angle * 180 / M_PI, 0, 360, color, cv::FILLED, cv::LINE_AA, shift);
        break;
      case 3: {  // triangle
        cv::Point pts[3];
        for (int k = 0; k < 3; ++k) {
          const double a = angle + k * 2 * M_PI / 3 + rng.Uniform(-0.5, 0.5);
          pts[k] = P(c.x + size / 2 * std::cos(a), c.y + size / 2 * std::sin(a));
        }
        cv::fillConvexPoly(texture, pts, 3, color, cv::LINE_AA, shift);
        break;
      }
      case 4: {  // thick stroke
        const int thickness = std::max(1, static_cast<int>(size * rng.Uniform(0.08, 0.2)));
        cv::line(texture, P(c.x - ca * size / 2, c.y - sa * size / 2),
                 P(c.x + ca * size / 2, c.y + sa * size / 2), color, thickness, cv::LINE_AA, shift);
        break;
      }
      default: {  // glyphs: dense corners like printed text
        const char letters[] = "ABCDEFGHKLMNPRSTUVWXYZ0123456789#%&";
        std::string text(1 + rng.UniformInt(0, 2), 'A');
        for (char& ch : text) ch = letters[rng.UniformInt(0, sizeof(letters) - 2)];
        const double font_scale = std::max(0.2, size / 30.0);
        cv::putText(texture, text, cv::Point(static_cast<int>(c.x), static_cast<int>(c.y)),
                    cv::FONT_HERSHEY_SIMPLEX, font_scale, color,
                    std::max(1, static_cast<int>(font_scale * 2)), cv::LINE_AA);
        break;
      }
    }
  }
  MipTexture mip;
  mip.levels.push_back(texture);
  while (std::min(mip.levels.back().cols, mip.levels.back().rows) >= 8) {
    cv::Mat next;
    cv::pyrDown(mip.levels.back(), next);
    mip.levels.push_back(next);
  }
  return mip;
}

void SyntheticScene::AddPolygon(const std::vector<Eigen::Vector3d>& vertices, int texture) {
  CCMD_CHECK_GE(vertices.size(), 3u);
  ScenePolygon p;
  p.vertices = vertices;
  // Newell's normal: robust for any planar polygon; its direction follows the winding.
  Eigen::Vector3d n = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < vertices.size(); ++i) {
    const Eigen::Vector3d& a = vertices[i];
    const Eigen::Vector3d& b = vertices[(i + 1) % vertices.size()];
    n += a.cross(b);
  }
  CCMD_CHECK_GT(n.norm(), 1e-12) << "degenerate polygon";
  p.normal = n.normalized();
  p.offset = p.normal.dot(vertices[0]);
  p.axis_s = (vertices[1] - vertices[0]).normalized();
  p.axis_t = p.normal.cross(p.axis_s);
  double min_s = 1e300, min_t = 1e300, max_s = -1e300, max_t = -1e300;
  for (const auto& v : vertices) {
    const Eigen::Vector3d d = v - vertices[0];
    min_s = std::min(min_s, d.dot(p.axis_s));
    max_s = std::max(max_s, d.dot(p.axis_s));
    min_t = std::min(min_t, d.dot(p.axis_t));
    max_t = std::max(max_t, d.dot(p.axis_t));
  }
  p.origin = vertices[0] + min_s * p.axis_s + min_t * p.axis_t;
  p.extent_s = max_s - min_s;
  p.extent_t = max_t - min_t;
  for (const auto& v : vertices) p.vertices_st.push_back(p.TextureCoordinates(v));

  if (texture >= 0) {
    p.texture = texture;
  } else {
    const int w = static_cast<int>(std::ceil(p.extent_s / texel_m_)) + 2;
    const int h = static_cast<int>(std::ceil(p.extent_t / texel_m_)) + 2;
    if (flat_textures_) {
      MipTexture flat;
      flat.levels.push_back(cv::Mat(4, 4, CV_8UC3, cv::Scalar(128, 128, 128)));
      textures_.push_back(flat);
    } else {
      textures_.push_back(MakeProceduralTexture(w, h, texel_m_, shapes_per_m2_,
                                                MixSeed(texture_seed_, polygons_.size())));
    }
    p.texture = static_cast<int>(textures_.size()) - 1;
  }
  polygons_.push_back(std::move(p));
}

SyntheticScene SyntheticScene::FromPolygons(std::vector<ScenePolygon> polygons, double texel_m) {
  SyntheticScene scene;
  scene.texel_m_ = texel_m;
  scene.flat_textures_ = true;
  for (const auto& p : polygons) scene.AddPolygon(p.vertices);
  return scene;
}

cv::Vec3b SyntheticScene::ColorAt(int index, const Eigen::Vector2d& st) const {
  const ScenePolygon& p = polygons_[index];
  const cv::Mat& level0 = textures_[p.texture].levels[0];
  const int x = std::clamp(static_cast<int>(st.x() / texel_m_), 0, level0.cols - 1);
  const int y = std::clamp(static_cast<int>(st.y() / texel_m_), 0, level0.rows - 1);
  return level0.at<cv::Vec3b>(y, x);
}

SyntheticScene::GridSize SyntheticScene::VisibilityGrid(int polygon, double spacing) const {
  const ScenePolygon& p = polygons_[polygon];
  return {std::max(1, static_cast<int>(std::ceil(p.extent_s / spacing))),
          std::max(1, static_cast<int>(std::ceil(p.extent_t / spacing)))};
}

PointCloud SyntheticScene::SampleSurface(
    double spacing, const std::vector<std::vector<std::uint8_t>>* visible) const {
  PointCloud cloud;
  for (int k = 0; k < static_cast<int>(polygons_.size()); ++k) {
    const ScenePolygon& p = polygons_[k];
    const GridSize grid = VisibilityGrid(k, spacing);
    for (int j = 0; j < grid.cells_t; ++j) {
      for (int i = 0; i < grid.cells_s; ++i) {
        if (visible && !(*visible)[k][static_cast<std::size_t>(j) * grid.cells_s + i]) continue;
        const Eigen::Vector2d st((i + 0.5) * spacing, (j + 0.5) * spacing);
        if (!p.ContainsSt(st, /*margin=*/1e-4)) continue;  // not on an edge shared with others
        const Eigen::Vector3d x = p.origin + st.x() * p.axis_s + st.y() * p.axis_t;
        cloud.points.push_back(x.cast<float>());
        cloud.normals.push_back(p.normal.cast<float>());
        const cv::Vec3b bgr = ColorAt(k, st);
        cloud.colors.push_back({bgr[2], bgr[1], bgr[0]});
      }
    }
  }
  return cloud;
}

namespace {

// Helpers to build the room out of boxes and prisms.
class RoomBuilder {
 public:
  RoomBuilder(SyntheticScene* scene, Rng* rng, const RoomSceneOptions& options)
      : scene_(scene), rng_(rng), options_(options) {}

  // Adds a polygon whose front faces `outward` (vertex order is fixed up to match).
  void Face(std::vector<Eigen::Vector3d> v, const Eigen::Vector3d& outward) {
    const Eigen::Vector3d n = (v[1] - v[0]).cross(v[2] - v[0]);
    if (n.dot(outward) < 0) std::reverse(v.begin(), v.end());
    scene_->AddPolygon(v);
  }

  // Box with centre, half sizes and rotation; bottom face skipped when it rests on the floor.
  void Box(const Eigen::Vector3d& centre, const Eigen::Vector3d& half, const Eigen::Matrix3d& R,
           bool skip_bottom = true) {
    auto corner = [&](int sx, int sy, int sz) {
      return Eigen::Vector3d(centre +
                             R * Eigen::Vector3d(sx * half.x(), sy * half.y(), sz * half.z()));
    };
    for (int axis = 0; axis < 3; ++axis) {
      for (int sign = -1; sign <= 1; sign += 2) {
        if (axis == 2 && sign < 0 && skip_bottom) continue;
        std::vector<Eigen::Vector3d> v;
        const int a = (axis + 1) % 3, b = (axis + 2) % 3;
        const int quad[4][2] = {{-1, -1}, {1, -1}, {1, 1}, {-1, 1}};
        for (const auto& q : quad) {
          int s[3];
          s[axis] = sign;
          s[a] = q[0];
          s[b] = q[1];
          v.push_back(corner(s[0], s[1], s[2]));
        }
        Eigen::Vector3d out = Eigen::Vector3d::Zero();
        out[axis] = sign;
        Face(v, R * out);
      }
    }
  }

  void AxisBox(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, bool skip_bottom = true) {
    Box((lo + hi) / 2, (hi - lo) / 2, Eigen::Matrix3d::Identity(), skip_bottom);
  }

  // Vertical n-sided prism (a column) from z0 to z1.
  void Prism(const Eigen::Vector2d& centre, double radius, int sides, double z0, double z1) {
    std::vector<Eigen::Vector3d> top;
    for (int i = 0; i < sides; ++i) {
      const double a0 = 2 * M_PI * i / sides, a1 = 2 * M_PI * (i + 1) / sides;
      const Eigen::Vector2d p0 = centre + radius * Eigen::Vector2d(std::cos(a0), std::sin(a0));
      const Eigen::Vector2d p1 = centre + radius * Eigen::Vector2d(std::cos(a1), std::sin(a1));
      const double am = (a0 + a1) / 2;
      Face({{p0.x(), p0.y(), z0}, {p1.x(), p1.y(), z0}, {p1.x(), p1.y(), z1}, {p0.x(), p0.y(), z1}},
           {std::cos(am), std::sin(am), 0});
      top.push_back({p0.x(), p0.y(), z1});
    }
    Face(top, Eigen::Vector3d::UnitZ());
  }

  // True if the footprint rectangle keeps out of the cameras' free ellipse.
  bool OutsideFreeZone(const Eigen::Vector2d& lo, const Eigen::Vector2d& hi) const {
    for (double x : {lo.x(), hi.x(), (lo.x() + hi.x()) / 2}) {
      for (double y : {lo.y(), hi.y(), (lo.y() + hi.y()) / 2}) {
        const double e =
            std::pow(x / options_.free_radius_x, 2) + std::pow(y / options_.free_radius_y, 2);
        if (e < 1.0) return false;
      }
    }
    return true;
  }

  // Furniture along one wall. `along` is the wall direction, `inward` points into the room,
  // `wall_point` is the wall's start corner at the floor, `length` its length.
  void FurnishWall(const Eigen::Vector2d& start, const Eigen::Vector2d& along,
                   const Eigen::Vector2d& inward, double length) {
    double pos = 0.35;
    while (pos < length - 0.6) {
      const double width = rng_->Uniform(0.5, 1.3);
      if (pos + width > length - 0.3) break;
      const int kind = rng_->UniformInt(0, 5);
      double depth = kind == 2 ? rng_->Uniform(0.5, 0.75) : rng_->Uniform(0.3, 0.6);
      auto footprint = [&](double d, Eigen::Vector2d* lo, Eigen::Vector2d* hi) {
        const Eigen::Vector2d a = start + along * pos + inward * 0.01;
        const Eigen::Vector2d b = start + along * (pos + width) + inward * (0.01 + d);
        *lo = a.cwiseMin(b);
        *hi = a.cwiseMax(b);
      };
      Eigen::Vector2d lo, hi;
      footprint(depth, &lo, &hi);
      while (!OutsideFreeZone(lo, hi) && depth > 0.15) {
        depth -= 0.05;
        footprint(depth, &lo, &hi);
      }
      if (!OutsideFreeZone(lo, hi)) {
        pos += width;
        continue;
      }
      const Eigen::Vector2d wall_a = start + along * pos, wall_b = start + along * (pos + width);
      switch (kind) {
        case 0:
        case 1: {  // cabinet, sometimes with a box on top
          const double h = rng_->Uniform(0.45, 1.9);
          AxisBox({lo.x(), lo.y(), 0}, {hi.x(), hi.y(), h});
          if (h < 1.2 && rng_->Bernoulli(0.6)) {
            const Eigen::Vector2d c = (lo + hi) / 2;
            const double s = rng_->Uniform(0.08, 0.2);
            Box({c.x(), c.y(), h + s}, {s, s * 0.8, s}, Yaw(rng_->Uniform(0, M_PI)));
          }
          if (h < 1.3) Picture(wall_a, wall_b, inward, 1.45);
          break;
        }
        case 2: {  // table: top slab, four legs, things on it
          const double h = rng_->Uniform(0.7, 0.78);
          AxisBox({lo.x(), lo.y(), h - 0.04}, {hi.x(), hi.y(), h}, /*skip_bottom=*/false);
          const double l = 0.045;
          for (int i = 0; i < 4; ++i) {
            const double x = (i & 1) ? hi.x() - l - 0.03 : lo.x() + 0.03;
            const double y = (i & 2) ? hi.y() - l - 0.03 : lo.y() + 0.03;
            AxisBox({x, y, 0}, {x + l, y + l, h - 0.04});
          }
          const int items = rng_->UniformInt(1, 3);
          for (int i = 0; i < items; ++i) {
            const double s = rng_->Uniform(0.05, 0.14);
            const Eigen::Vector2d c(rng_->Uniform(lo.x() + s + 0.02, hi.x() - s - 0.02),
                                    rng_->Uniform(lo.y() + s + 0.02, hi.y() - s - 0.02));
            Box({c.x(), c.y(), h + s * 0.9}, {s, s * rng_->Uniform(0.5, 1.0), s * 0.9},
                Yaw(rng_->Uniform(0, M_PI)));
          }
          Picture(wall_a, wall_b, inward, 1.2);
          break;
        }
        case 3: {  // open shelf: two sides, back, boards, items
          const double h = rng_->Uniform(1.2, 2.0), t = 0.025;
          const Eigen::Vector2d a = wall_a + inward * 0.01, b = wall_b + inward * 0.01;
          const Eigen::Vector2d d = inward * depth;
          Slab(a, a + along * t, d, 0, h);
          Slab(b - along * t, b, d, 0, h);
          Slab(a, b, inward * t, 0, h);
          const int boards = static_cast<int>(h / 0.38);
          for (int i = 0; i <= boards; ++i) {
            const double z = std::min(h - t, 0.05 + i * (h - 0.05) / boards);
            Slab(a + along * t, b - along * t, d, z, z + t, /*skip_bottom=*/false);
            if (i < boards && rng_->Bernoulli(0.8)) {
              const double s = rng_->Uniform(0.05, 0.12);
              const double u = rng_->Uniform(t + s, width - t - s);
              const Eigen::Vector2d c = a + along * u + inward * (depth * 0.5);
              Box({c.x(), c.y(), z + t + s}, {s, s * 0.7, s}, Yaw(rng_->Uniform(0, M_PI)));
            }
          }
          break;
        }
        case 4: {  // board leaning against the wall
          const double h = rng_->Uniform(0.9, 1.6);
          const double tilt = rng_->Uniform(0.12, 0.3);
          const Eigen::Vector2d c =
              (wall_a + wall_b) / 2 + inward * (0.02 + std::sin(tilt) * h / 2);
          const double yaw = std::atan2(along.y(), along.x());
          const Eigen::Matrix3d R =
              Yaw(yaw) * Eigen::AngleAxisd(-tilt, Eigen::Vector3d::UnitX()).toRotationMatrix();
          Box({c.x(), c.y(), std::cos(tilt) * h / 2}, {width / 2 * 0.9, 0.012, h / 2}, R, false);
          Picture(wall_a, wall_b, inward, 1.75);
          break;
        }
        default:  // a gap with a picture
          Picture(wall_a, wall_b, inward, rng_->Uniform(0.9, 1.4));
          break;
      }
      pos += width + rng_->Uniform(0.05, 0.35);
    }
  }

  Eigen::Matrix3d Yaw(double a) const {
    return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  }

 private:
  // A vertical slab between two wall-side points, extruded by `d` into the room.
  void Slab(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Eigen::Vector2d& d, double z0,
            double z1, bool skip_bottom = true) {
    const Eigen::Vector2d lo = a.cwiseMin(b).cwiseMin(a + d).cwiseMin(b + d);
    const Eigen::Vector2d hi = a.cwiseMax(b).cwiseMax(a + d).cwiseMax(b + d);
    AxisBox({lo.x(), lo.y(), z0}, {hi.x(), hi.y(), z1}, skip_bottom && z0 <= 0.0);
  }

  // A thin frame on the wall above `bottom`.
  void Picture(const Eigen::Vector2d& wall_a, const Eigen::Vector2d& wall_b,
               const Eigen::Vector2d& inward, double bottom) {
    if (!rng_->Bernoulli(0.7)) return;
    const double len = (wall_b - wall_a).norm();
    const double w = std::min(len * 0.8, rng_->Uniform(0.3, 0.9));
    const double h = rng_->Uniform(0.25, 0.6);
    if (bottom + h > options_.height - 0.1) return;
    const Eigen::Vector2d along = (wall_b - wall_a) / len;
    const Eigen::Vector2d c = wall_a + along * (len / 2) + inward * 0.015;
    const double yaw = std::atan2(along.y(), along.x());
    Box({c.x(), c.y(), bottom + h / 2}, {w / 2, 0.012, h / 2}, Yaw(yaw), false);
  }

  SyntheticScene* scene_;
  Rng* rng_;
  const RoomSceneOptions& options_;
};

}  // namespace

SyntheticScene SyntheticScene::MakeRoom(const RoomSceneOptions& options) {
  SyntheticScene scene;
  scene.texel_m_ = options.texel_m;
  scene.shapes_per_m2_ = options.shapes_per_m2;
  scene.texture_seed_ = MixSeed(options.seed, 0x7e47);
  scene.light_ = Eigen::Vector3d(0.3, -0.2, options.height - 0.2);
  Rng rng(MixSeed(options.seed, 0x5ce4e));
  RoomBuilder b(&scene, &rng, options);
  const double hx = options.size_x / 2, hy = options.size_y / 2, h = options.height;
  // Room shell, seen from inside.
  b.Face({{-hx, -hy, 0}, {hx, -hy, 0}, {hx, hy, 0}, {-hx, hy, 0}}, Eigen::Vector3d::UnitZ());
  b.Face({{-hx, -hy, h}, {hx, -hy, h}, {hx, hy, h}, {-hx, hy, h}}, -Eigen::Vector3d::UnitZ());
  b.Face({{-hx, -hy, 0}, {hx, -hy, 0}, {hx, -hy, h}, {-hx, -hy, h}}, Eigen::Vector3d::UnitY());
  b.Face({{-hx, hy, 0}, {hx, hy, 0}, {hx, hy, h}, {-hx, hy, h}}, -Eigen::Vector3d::UnitY());
  b.Face({{-hx, -hy, 0}, {-hx, hy, 0}, {-hx, hy, h}, {-hx, -hy, h}}, Eigen::Vector3d::UnitX());
  b.Face({{hx, -hy, 0}, {hx, hy, 0}, {hx, hy, h}, {hx, -hy, h}}, -Eigen::Vector3d::UnitX());
  // Furniture along the four walls (counter-clockwise seen from above).
  b.FurnishWall({-hx, -hy}, {1, 0}, {0, 1}, options.size_x);
  b.FurnishWall({hx, -hy}, {0, 1}, {-1, 0}, options.size_y);
  b.FurnishWall({hx, hy}, {-1, 0}, {0, -1}, options.size_x);
  b.FurnishWall({-hx, hy}, {0, -1}, {1, 0}, options.size_y);
  // Columns in two corners.
  for (int corner = 0; corner < 4; ++corner) {
    if (corner % 2 != static_cast<int>(options.seed % 2)) continue;
    const double sx = (corner & 1) ? 1 : -1, sy = (corner & 2) ? 1 : -1;
    const double r = rng.Uniform(0.13, 0.2);
    b.Prism({sx * (hx - r - 0.02), sy * (hy - r - 0.02)}, r, 8, 0, h);
  }
  return scene;
}

}  // namespace ccmd
