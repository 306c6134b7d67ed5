#pragma once

#include <opencv2/core/mat.hpp>

namespace ccmd {

// One colour + depth frame as every part of the system sees it after loading:
// colour 8-bit BGR (OpenCV order), depth uint16 millimetres with 0 meaning "no depth".
// Colour may be larger than depth (e.g. 1920x1080 with 640x480 depth); consumers that
// need them aligned resize colour to the depth size.
struct RgbdFrame {
  int index = -1;        // position in its sequence (or capture counter for live sources)
  double timestamp = 0;  // seconds: when the colour image was taken (dataset or device time)
  cv::Mat bgr;           // CV_8UC3
  cv::Mat depth_mm;      // CV_16UC1
  // When the depth image was taken, in seconds after the colour image: a sensor whose two
  // streams are not synchronised (a Kinect v1: TUM RGB-D's depth comes 10-15 ms after its
  // colour) sees a moving scene from two poses. 0: taken together.
  double depth_time_offset = 0;
};

}  // namespace ccmd
