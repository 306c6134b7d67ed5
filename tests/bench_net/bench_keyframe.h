#pragma once

// The transport benchmarks' keyframe: about `bytes` long, with 1000 keypoints (half linked to
// map points) and opaque RGB-D payload for the rest, so the server parses and accounts a
// realistic message (the paper's average keyframe is 58.8 kB).

#include <cstdint>
#include <vector>

#include "libccmd/util/random.h"
#include "proto/messages.h"

namespace ccmd::bench {

inline std::vector<std::uint8_t> MakeKeyframe(std::uint64_t seed, std::size_t bytes) {
  Rng rng(seed);
  KeyframeMessage m;
  m.id = KeyframeId(static_cast<std::uint32_t>(seed));
  for (int i = 0; i < 1000; ++i) {
    WireKeypoint k;
    k.u = static_cast<float>(rng.Uniform(0, 640));
    k.v = static_cast<float>(rng.Uniform(0, 480));
    k.depth_m = static_cast<float>(rng.Uniform(0.5, 4));
    for (auto& b : k.descriptor) b = static_cast<std::uint8_t>(rng.Next());
    if (i % 2 == 0) k.map_point = MapPointId(static_cast<std::uint32_t>(i));
    m.keypoints.push_back(k);
  }
  const std::size_t base = SerializeKeyframe(m).value().size();
  if (bytes > base + 16) {
    RgbdPayload p;
    p.downsample = 2;
    p.colour_jpeg.resize((bytes - base - 16) * 3 / 4);
    p.depth.resize(bytes - base - 16 - p.colour_jpeg.size());
    for (auto& b : p.colour_jpeg) b = static_cast<std::uint8_t>(rng.Next());
    for (auto& b : p.depth) b = static_cast<std::uint8_t>(rng.Next());
    m.rgbd = std::move(p);
  }
  return SerializeKeyframe(m).value();
}

}  // namespace ccmd::bench
