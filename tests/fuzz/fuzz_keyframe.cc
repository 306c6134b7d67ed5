// Fuzz target: the keyframe and pose-update parsers. An accepted message must survive a
// second trip through the wire unchanged (its values are already on the quantisation grid).

#include "proto/messages.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  KeyframeMessage m;
  m.id = KeyframeId(12);
  m.timestamp = 3.5;
  m.parent = KeyframeId(11);
  for (int i = 0; i < 6; ++i) {
    WireKeypoint k;
    k.u = 10.0f * i;
    k.v = 5.0f * i;
    k.depth_m = 1.5f;
    k.descriptor.fill(static_cast<std::uint8_t>(i));
    if (i % 3 == 1) k.map_point = MapPointId(100 + i);
    if (i % 3 == 2) {
      m.new_map_points.push_back({MapPointId(200 + i), {0.1f, 0.2f, 1.5f}, {}});
      k.map_point = MapPointId(200 + i);
    }
    m.keypoints.push_back(k);
  }
  m.new_map_points.push_back({MapPointId(300), {40.0f, 0.0f, 50.0f}, {}});  // float escape
  m.covisibility.push_back({KeyframeId(10), 30});
  m.rgbd = RgbdPayload{2, 7, {0xFF, 0xD8, 0xFF}, {0xD7, 1, 7}};
  PoseUpdateMessage p;
  p.entries.push_back({KeyframeId(5), {}});
  p.entries.push_back({KeyframeId(3), {{0, 0, 0.6, 0.8}, {1, 2, 3}}});
  std::vector<std::uint8_t> pose_seed = *SerializePoseUpdate(p);
  pose_seed.insert(pose_seed.begin(), 1);  // first byte selects the parser
  std::vector<std::uint8_t> keyframe_seed = *SerializeKeyframe(m);
  keyframe_seed.insert(keyframe_seed.begin(), 0);
  return {keyframe_seed, pose_seed};
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  if (size == 0) return 0;
  const ByteSpan payload(data + 1, size - 1);
  if (data[0] % 2 == 0) {
    auto m = ParseKeyframe(payload);
    if (!m.ok()) return 0;
    auto again = SerializeKeyframe(*m);
    if (!again.ok()) fuzz::FuzzFail("an accepted keyframe does not serialise");
    auto back = ParseKeyframe(*again);
    if (!back.ok()) fuzz::FuzzFail("a re-serialised keyframe does not parse");
    auto third = SerializeKeyframe(*back);
    if (!third.ok() || *third != *again) fuzz::FuzzFail("keyframe round trip is not stable");
  } else {
    auto p = ParsePoseUpdate(payload);
    if (!p.ok()) return 0;
    auto again = SerializePoseUpdate(*p);
    if (!again.ok() || !ParsePoseUpdate(*again).ok()) fuzz::FuzzFail("pose update round trip");
  }
  return 0;
}
