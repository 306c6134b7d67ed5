#include "libccmd/eval/plot.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/util/file_util.h"

namespace ccmd {

Status PlotOptions::Validate() const {
  if (width < 64 || height < 64 || width > 8192 || height > 8192) {
    return InvalidArgument("plots must be 64 to 8192 pixels wide and high");
  }
  return Status::Ok();
}

void PlotOptions::Describe(OptionsWriter* out) const {
  out->Add("title", title);
  out->Add("x_label", x_label);
  out->Add("y_label", y_label);
  out->Add("width", width);
  out->Add("height", height);
  out->Add("equal_aspect", equal_aspect);
}
namespace {

constexpr int kLeft = 90, kRight = 30, kTop = 50, kBottom = 70;
const cv::Scalar kBlack(0, 0, 0), kGrey(220, 220, 220), kDark(90, 90, 90);

// 1, 2 or 5 times a power of ten, giving about `target` ticks over [lo, hi].
double NiceStep(double lo, double hi, int target) {
  const double raw = std::max((hi - lo) / target, 1e-12);
  const double base = std::pow(10.0, std::floor(std::log10(raw)));
  for (double m : {1.0, 2.0, 5.0, 10.0}) {
    if (m * base >= raw) return m * base;
  }
  return 10 * base;
}

std::string FormatTick(double v, double step) {
  char text[32];
  const int decimals = step >= 1 ? 0 : static_cast<int>(std::ceil(-std::log10(step) - 1e-9));
  std::snprintf(text, sizeof(text), "%.*f", std::min(decimals, 6), std::abs(v) < 1e-12 ? 0.0 : v);
  return text;
}

void Text(cv::Mat& img, const std::string& s, cv::Point at, double scale = 0.5,
          const cv::Scalar& color = kBlack, bool centred = false) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(s, cv::FONT_HERSHEY_SIMPLEX, scale, 1, &baseline);
  if (centred) at.x -= size.width / 2;
  cv::putText(img, s, at, cv::FONT_HERSHEY_SIMPLEX, scale, color, 1, cv::LINE_AA);
}

struct Axes {
  double x0, x1, y0, y1;
  int w, h;
  cv::Point Map(double x, double y) const {
    const double u = kLeft + (x - x0) / (x1 - x0) * (w - kLeft - kRight);
    const double v = h - kBottom - (y - y0) / (y1 - y0) * (h - kTop - kBottom);
    return cv::Point(static_cast<int>(std::lround(u)), static_cast<int>(std::lround(v)));
  }
};

void DrawFrame(cv::Mat& img, const Axes& a, const PlotOptions& o, bool x_ticks = true) {
  const double xs = NiceStep(a.x0, a.x1, 8), ys = NiceStep(a.y0, a.y1, 6);
  if (x_ticks) {
    for (double x = std::ceil(a.x0 / xs) * xs; x <= a.x1 + 1e-9; x += xs) {
      cv::line(img, a.Map(x, a.y0), a.Map(x, a.y1), kGrey, 1);
      Text(img, FormatTick(x, xs), a.Map(x, a.y0) + cv::Point(0, 20), 0.45, kDark, true);
    }
  }
  for (double y = std::ceil(a.y0 / ys) * ys; y <= a.y1 + 1e-9; y += ys) {
    cv::line(img, a.Map(a.x0, y), a.Map(a.x1, y), kGrey, 1);
    Text(img, FormatTick(y, ys), a.Map(a.x0, y) + cv::Point(-kLeft + 8, 5), 0.45, kDark);
  }
  cv::rectangle(img, a.Map(a.x0, a.y1), a.Map(a.x1, a.y0), kDark, 1);
  Text(img, o.title, cv::Point(a.w / 2, 30), 0.65, kBlack, true);
  Text(img, o.x_label, cv::Point(a.w / 2, a.h - 20), 0.5, kBlack, true);
  // Vertical label written horizontally above the axis (OpenCV has no rotated text).
  Text(img, o.y_label, cv::Point(10, kTop - 12), 0.5, kBlack);
}

void DrawLegend(cv::Mat& img, const std::vector<std::pair<std::string, cv::Scalar>>& entries,
                int width) {
  int y = kTop + 18;
  for (const auto& [label, color] : entries) {
    if (label.empty()) continue;
    const int x = width - kRight - 190;
    cv::rectangle(img, cv::Point(x, y - 10), cv::Point(x + 18, y + 2), color, cv::FILLED);
    Text(img, label, cv::Point(x + 26, y), 0.45);
    y += 20;
  }
}

}  // namespace

cv::Scalar SeriesColor(int index) {
  static const cv::Scalar palette[] = {{200, 80, 30},   {40, 140, 240}, {60, 170, 60},
                                       {50, 50, 210},   {170, 90, 150}, {40, 190, 200},
                                       {120, 120, 120}, {150, 150, 20}};
  return palette[static_cast<std::size_t>(index) % 8];
}

