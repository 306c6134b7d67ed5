#pragma once

// Colour coding for keyframes: the BGR image is resized to the depth image's size when the
// two differ (e.g. 1920x1080 -> 640x480, so colour and depth pixels correspond), then
// downsampled by the same factor as the depth (r = 1, 0.5, 0.25), then coded as a baseline
// JPEG with libjpeg-turbo's TurboJPEG API (4:2:0 chroma, quality configurable).
//
// Decoding untrusted bytes returns an error: the header's size is checked against a limit
// before anything is allocated, progressive scans are limited and warnings are errors.

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ColourEncodeOptions {
  int quality = 75;    // JPEG quality, 1..100
  int downsample = 1;  // 1, 2 or 4, applied after matching the depth size

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct ColourDecodeOptions {
  std::uint32_t max_pixels = 4096u * 4096u;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// bgr: CV_8UC3. depth_size: the depth image's full size (empty: keep the colour size).
StatusOr<std::vector<std::uint8_t>> EncodeColour(const cv::Mat& bgr, cv::Size depth_size,
                                                 const ColourEncodeOptions& options);

// Returns CV_8UC3 BGR.
StatusOr<cv::Mat> DecodeColour(std::span<const std::uint8_t> jpeg,
                               const ColourDecodeOptions& options = {});

// The colour image EncodeColour codes, before JPEG: for comparisons (PSNR) in tests and
// benchmarks.
StatusOr<cv::Mat> PrepareColour(const cv::Mat& bgr, cv::Size depth_size, int downsample);

}  // namespace ccmd
