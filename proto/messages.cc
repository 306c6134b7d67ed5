#include "proto/messages.h"

#include <cmath>
#include <string>

namespace ccmd {
namespace {

constexpr std::uint8_t kHasParent = 1u << 0;
constexpr std::uint8_t kHasRgbd = 1u << 1;
constexpr std::uint8_t kHasDepthLinks = 1u << 2;
constexpr std::uint8_t kRestart = 1u << 3;
constexpr std::uint8_t kReset = 1u << 4;  // only with kRestart
constexpr std::uint8_t kKnownFlags = kHasParent | kHasRgbd | kHasDepthLinks | kRestart | kReset;

constexpr std::size_t kPoseBytes = 7 * 4;
constexpr std::size_t kDepthLinkBytes = 1 + kPoseBytes + 21 * 4;
constexpr std::size_t kKeypointBytes = 8;
constexpr std::size_t kDescriptorBytes = 32;
constexpr std::int16_t kPositionEscape = INT16_MIN;
// Smallest encodings, used to check counts against the bytes present before allocating.
constexpr std::size_t kMinNewMapPointBytes = 1 + 6 + kDescriptorBytes;
constexpr std::size_t kMinCovisibilityBytes = 2;
constexpr std::size_t kPoseUpdateEntryBytes = 1 + kPoseBytes;

bool Finite(const WirePose& p) {
  for (double v : p.q_xyzw) {
    if (!std::isfinite(v)) return false;
  }
  for (double v : p.t) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}

void PutPose(const WirePose& p, ByteWriter* w) {
  for (double v : p.q_xyzw) w->PutF32(static_cast<float>(v));
  for (double v : p.t) w->PutF32(static_cast<float>(v));
}

Status ReadPose(ByteReader* r, WirePose* p) {
  for (double& v : p->q_xyzw) {
    float f;
    CCMD_RETURN_IF_ERROR(r->ReadF32(&f));
    v = f;
  }
  for (double& v : p->t) {
    float f;
    CCMD_RETURN_IF_ERROR(r->ReadF32(&f));
    v = f;
  }
  if (!Finite(*p)) return Corrupt("pose has a non-finite component");
  return Status::Ok();
}

bool PixelInRange(float u) { return std::isfinite(u) && u >= -4096.0f && u < 4096.0f; }

// Reads a count and checks it against the limit and against the bytes left, assuming each
// element takes at least min_bytes.
Status ReadCount(ByteReader* r, std::uint32_t limit, std::size_t min_bytes, const char* what,
                 std::size_t* count) {
  std::uint64_t n;
  CCMD_RETURN_IF_ERROR(r->ReadVarintAtMost(limit, &n, what));
  if (n * min_bytes > r->remaining()) {
    return Corrupt(std::string(what) + " " + std::to_string(n) + " needs at least " +
                   std::to_string(n * min_bytes) + " bytes, " + std::to_string(r->remaining()) +
                   " left");
  }
  *count = static_cast<std::size_t>(n);
  return Status::Ok();
}

// Applies a signed delta to a 32-bit id, failing if it leaves the id range.
Status ApplyDelta(std::uint64_t base, std::int64_t delta, const char* what, std::uint32_t* id) {
  // base < 2^32, so checking |delta| first keeps the sum from overflowing.
  if (delta > (1ll << 33) || delta < -(1ll << 33)) {
    return Corrupt(std::string(what) + " id delta out of range");
  }
  const std::int64_t value = static_cast<std::int64_t>(base) + delta;
  if (value < 0 || value > 0xFFFFFFFFll) return Corrupt(std::string(what) + " id out of range");
  *id = static_cast<std::uint32_t>(value);
  return Status::Ok();
}

// Reads a signed varint delta and applies it to `base` (ApplyDelta).
Status ReadDelta(ByteReader* r, std::uint64_t base, const char* what, std::uint32_t* id) {
  std::int64_t delta;
  CCMD_RETURN_IF_ERROR(r->ReadSignedVarint(&delta));
  return ApplyDelta(base, delta, what, id);
}

}  // namespace

std::int16_t QuantizePixel(float u) { return static_cast<std::int16_t>(std::lround(u * 8.0f)); }
float DequantizePixel(std::int16_t q) { return static_cast<float>(q) / 8.0f; }

std::uint8_t QuantizeAngle(float degrees) {
  if (!std::isfinite(degrees)) return 0;
  double a = std::fmod(static_cast<double>(degrees), 360.0);
  if (a < 0) a += 360.0;
  return static_cast<std::uint8_t>(std::lround(a * (256.0 / 360.0)) & 0xFF);
}
float DequantizeAngle(std::uint8_t q) { return static_cast<float>(q * (360.0 / 256.0)); }

std::uint16_t QuantizeDepthMm(float metres) {
  if (!std::isfinite(metres) || metres <= 0.0f) return 0;
  const long mm = std::lround(static_cast<double>(metres) * 1000.0);
  if (mm > 65535) return 0;
  return static_cast<std::uint16_t>(mm);
}
float DequantizeDepthMm(std::uint16_t mm) { return static_cast<float>(mm / 1000.0); }

StatusOr<std::vector<std::uint8_t>> SerializeKeyframe(const KeyframeMessage& m,
                                                      KeyframeSizeBreakdown* breakdown) {
  const MessageLimits limits;
  if (!Finite(m.T_world_cam)) return InvalidArgument("keyframe pose is not finite");
  if (!std::isfinite(m.timestamp)) return InvalidArgument("keyframe timestamp is not finite");
  if (m.keypoints.size() > limits.max_keypoints) {
    return InvalidArgument("too many keypoints: " + std::to_string(m.keypoints.size()));
  }
  if (m.new_map_points.size() > limits.max_new_map_points) {
    return InvalidArgument("too many new map points: " + std::to_string(m.new_map_points.size()));
  }
  if (m.covisibility.size() > limits.max_covisibility) {
    return InvalidArgument("too many covisibility links: " + std::to_string(m.covisibility.size()));
  }
  if (m.depth_links.size() > limits.max_depth_links) {
    return InvalidArgument("too many depth links: " + std::to_string(m.depth_links.size()));
  }
  if (m.rgbd) {
    if (m.rgbd->downsample != 1 && m.rgbd->downsample != 2 && m.rgbd->downsample != 4) {
      return InvalidArgument("RGB-D downsample must be 1, 2 or 4");
    }
    if (m.rgbd->colour_jpeg.size() > limits.max_colour_bytes ||
        m.rgbd->depth.size() > limits.max_depth_bytes) {
      return InvalidArgument("RGB-D payload larger than the receiver's limits");
    }
  }
  for (const WireKeypoint& k : m.keypoints) {
    if (!PixelInRange(k.u) || !PixelInRange(k.v)) {
      return InvalidArgument("keypoint coordinates outside [-4096, 4096)");
    }
  }

  KeyframeSizeBreakdown b;
  ByteWriter w(64 + m.keypoints.size() * (kKeypointBytes + 2 + kDescriptorBytes / 2));
  std::size_t mark = 0;
  auto account = [&](std::size_t* part) {
    *part += w.size() - mark;
    mark = w.size();
  };

  w.PutU8(static_cast<std::uint8_t>((m.parent ? kHasParent : 0) | (m.rgbd ? kHasRgbd : 0) |
                                    (m.depth_links.empty() ? 0 : kHasDepthLinks) |
                                    (m.restart ? kRestart : 0) |
                                    (m.restart && m.reset ? kReset : 0)));
  w.PutVarint(m.id.value());
  w.PutF64(m.timestamp);
  account(&b.other);
  PutPose(m.T_world_cam, &w);
  account(&b.pose);
  if (m.parent) {
    w.PutSignedVarint(static_cast<std::int64_t>(m.parent->value()) - m.id.value());
  }
  w.PutVarint(m.keypoints.size());
  account(&b.other);

  for (const WireKeypoint& k : m.keypoints) {
    w.PutI16(QuantizePixel(k.u));
    w.PutI16(QuantizePixel(k.v));
    w.PutU8(k.octave);
    w.PutU8(QuantizeAngle(k.angle_deg));
    w.PutU16(QuantizeDepthMm(k.depth_m));
  }
  account(&b.keypoints);

  // Links: 0 = none, otherwise 1 + zigzag(id - previous linked id).
  std::int64_t previous = 0;
  for (const WireKeypoint& k : m.keypoints) {
    if (!k.map_point) {
      w.PutVarint(0);
      continue;
    }
    const std::int64_t id = k.map_point->value();
    w.PutVarint(ZigzagEncode(id - previous) + 1);
    previous = id;
  }
  account(&b.map_points);
  for (const WireKeypoint& k : m.keypoints) {
    if (!k.map_point) w.PutBytes(k.descriptor.data(), k.descriptor.size());
  }
  account(&b.descriptors);

  w.PutVarint(m.new_map_points.size());
  account(&b.other);
  previous = 0;
  for (const NewMapPoint& p : m.new_map_points) {
    for (float c : p.p_cam) {
      if (!std::isfinite(c)) return InvalidArgument("new map point position is not finite");
    }
    const std::int64_t id = p.id.value();
    w.PutSignedVarint(id - previous);
    previous = id;
    long mm[3];
    bool fits = true;
    for (int i = 0; i < 3; ++i) {
      const double v = std::round(static_cast<double>(p.p_cam[i]) * 1000.0);
      fits = fits && v >= -32767.0 && v <= 32767.0;
      mm[i] = fits ? static_cast<long>(v) : 0;
    }
    if (fits) {
      for (long v : mm) w.PutI16(static_cast<std::int16_t>(v));
    } else {
      w.PutI16(kPositionEscape);
      for (float c : p.p_cam) w.PutF32(c);
    }
    account(&b.map_points);
    w.PutBytes(p.descriptor.data(), p.descriptor.size());
    account(&b.descriptors);
  }

  w.PutVarint(m.covisibility.size());
  for (const CovisibilityLink& c : m.covisibility) {
    w.PutSignedVarint(static_cast<std::int64_t>(c.keyframe.value()) - m.id.value());
    w.PutVarint(c.weight);
  }
  account(&b.other);

  if (!m.depth_links.empty()) {
    w.PutVarint(m.depth_links.size());
    for (const DepthLink& l : m.depth_links) {
      if (!Finite(l.T_this_other)) return InvalidArgument("depth link pose is not finite");
      for (float v : l.information) {
        if (!std::isfinite(v)) return InvalidArgument("depth link information is not finite");
      }
      w.PutSignedVarint(static_cast<std::int64_t>(l.keyframe.value()) - m.id.value());
      PutPose(l.T_this_other, &w);
      for (float v : l.information) w.PutF32(v);
    }
    account(&b.other);
  }

  if (m.rgbd) {
    w.PutU8(m.rgbd->downsample);
    w.PutU8(m.rgbd->depth_mode);
    w.PutVarint(m.rgbd->colour_jpeg.size());
    account(&b.other);
    w.PutBytes(m.rgbd->colour_jpeg.data(), m.rgbd->colour_jpeg.size());
    account(&b.colour);
    w.PutVarint(m.rgbd->depth.size());
    account(&b.other);
    w.PutBytes(m.rgbd->depth.data(), m.rgbd->depth.size());
    account(&b.depth);
  }
  if (breakdown) *breakdown = b;
  return w.Take();
}

StatusOr<KeyframeMessage> ParseKeyframe(ByteSpan payload, const MessageLimits& limits) {
  ByteReader r(payload);
  KeyframeMessage m;
  std::uint8_t flags;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&flags));
  if (flags & ~kKnownFlags) {
    return Corrupt("keyframe has unknown flag bits " + std::to_string(flags & ~kKnownFlags));
  }
  std::uint32_t id;
  CCMD_RETURN_IF_ERROR(r.ReadVarint32(&id));
  m.id = KeyframeId(id);
  CCMD_RETURN_IF_ERROR(r.ReadF64(&m.timestamp));
  if (!std::isfinite(m.timestamp)) return Corrupt("keyframe timestamp is not finite");
  CCMD_RETURN_IF_ERROR(ReadPose(&r, &m.T_world_cam));
  m.restart = (flags & kRestart) != 0;
  m.reset = (flags & kReset) != 0;
  if (m.reset && !m.restart) return Corrupt("keyframe is a reset but no restart");
  if (flags & kHasParent) {
    std::uint32_t parent;
    CCMD_RETURN_IF_ERROR(ReadDelta(&r, id, "parent keyframe", &parent));
    m.parent = KeyframeId(parent);
  }

  std::size_t n;
  // Each keypoint takes its record and at least one link byte.
  CCMD_RETURN_IF_ERROR(
      ReadCount(&r, limits.max_keypoints, kKeypointBytes + 1, "keypoint count", &n));
  m.keypoints.resize(n);
  for (WireKeypoint& k : m.keypoints) {
    std::int16_t u, v;
    std::uint8_t angle;
    std::uint16_t depth;
    CCMD_RETURN_IF_ERROR(r.ReadI16(&u));
    CCMD_RETURN_IF_ERROR(r.ReadI16(&v));
    CCMD_RETURN_IF_ERROR(r.ReadU8(&k.octave));
    CCMD_RETURN_IF_ERROR(r.ReadU8(&angle));
    CCMD_RETURN_IF_ERROR(r.ReadU16(&depth));
    k.u = DequantizePixel(u);
    k.v = DequantizePixel(v);
    k.angle_deg = DequantizeAngle(angle);
    k.depth_m = DequantizeDepthMm(depth);
  }
  std::uint64_t previous = 0;
  std::size_t unlinked = 0;
  for (WireKeypoint& k : m.keypoints) {
    std::uint64_t code;
    CCMD_RETURN_IF_ERROR(r.ReadVarint(&code));
    if (code == 0) {
      ++unlinked;
      continue;
    }
    std::uint32_t point;
    CCMD_RETURN_IF_ERROR(ApplyDelta(previous, ZigzagDecode(code - 1), "map point", &point));
    k.map_point = MapPointId(point);
    previous = point;
  }
  if (unlinked * kDescriptorBytes > r.remaining()) {
    return Corrupt("descriptors of " + std::to_string(unlinked) + " unlinked keypoints need " +
                   std::to_string(unlinked * kDescriptorBytes) + " bytes, " +
                   std::to_string(r.remaining()) + " left");
  }
  for (WireKeypoint& k : m.keypoints) {
    if (!k.map_point) CCMD_RETURN_IF_ERROR(r.ReadBytes(kDescriptorBytes, k.descriptor.data()));
  }

  CCMD_RETURN_IF_ERROR(
      ReadCount(&r, limits.max_new_map_points, kMinNewMapPointBytes, "new map point count", &n));
  m.new_map_points.resize(n);
  previous = 0;
  for (NewMapPoint& p : m.new_map_points) {
    std::uint32_t point;
    CCMD_RETURN_IF_ERROR(ReadDelta(&r, previous, "new map point", &point));
    p.id = MapPointId(point);
    previous = point;
    std::int16_t x;
    CCMD_RETURN_IF_ERROR(r.ReadI16(&x));
    if (x == kPositionEscape) {
      for (float& c : p.p_cam) CCMD_RETURN_IF_ERROR(r.ReadF32(&c));
      for (float c : p.p_cam) {
        if (!std::isfinite(c)) return Corrupt("new map point position is not finite");
      }
    } else {
      std::int16_t y, z;
      CCMD_RETURN_IF_ERROR(r.ReadI16(&y));
      CCMD_RETURN_IF_ERROR(r.ReadI16(&z));
      p.p_cam = {x / 1000.0f, y / 1000.0f, z / 1000.0f};
    }
    CCMD_RETURN_IF_ERROR(r.ReadBytes(kDescriptorBytes, p.descriptor.data()));
  }

  CCMD_RETURN_IF_ERROR(
      ReadCount(&r, limits.max_covisibility, kMinCovisibilityBytes, "covisibility count", &n));
  m.covisibility.resize(n);
  for (CovisibilityLink& c : m.covisibility) {
    std::uint32_t other;
    CCMD_RETURN_IF_ERROR(ReadDelta(&r, id, "covisible keyframe", &other));
    c.keyframe = KeyframeId(other);
    CCMD_RETURN_IF_ERROR(r.ReadVarint32(&c.weight));
  }

  if (flags & kHasDepthLinks) {
    CCMD_RETURN_IF_ERROR(
        ReadCount(&r, limits.max_depth_links, kDepthLinkBytes, "depth link count", &n));
    if (n == 0) return Corrupt("depth link section without links");
    m.depth_links.resize(n);
    for (DepthLink& l : m.depth_links) {
      std::uint32_t other;
      CCMD_RETURN_IF_ERROR(ReadDelta(&r, id, "depth link keyframe", &other));
      l.keyframe = KeyframeId(other);
      CCMD_RETURN_IF_ERROR(ReadPose(&r, &l.T_this_other));
      for (float& v : l.information) {
        CCMD_RETURN_IF_ERROR(r.ReadF32(&v));
        if (!std::isfinite(v)) return Corrupt("depth link information is not finite");
      }
    }
  }

  if (flags & kHasRgbd) {
    RgbdPayload& rgbd = m.rgbd.emplace();
    CCMD_RETURN_IF_ERROR(r.ReadU8(&rgbd.downsample));
    if (rgbd.downsample != 1 && rgbd.downsample != 2 && rgbd.downsample != 4) {
      return Corrupt("RGB-D downsample " + std::to_string(rgbd.downsample) + " is not 1, 2 or 4");
    }
    CCMD_RETURN_IF_ERROR(r.ReadU8(&rgbd.depth_mode));
    std::uint64_t size;
    ByteSpan bytes;
    CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(limits.max_colour_bytes, &size, "colour size"));
    CCMD_RETURN_IF_ERROR(r.ReadBytes(size, &bytes));
    rgbd.colour_jpeg.assign(bytes.begin(), bytes.end());
    CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(limits.max_depth_bytes, &size, "depth size"));
    CCMD_RETURN_IF_ERROR(r.ReadBytes(size, &bytes));
    rgbd.depth.assign(bytes.begin(), bytes.end());
  }
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  return m;
}

