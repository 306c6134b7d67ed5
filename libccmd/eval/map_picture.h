#pragma once

// Pictures of a dense map for reports, drawn from the points (no other program needed): a
// top view (orthographic, looking down) and a perspective view from above one side of the
// map, each as two panels: the points' own colours and the colour of the agent that mapped
// them (the label's agent, label.h).
//
// "Up" is the mean up direction of the cameras that mapped it (cameras are held or mounted
// roughly upright; a camera's up is its -y axis), and points higher than the highest camera
// plus a margin are left out: the ceiling would otherwise hide the room. Each point is drawn
// as a square about the map's voxel wide (at least a pixel), nearest surface in front.

#include <limits>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "libccmd/io/ply.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

enum class MapColouring { kRgb, kAgent };

struct MapPictureOptions {
  int panel_width = 640;
  int panel_height = 480;
  double point_size_m = 0.01;     // the dense map's voxel
  double ceiling_margin_m = 0.4;  // kept above the highest camera
  double elevation_deg = 40;      // perspective view: camera above the horizon
  // Perspective view: points in the nearest part of the map (this fraction of its depth) that
  // stand higher than the floor are left out, so the near wall does not hide the room.
  double cutaway_fraction = 0.12;
  double field_of_view_deg = 60;                      // perspective view, horizontal
  cv::Scalar background = cv::Scalar(255, 255, 255);  // BGR
  // Agent id (the label's top byte) -> name and colour (BGR) for the agent panels and legend.
  std::map<int, std::pair<std::string, cv::Scalar>> agents;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// The frame the pictures use: up from the cameras (or -y of the map frame without any), and
// the height above which points are left out (+infinity without cameras).
struct MapViewFrame {
  Eigen::Vector3d up = -Eigen::Vector3d::UnitY();
  double cut_height = std::numeric_limits<double>::infinity();
};
MapViewFrame EstimateMapViewFrame(const Trajectory& cameras, double ceiling_margin_m);

// One panel (CV_8UC3, panel size). Errors: an empty map, agent colouring without labels.
StatusOr<cv::Mat> RenderMapTop(const PointCloud& map, const MapViewFrame& frame,
                               MapColouring colouring, const MapPictureOptions& options);
StatusOr<cv::Mat> RenderMapPerspective(const PointCloud& map, const MapViewFrame& frame,
                                       MapColouring colouring, const MapPictureOptions& options);

// map_top.png and map_view.png in `folder`: each the RGB panel beside the agent panel (the
// RGB panel alone when the map has no labels), with titles and the agents' legend.
Status WriteMapPictures(const PointCloud& map, const Trajectory& cameras,
                        const MapPictureOptions& options, const std::string& folder);

}  // namespace ccmd
