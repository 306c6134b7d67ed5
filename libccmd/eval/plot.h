#pragma once

// Small chart renderer for evaluation reports (PNG via OpenCV): line/scatter charts with axes,
// ticks, grid and legend, and grouped bar charts.

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct PlotSeries {
  std::string label;
  std::vector<double> x, y;
  cv::Scalar color = cv::Scalar(200, 80, 30);  // BGR
  int thickness = 2;
  bool points = false;  // markers instead of a line
};

struct PlotOptions {
  std::string title, x_label, y_label;
  int width = 900, height = 600;
  bool equal_aspect = false;  // same scale on both axes (top views of trajectories)

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

cv::Mat PlotLines(const std::vector<PlotSeries>& series, const PlotOptions& options);

struct BarGroup {
  std::string label;           // one per category on the x axis
  std::vector<double> values;  // one per series
};
cv::Mat PlotBars(const std::vector<BarGroup>& groups, const std::vector<std::string>& series_labels,
                 const std::vector<cv::Scalar>& colors, const PlotOptions& options,
                 bool log_scale = false);

// A distinct colour per index (agents).
cv::Scalar SeriesColor(int index);

Status WritePng(const cv::Mat& image, const std::string& path);

}  // namespace ccmd
