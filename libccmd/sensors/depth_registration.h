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

// Depth as `camera` would have measured it from a nearby pose: `T_in_out` takes points from
// the wanted camera's frame into the frame of the one that measured `depth_mm` (uint16 mm),
// both with the intrinsics of `camera` (distortion not applied: for the few pixels of a
// camera's motion over a few milliseconds it changes the shift by hundredths of a pixel).
// Each output pixel finds where its point lies in the input, from its own depth (two
// fixed-point steps), takes the depth there bilinearly where the four pixels around are one
// surface and the nearest one elsewhere, and gives that point's depth in the wanted frame.
// Unlike the forward projection above, a sub-pixel shift is kept, no holes open where the
// surface stretches and noise is not biased towards the nearer of overlapping pixels.
cv::Mat DepthFromNearbyPose(const cv::Mat& depth_mm, const PinholeCamera& camera,
                            const Pose& T_in_out);

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
