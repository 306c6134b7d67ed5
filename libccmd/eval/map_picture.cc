#include "libccmd/eval/map_picture.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>
#include <opencv2/imgproc.hpp>

#include "libccmd/dense/label.h"
#include "libccmd/eval/plot.h"
#include "libccmd/util/file_util.h"

namespace ccmd {

namespace {

constexpr int kTitleHeight = 34;

// Horizontal axes: e1 along the map's largest horizontal spread, e2 = up x e1.
void HorizontalAxes(const PointCloud& map, const Eigen::Vector3d& up, Eigen::Vector3d* e1,
                    Eigen::Vector3d* e2) {
  Eigen::Vector3d any =
      std::abs(up.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  Eigen::Vector3d a = (any - any.dot(up) * up).normalized();
  Eigen::Vector3d b = up.cross(a);
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  Eigen::Matrix2d cov = Eigen::Matrix2d::Zero();
  const std::size_t step = std::max<std::size_t>(1, map.size() / 20000);
  std::size_t n = 0;
  for (std::size_t i = 0; i < map.size(); i += step, ++n) {
    const Eigen::Vector3d p = map.points[i].cast<double>();
    mean += Eigen::Vector2d(p.dot(a), p.dot(b));
  }
  mean /= static_cast<double>(std::max<std::size_t>(1, n));
  for (std::size_t i = 0; i < map.size(); i += step) {
    const Eigen::Vector3d p = map.points[i].cast<double>();
    const Eigen::Vector2d d = Eigen::Vector2d(p.dot(a), p.dot(b)) - mean;
    cov += d * d.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> solver(cov);
  const Eigen::Vector2d major = solver.eigenvectors().col(1);
  *e1 = (major.x() * a + major.y() * b).normalized();
  *e2 = up.cross(*e1);
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(q * (v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

cv::Vec3b PointColour(const PointCloud& map, std::size_t i, MapColouring colouring,
                      const MapPictureOptions& o) {
  if (colouring == MapColouring::kRgb) {
    if (map.colors.empty()) return cv::Vec3b(90, 90, 90);
    const auto& c = map.colors[i];
    return cv::Vec3b(c[2], c[1], c[0]);
  }
  const auto it = o.agents.find(DecodeLabel(map.labels[i]).agent.value());
  const cv::Scalar s = it != o.agents.end() ? it->second.second : cv::Scalar(150, 150, 150);
  return cv::Vec3b(static_cast<uchar>(s[0]), static_cast<uchar>(s[1]), static_cast<uchar>(s[2]));
}

Status CheckMap(const PointCloud& map, MapColouring colouring, const MapPictureOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (map.size() == 0) return InvalidArgument("map picture: the map has no points");
  if (colouring == MapColouring::kAgent && map.labels.size() != map.size()) {
    return InvalidArgument("map picture: colouring by agent needs the points' labels");
  }
  return Status::Ok();
}

// Draws a square of half-width r at (x, y) where `depth` is nearer than the buffer's.
void Splat(cv::Mat* image, cv::Mat* zbuffer, int x, int y, int r, float depth,
           const cv::Vec3b& colour) {
  for (int v = std::max(0, y - r); v <= std::min(image->rows - 1, y + r); ++v) {
    for (int u = std::max(0, x - r); u <= std::min(image->cols - 1, x + r); ++u) {
      float& z = zbuffer->at<float>(v, u);
      if (depth < z) {
        z = depth;
        image->at<cv::Vec3b>(v, u) = colour;
      }
    }
  }
}

}  // namespace

Status MapPictureOptions::Validate() const {
  if (panel_width < 16 || panel_height < 16 || panel_width > 8192 || panel_height > 8192) {
    return InvalidArgument("map picture: panels must be 16 to 8192 pixels wide and high");
  }
  if (!(point_size_m > 0)) return InvalidArgument("map picture: point size must be > 0");
  if (!(ceiling_margin_m >= 0)) return InvalidArgument("map picture: ceiling margin must be >= 0");
  if (!(elevation_deg > 0 && elevation_deg < 90))
    return InvalidArgument("map picture: elevation must be in (0, 90)");
  if (!(field_of_view_deg > 1 && field_of_view_deg < 170)) {
    return InvalidArgument("map picture: field of view must be in (1, 170) degrees");
  }
  if (!(cutaway_fraction >= 0 && cutaway_fraction < 1))
    return InvalidArgument("map picture: cutaway must be in [0, 1)");
  return Status::Ok();
}

void MapPictureOptions::Describe(OptionsWriter* out) const {
  out->Add("panel_width", panel_width);
  out->Add("panel_height", panel_height);
  out->Add("point_size_m", point_size_m);
  out->Add("ceiling_margin_m", ceiling_margin_m);
  out->Add("elevation_deg", elevation_deg);
  out->Add("cutaway_fraction", cutaway_fraction);
  out->Add("field_of_view_deg", field_of_view_deg);
  out->Add("background", std::vector<double>{background[0], background[1], background[2]});
  std::vector<std::string> agents_text;
  for (const auto& [id, name_colour] : agents)
    agents_text.push_back(std::to_string(id) + ":" + name_colour.first);
  out->Add("agents", agents_text);
}

MapViewFrame EstimateMapViewFrame(const Trajectory& cameras, double ceiling_margin_m) {
  MapViewFrame frame;
  if (cameras.empty()) return frame;
  Eigen::Vector3d up = Eigen::Vector3d::Zero();
  for (const StampedPose& p : cameras) up -= p.T_world_cam.linear().col(1);
  if (up.norm() < 1e-6) return frame;
  frame.up = up.normalized();
  // Cameras that look down (or up) while they move tilt that mean towards where they look.
  // A path that spreads over a plane (a robot, a person walking) is a better guide: its
  // normal, when it is near the cameras' up.
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const StampedPose& p : cameras) mean += p.T_world_cam.translation();
  mean /= static_cast<double>(cameras.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const StampedPose& p : cameras) {
    const Eigen::Vector3d d = p.T_world_cam.translation() - mean;
    cov += d * d.transpose() / static_cast<double>(cameras.size());
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(cov);
  const Eigen::Vector3d l = solver.eigenvalues();  // ascending
  Eigen::Vector3d normal = solver.eigenvectors().col(0);
  if (normal.dot(frame.up) < 0) normal = -normal;
  constexpr double kMinSpreadM = 0.2;
  if (l(1) > 6 * l(0) && std::sqrt(l(1)) > kMinSpreadM &&
      normal.dot(frame.up) > std::cos(M_PI / 4)) {
    frame.up = normal;
  }
  double highest = -std::numeric_limits<double>::infinity();
  for (const StampedPose& p : cameras)
    highest = std::max(highest, p.T_world_cam.translation().dot(frame.up));
  frame.cut_height = highest + ceiling_margin_m;
  return frame;
}

StatusOr<cv::Mat> RenderMapTop(const PointCloud& map, const MapViewFrame& frame,
                               MapColouring colouring, const MapPictureOptions& o) {
  CCMD_RETURN_IF_ERROR(CheckMap(map, colouring, o));
  Eigen::Vector3d e1, e2;
  HorizontalAxes(map, frame.up, &e1, &e2);
  std::vector<double> xs, ys;
  std::vector<std::size_t> shown;
  for (std::size_t i = 0; i < map.size(); ++i) {
    const Eigen::Vector3d p = map.points[i].cast<double>();
    if (p.dot(frame.up) > frame.cut_height) continue;
    shown.push_back(i);
    xs.push_back(p.dot(e1));
    ys.push_back(p.dot(e2));
  }
  cv::Mat image(o.panel_height, o.panel_width, CV_8UC3, o.background);
  if (shown.empty()) return image;
  // Bounds without the stray 0.5% on each side, and a margin.
  const double x0 = Percentile(xs, 0.005), x1 = Percentile(xs, 0.995);
  const double y0 = Percentile(ys, 0.005), y1 = Percentile(ys, 0.995);
  const double scale = 0.94 * std::min(o.panel_width / std::max(1e-6, x1 - x0),
                                       o.panel_height / std::max(1e-6, y1 - y0));
  const double cx = 0.5 * (x0 + x1), cy = 0.5 * (y0 + y1);
  const int r = std::max(0, static_cast<int>(std::lround(o.point_size_m * scale / 2)));
  cv::Mat zbuffer(o.panel_height, o.panel_width, CV_32F,
                  cv::Scalar(std::numeric_limits<float>::infinity()));
  for (std::size_t j = 0; j < shown.size(); ++j) {
    const std::size_t i = shown[j];
    const int u = static_cast<int>(std::lround(o.panel_width / 2.0 + (xs[j] - cx) * scale));
    const int v = static_cast<int>(std::lround(o.panel_height / 2.0 - (ys[j] - cy) * scale));
    // Seen from above: the highest point is in front.
    const float depth = -static_cast<float>(map.points[i].cast<double>().dot(frame.up));
    Splat(&image, &zbuffer, u, v, r, depth, PointColour(map, i, colouring, o));
  }
  return image;
}

StatusOr<cv::Mat> RenderMapPerspective(const PointCloud& map, const MapViewFrame& frame,
                                       MapColouring colouring, const MapPictureOptions& o) {
  CCMD_RETURN_IF_ERROR(CheckMap(map, colouring, o));
  Eigen::Vector3d e1, e2;
  HorizontalAxes(map, frame.up, &e1, &e2);
  std::vector<double> xs, ys, hs;
  for (const Eigen::Vector3f& pf : map.points) {
    const Eigen::Vector3d p = pf.cast<double>();
    if (p.dot(frame.up) > frame.cut_height) continue;
    xs.push_back(p.dot(e1));
    ys.push_back(p.dot(e2));
    hs.push_back(p.dot(frame.up));
  }
  cv::Mat image(o.panel_height, o.panel_width, CV_8UC3, o.background);
  if (xs.empty()) return image;
  const double x0 = Percentile(xs, 0.01), x1 = Percentile(xs, 0.99);
  const double y0 = Percentile(ys, 0.01), y1 = Percentile(ys, 0.99);
  const double h0 = Percentile(hs, 0.01), h1 = Percentile(hs, 0.99);
  const Eigen::Vector3d target =
      0.5 * (x0 + x1) * e1 + 0.5 * (y0 + y1) * e2 + 0.5 * (h0 + h1) * frame.up;
  const double near_limit = y0 + o.cutaway_fraction * (y1 - y0), floor_limit = h0 + 0.3;
  // Seen across its shorter side (along e2) from above: the long side fills the width.
  const double half_fov = 0.5 * o.field_of_view_deg * M_PI / 180;
  const double distance = 1.1 * 0.5 * (x1 - x0) / std::tan(half_fov) + 0.5 * (y1 - y0);
  const double elevation = o.elevation_deg * M_PI / 180;
  const Eigen::Vector3d eye =
      target - distance * std::cos(elevation) * e2 + distance * std::sin(elevation) * frame.up;
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = z.cross(frame.up).normalized();
  const Eigen::Vector3d y = z.cross(x);
  const double f = 0.5 * o.panel_width / std::tan(half_fov);
  cv::Mat zbuffer(o.panel_height, o.panel_width, CV_32F,
                  cv::Scalar(std::numeric_limits<float>::infinity()));
  for (std::size_t i = 0; i < map.size(); ++i) {
    const Eigen::Vector3d p = map.points[i].cast<double>();
    if (p.dot(frame.up) > frame.cut_height) continue;
    if (p.dot(e2) < near_limit && p.dot(frame.up) > floor_limit) continue;  // the cutaway
    const Eigen::Vector3d d = p - eye;
    const double depth = d.dot(z);
    if (depth < 0.05) continue;
    const int u = static_cast<int>(std::lround(o.panel_width / 2.0 + f * d.dot(x) / depth));
    const int v = static_cast<int>(std::lround(o.panel_height / 2.0 + f * d.dot(y) / depth));
    const int r = std::max(0, static_cast<int>(std::lround(f * o.point_size_m / depth / 2)));
    Splat(&image, &zbuffer, u, v, r, static_cast<float>(depth), PointColour(map, i, colouring, o));
  }
  return image;
}

namespace {

cv::Mat Titled(const cv::Mat& panel, const std::string& title) {
  cv::Mat out(panel.rows + kTitleHeight, panel.cols, CV_8UC3, cv::Scalar(255, 255, 255));
  panel.copyTo(out(cv::Rect(0, kTitleHeight, panel.cols, panel.rows)));
  cv::putText(out, title, cv::Point(8, 23), cv::FONT_HERSHEY_SIMPLEX, 0.6, cv::Scalar(40, 40, 40),
              1, cv::LINE_AA);
  return out;
}

void DrawLegend(cv::Mat* panel, const MapPictureOptions& o) {
  // In the order of the names (agent2 before agent10), not of the ids.
  std::vector<std::pair<std::string, cv::Scalar>> legend;
  for (const auto& [id, named] : o.agents) legend.push_back(named);
  std::sort(legend.begin(), legend.end(), [](const auto& a, const auto& b) {
    return a.first.size() != b.first.size() ? a.first.size() < b.first.size() : a.first < b.first;
  });
  int y = 14;
  for (const auto& named : legend) {
    cv::rectangle(*panel, cv::Rect(10, y - 10, 14, 14), named.second, cv::FILLED);
    cv::putText(*panel, named.first, cv::Point(30, y + 2), cv::FONT_HERSHEY_SIMPLEX, 0.5,
                cv::Scalar(40, 40, 40), 1, cv::LINE_AA);
    y += 20;
  }
}

}  // namespace

Status WriteMapPictures(const PointCloud& map, const Trajectory& cameras,
                        const MapPictureOptions& o, const std::string& folder) {
  CCMD_RETURN_IF_ERROR(o.Validate());
  const MapViewFrame frame = EstimateMapViewFrame(cameras, o.ceiling_margin_m);
  const bool by_agent = map.labels.size() == map.size();
  using Renderer = StatusOr<cv::Mat> (*)(const PointCloud&, const MapViewFrame&, MapColouring,
                                         const MapPictureOptions&);
  const std::pair<Renderer, std::string> views[] = {{&RenderMapTop, "map_top.png"},
                                                    {&RenderMapPerspective, "map_view.png"}};
  for (const auto& [render, name] : views) {
    const std::string what = render == &RenderMapTop ? "top view" : "perspective";
    CCMD_ASSIGN_OR_RETURN(cv::Mat rgb, render(map, frame, MapColouring::kRgb, o));
    cv::Mat picture = Titled(rgb, "Dense map, " + what + ": colour");
    if (by_agent) {
      CCMD_ASSIGN_OR_RETURN(cv::Mat agents, render(map, frame, MapColouring::kAgent, o));
      DrawLegend(&agents, o);
      cv::hconcat(picture, Titled(agents, "by agent"), picture);
    }
    CCMD_RETURN_IF_ERROR(WritePng(picture, JoinPath(folder, name)));
  }
  return Status::Ok();
}

}  // namespace ccmd