StatusOr<std::vector<std::uint8_t>> SerializePoseUpdate(const PoseUpdateMessage& m) {
  if (m.entries.size() > MessageLimits().max_pose_updates) {
    return InvalidArgument("too many pose updates: " + std::to_string(m.entries.size()));
  }
  ByteWriter w(4 + m.entries.size() * (kPoseBytes + 2));
  w.PutVarint(m.entries.size());
  std::int64_t previous = 0;
  for (const PoseUpdateEntry& e : m.entries) {
    if (!Finite(e.T_world_cam)) return InvalidArgument("pose update is not finite");
    const std::int64_t id = e.keyframe.value();
    w.PutSignedVarint(id - previous);
    previous = id;
    PutPose(e.T_world_cam, &w);
  }
  return w.Take();
}

StatusOr<PoseUpdateMessage> ParsePoseUpdate(ByteSpan payload, const MessageLimits& limits) {
  ByteReader r(payload);
  PoseUpdateMessage m;
  std::size_t n;
  CCMD_RETURN_IF_ERROR(
      ReadCount(&r, limits.max_pose_updates, kPoseUpdateEntryBytes, "pose update count", &n));
  m.entries.resize(n);
  std::uint64_t previous = 0;
  for (PoseUpdateEntry& e : m.entries) {
    std::uint32_t id;
    CCMD_RETURN_IF_ERROR(ReadDelta(&r, previous, "pose update keyframe", &id));
    e.keyframe = KeyframeId(id);
    previous = id;
    CCMD_RETURN_IF_ERROR(ReadPose(&r, &e.T_world_cam));
  }
  CCMD_RETURN_IF_ERROR(r.ExpectEnd());
  return m;
}

}  // namespace ccmd
