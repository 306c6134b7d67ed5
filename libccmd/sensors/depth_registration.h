#pragma once

// Depth registered to colour in software, for cameras whose depth and colour come from
// different sensors without hardware registration (a RealSense D435 over plain UVC/V4L2:
// depth from the left IR imager, 87 x 58 degrees; colour from the RGB imager, 69 x 42
// degrees, about 15 mm to the side). Without it a colour pixel and the depth pixel at the
// same coordinates see different points.
//
// Each depth pixel is back-projected with the depth intrinsics, moved into the colour
// frame and projected with the colour intrinsics. The pixel's whole footprint (its
// corners) is filled, so magnification does not leave cracks, and where several depth
// pixels land on one colour pixel the nearest wins (occlusion).

#include <optional>
#include <string>

#include <opencv2/core/mat.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/io/config.h"  // DepthToColorCalibration and its loader
#include "libccmd/util/status.h"

namespace ccmd {

// Depth (uint16 mm) seen from `color` (intrinsics at the output size). Depth pixels whose
// footprint would cover more than `max_footprint` pixels (grazing surfaces) are skipped.
// The output is the colour image as recorded: with colour distortion, depth lands on the
// raw (distorted) colour pixel, where features are detected and depth is looked up.
cv::Mat RegisterDepthToColor(const cv::Mat& depth_mm, const PinholeCamera& depth_camera,
                             const PinholeCamera& color_camera, const Pose& T_color_depth,
                             int max_footprint = 8);

// RegisterDepthToColor with `calibration`, once the depth image is checked to have the size
// the calibration describes (a recording or camera mode that does not match is an error).
StatusOr<cv::Mat> RegisterDepth(const cv::Mat& depth_mm, const DepthToColorCalibration& calibration,
                                const PinholeCamera& color_camera);

// How well depth registered to a colour image lines up with it: the mean colour gradient
// magnitude (grey levels per pixel, Sobel on a slightly blurred image) at the depth edges, i.e.
// the nearer pixel of every jump of more than 5 % to a farther or missing neighbour, on all four
// sides alike. Depth edges that land on object outlines in colour score high; a wrong offset or
// focal length moves them onto flat colour. Used to check a registration without a pattern.
double EdgeAlignmentScore(const cv::Mat& bgr, const cv::Mat& depth_mm);

}  // namespace ccmd
