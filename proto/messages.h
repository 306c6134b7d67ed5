#pragma once

// The data messages: Keyframe (type 16, agent -> server) and PoseUpdate (type 17). The
// byte-by-byte layout is in proto/PROTOCOL.md; this header gives the in-memory form.
//
// Bandwidth is the point of the keyframe format: nothing the server already has is sent
// again. A keypoint linked to a map point carries only the link; its descriptor is not sent
// (the server uses the map point's descriptor, sent once when the map point was new). The
// descriptors sent are those of unlinked keypoints and of the message's new map points.
// Ids are delta-coded varints, keypoints are 8-byte fixed-point records.
//
// Quantisation (Serialize then Parse returns, for each field):
//   pose (quaternion, translation)     each component rounded to float32 (rel. 2^-24)
//   keypoint u, v                      1/8 pixel (error <= 1/16 px); range [-4096, 4096)
//   keypoint angle                     360/256 degrees (error <= 0.703125 deg, modulo 360)
//   keypoint depth                     1 mm (error <= 0.5 mm); 0 = none; > 65.535 m = none
//   new map point position             1 mm per coordinate (error <= 0.5 mm) within
//                                      +-32.767 m of the camera; beyond that the point is
//                                      sent as three float32 metres instead (an escape)
//   depth link pose and information      float32
//   everything else (ids, timestamp, octave, descriptors, links, weights, RGB-D bytes): exact

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "libccmd/util/ids.h"
#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

using OrbDescriptor = std::array<std::uint8_t, 32>;

// T_world_cam of the agent's own map: unit quaternion (x, y, z, w) and translation (metres).
struct WirePose {
  std::array<double, 4> q_xyzw{0, 0, 0, 1};
  std::array<double, 3> t{0, 0, 0};
};

struct WireKeypoint {
  float u = 0;  // pixels, undistorted
  float v = 0;
  std::uint8_t octave = 0;              // pyramid level
  float angle_deg = 0;                  // orientation, any value (sent modulo 360)
  float depth_m = 0;                    // measured depth; <= 0 or not finite: none
  std::optional<MapPointId> map_point;  // the map point this keypoint observes
  // Sent only when map_point is empty. After Parse, zero for linked keypoints.
  OrbDescriptor descriptor{};
};

// A map point the server has not seen yet, sent with the first keyframe that observes it.
struct NewMapPoint {
  MapPointId id;
  std::array<float, 3> p_cam{0, 0, 0};  // position in this keyframe's camera frame, metres
  OrbDescriptor descriptor{};           // the map point's representative descriptor
};

struct CovisibilityLink {
  KeyframeId keyframe;
  std::uint32_t weight = 0;  // map points shared with that keyframe
};

// A dense depth alignment the agent measured between this keyframe and an earlier one it sent
// (libccmd/tracking/depth_alignment.h): T_this_other, with the information of the relative
// pose's perturbation (rotation, then translation) as the upper triangle of the 6x6 matrix,
// row by row (21 values), already weighted as the agent's local BA uses it.
struct DepthLink {
  KeyframeId keyframe;
  WirePose T_this_other;
  std::array<float, 21> information{};
};

// Optional dense payload. The depth bytes are a self-describing libccmd/codec bitstream;
// the two fields before them let a receiver route it without decoding.
struct RgbdPayload {
  std::uint8_t downsample = 1;  // 1, 2 or 4: the images are 1/downsample of full size (r)
  std::uint8_t depth_mode = 0;  // libccmd/codec DepthMode value
  std::vector<std::uint8_t> colour_jpeg;
  std::vector<std::uint8_t> depth;
};

// A map segment this young is too young to relocalise in (ORB-SLAM resets such a map):
// KeyframeMessage::restart.
inline constexpr std::uint32_t kYoungSegmentKeyframes = 5;

struct KeyframeMessage {
  KeyframeId id;
  double timestamp = 0;  // seconds
  WirePose T_world_cam;
  std::optional<KeyframeId> parent;  // spanning-tree parent; empty for an agent's first
  // Flag bit 3: the first keyframe of a map segment the agent started after losing tracking.
  // Its pose continues from the last tracked frame's (a guess), and it shares no map points
  // with the agent's earlier keyframes.
  bool restart = false;
  // Flag bit 4, only with bit 3: a reset. The segment before was too young to relocalise in
  // (fewer than kYoungSegmentKeyframes keyframes), so the agent started again at once, at the
  // frame right after the last one it tracked: the pose is as good as tracking across a frame.
  bool reset = false;
  std::vector<WireKeypoint> keypoints;
  std::vector<NewMapPoint> new_map_points;
  std::vector<CovisibilityLink> covisibility;
  std::vector<DepthLink> depth_links;  // flag bit 2; empty: the section is absent
  std::optional<RgbdPayload> rgbd;
};

struct PoseUpdateEntry {
  KeyframeId keyframe;
  WirePose T_world_cam;
};

struct PoseUpdateMessage {
  std::vector<PoseUpdateEntry> entries;
};

// Limits a receiver applies before allocating (every count is also checked against the
// bytes actually present).
struct MessageLimits {
  std::uint32_t max_keypoints = 65535;
  std::uint32_t max_new_map_points = 65535;
  std::uint32_t max_covisibility = 65535;
  std::uint32_t max_depth_links = 64;
  std::uint32_t max_colour_bytes = 8u << 20;
  std::uint32_t max_depth_bytes = 8u << 20;
  std::uint32_t max_pose_updates = 1u << 20;
};

// Bytes of a serialized keyframe by part, for bandwidth accounting. map_points counts the
// per-keypoint links and the new map points' ids and positions; their descriptors are in
// descriptors. other: flags, ids, timestamp, parent, covisibility, RGB-D sizes.
struct KeyframeSizeBreakdown {
  std::size_t pose = 0;
  std::size_t keypoints = 0;
  std::size_t descriptors = 0;
  std::size_t map_points = 0;
  std::size_t colour = 0;
  std::size_t depth = 0;
  std::size_t other = 0;
  std::size_t total() const {
    return pose + keypoints + descriptors + map_points + colour + depth + other;
  }
};

// Fails (kInvalidArgument) on values the format cannot carry: non-finite pose or position,
// keypoint coordinates outside [-4096, 4096), a downsample other than 1, 2, 4, more entries
// than the default limits.
StatusOr<std::vector<std::uint8_t>> SerializeKeyframe(const KeyframeMessage& message,
                                                      KeyframeSizeBreakdown* breakdown = nullptr);
StatusOr<KeyframeMessage> ParseKeyframe(ByteSpan payload, const MessageLimits& limits = {});

StatusOr<std::vector<std::uint8_t>> SerializePoseUpdate(const PoseUpdateMessage& message);
StatusOr<PoseUpdateMessage> ParsePoseUpdate(ByteSpan payload, const MessageLimits& limits = {});

// Wire quantisation of single values, exposed for tests and for code that wants to know
// what the receiver will see.
std::int16_t QuantizePixel(float u);  // 1/8 px, precondition: in range
float DequantizePixel(std::int16_t q);
std::uint8_t QuantizeAngle(float degrees);  // 256 steps per turn
float DequantizeAngle(std::uint8_t q);
std::uint16_t QuantizeDepthMm(float metres);  // 0 = none
float DequantizeDepthMm(std::uint16_t mm);

}  // namespace ccmd