cv::Mat PlotLines(const std::vector<PlotSeries>& series, const PlotOptions& o) {
  cv::Mat img(o.height, o.width, CV_8UC3, cv::Scalar(255, 255, 255));
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const auto& s : series) {
    for (std::size_t i = 0; i < s.x.size() && i < s.y.size(); ++i) {
      if (!std::isfinite(s.x[i]) || !std::isfinite(s.y[i])) continue;
      x0 = std::min(x0, s.x[i]);
      x1 = std::max(x1, s.x[i]);
      y0 = std::min(y0, s.y[i]);
      y1 = std::max(y1, s.y[i]);
    }
  }
  if (x0 > x1) x0 = 0, x1 = 1, y0 = 0, y1 = 1;
  if (x1 - x0 < 1e-9) x0 -= 0.5, x1 += 0.5;
  if (y1 - y0 < 1e-9) y0 -= 0.5, y1 += 0.5;
  const double mx = 0.05 * (x1 - x0), my = 0.05 * (y1 - y0);
  Axes a{x0 - mx, x1 + mx, y0 - my, y1 + my, o.width, o.height};
  if (o.equal_aspect) {
    const double sx = (a.x1 - a.x0) / (o.width - kLeft - kRight),
                 sy = (a.y1 - a.y0) / (o.height - kTop - kBottom);
    const double s = std::max(sx, sy);
    const double cx = (a.x0 + a.x1) / 2, cy = (a.y0 + a.y1) / 2;
    a.x0 = cx - s * (o.width - kLeft - kRight) / 2;
    a.x1 = cx + s * (o.width - kLeft - kRight) / 2;
    a.y0 = cy - s * (o.height - kTop - kBottom) / 2;
    a.y1 = cy + s * (o.height - kTop - kBottom) / 2;
  }
  DrawFrame(img, a, o);
  std::vector<std::pair<std::string, cv::Scalar>> legend;
  for (const auto& s : series) {
    std::vector<cv::Point> pts;
    for (std::size_t i = 0; i < s.x.size() && i < s.y.size(); ++i) {
      if (std::isfinite(s.x[i]) && std::isfinite(s.y[i])) pts.push_back(a.Map(s.x[i], s.y[i]));
    }
    if (s.points) {
      for (const auto& p : pts)
        cv::circle(img, p, s.thickness + 1, s.color, cv::FILLED, cv::LINE_AA);
    } else if (pts.size() > 1) {
      cv::polylines(img, pts, false, s.color, s.thickness, cv::LINE_AA);
    }
    legend.emplace_back(s.label, s.color);
  }
  DrawLegend(img, legend, o.width);
  return img;
}

cv::Mat PlotBars(const std::vector<BarGroup>& groups, const std::vector<std::string>& series_labels,
                 const std::vector<cv::Scalar>& colors, const PlotOptions& o, bool log_scale) {
  cv::Mat img(o.height, o.width, CV_8UC3, cv::Scalar(255, 255, 255));
  double top = 0;
  for (const auto& g : groups) {
    for (double v : g.values) top = std::max(top, log_scale ? std::log10(std::max(v, 1.0)) : v);
  }
  if (top <= 0) top = 1;
  Axes a{0,       static_cast<double>(std::max<std::size_t>(groups.size(), 1)),
         0,       top * 1.1,
         o.width, o.height};
  DrawFrame(img, a, o, /*x_ticks=*/false);
  const std::size_t n = series_labels.size();
  for (std::size_t gi = 0; gi < groups.size(); ++gi) {
    const double slot = 0.8 / std::max<std::size_t>(n, 1);
    for (std::size_t si = 0; si < groups[gi].values.size() && si < n; ++si) {
      const double v = groups[gi].values[si];
      const double h = log_scale ? std::log10(std::max(v, 1.0)) : v;
      const double left = gi + 0.1 + si * slot;
      cv::rectangle(img, a.Map(left, 0), a.Map(left + slot * 0.9, h), colors[si % colors.size()],
                    cv::FILLED);
    }
    Text(img, groups[gi].label, a.Map(gi + 0.5, 0) + cv::Point(0, 20), 0.45, kBlack, true);
  }
  std::vector<std::pair<std::string, cv::Scalar>> legend;
  for (std::size_t si = 0; si < n; ++si)
    legend.emplace_back(series_labels[si], colors[si % colors.size()]);
  DrawLegend(img, legend, o.width);
  return img;
}

Status WritePng(const cv::Mat& image, const std::string& path) {
  std::vector<uchar> bytes;
  try {
    if (!cv::imencode(".png", image, bytes)) return IoError("cannot encode " + path);
  } catch (const cv::Exception& e) {
    return IoError("cannot encode " + path + ": " + e.msg);
  }
  return WriteFileAtomic(
      path, std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
}

}  // namespace ccmd
