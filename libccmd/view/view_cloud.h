#pragma once

// A keyframe's cloud as the browser receives it: at a viewing density, in the keyframe's own
// camera frame (so that a pose update moves it with one matrix), compact and in an order that
// lets the browser draw any fraction of it as an even subsample (its level of detail).
//
// Record layout (little-endian), one per requested keyframe:
//   u16 agent, u8 found (0: not in the dense store, n = 0), u8 reserved (0), u32 keyframe,
//   u32 n, then n x (i16 x, i16 y, i16 z) millimetres, then n x (u8 r, g, b), then zero
//   bytes up to a multiple of 4.
// Points: at most one per cube of `voxel_m` in the camera frame (the first in raster order),
// then shuffled with a permutation seeded by the keyframe's label, at most `max_points`
// (the first of the shuffled order: an even subsample). Points further than 32.7 m on an
// axis do not fit the millimetre range and are left out.

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "libccmd/dense/backprojection.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ViewCloudOptions {
  // The dense store keeps about one point per 1 cm (its voxel); a browser needs less to show
  // the surfaces, and every keyframe overlaps its neighbours.
  double voxel_m = 0.02;
  std::size_t max_points = 30000;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

inline constexpr std::size_t kViewCloudHeaderBytes = 12;

// Appends the record of `id` to `out`; `cloud` null: the "not found" record.
void AppendViewCloud(const GlobalKeyframeId& id, const CameraCloud* cloud,
                     const ViewCloudOptions& options, std::string* out);

struct ViewCloud {
  GlobalKeyframeId id;
  bool found = false;
  std::vector<std::array<std::int16_t, 3>> points_mm;
  std::vector<std::array<std::uint8_t, 3>> colors;
};

// Standard base64 (clouds inlined in the event stream, which carries text).
std::string EncodeBase64(std::string_view bytes);

// Reads records back (tests, benchmarks). Untrusted bytes: a truncated or inconsistent
// record is an error.
StatusOr<std::vector<ViewCloud>> ParseViewClouds(std::string_view bytes);

}  // namespace ccmd
