#include "libccmd/view/view_cloud.h"

#include <cmath>
#include <cstring>
#include <numeric>
#include <unordered_set>

#include "libccmd/util/random.h"

namespace ccmd {

namespace {

constexpr double kMaxMillimetres = 32767;

void PutLe(std::uint64_t v, int bytes, std::string* out) {
  for (int i = 0; i < bytes; ++i) out->push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}

std::uint64_t GetLe(std::string_view bytes, std::size_t at, int n) {
  std::uint64_t v = 0;
  for (int i = 0; i < n; ++i)
    v |= static_cast<std::uint64_t>(static_cast<std::uint8_t>(bytes[at + i])) << (8 * i);
  return v;
}

// Indices of the points kept at the viewing density, in the order they are sent.
std::vector<std::uint32_t> ViewOrder(const GlobalKeyframeId& id, const CameraCloud& cloud,
                                     const ViewCloudOptions& options) {
  std::vector<std::uint32_t> kept;
  kept.reserve(cloud.size());
  std::unordered_set<std::uint64_t> voxels;
  voxels.reserve(cloud.size());
  const double inv = 1.0 / options.voxel_m;
  for (std::uint32_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f& p = cloud.points[i];
    if (!p.allFinite() || (p.cast<double>() * 1e3).cwiseAbs().maxCoeff() > kMaxMillimetres)
      continue;
    std::uint64_t key = 0;
    for (int a = 0; a < 3; ++a) {
      key =
          (key << 21) | (static_cast<std::uint64_t>(std::floor(p[a] * inv) + (1 << 20)) & 0x1fffff);
    }
    if (voxels.insert(key).second) kept.push_back(i);
  }
  // Fisher-Yates with a seed of the keyframe: the same cloud is always sent in the same order.
  Rng rng(MixSeed(id.agent.value(), id.keyframe.value()));
  for (std::size_t i = kept.size(); i > 1; --i) {
    const std::size_t j = static_cast<std::size_t>(rng.UniformInt(0, static_cast<int>(i - 1)));
    std::swap(kept[i - 1], kept[j]);
  }
  if (kept.size() > options.max_points) kept.resize(options.max_points);
  return kept;
}

}  // namespace

Status ViewCloudOptions::Validate() const {
  if (!(voxel_m >= 0.001 && voxel_m <= 1.0))
    return InvalidArgument("view voxel must be in [0.001, 1] m");
  if (max_points < 1 || max_points > 1000000)
    return InvalidArgument("view points per keyframe must be in [1, 1e6]");
  return Status::Ok();
}

void ViewCloudOptions::Describe(OptionsWriter* out) const {
  out->Add("voxel_m", voxel_m);
  out->Add("max_points", max_points);
}

void AppendViewCloud(const GlobalKeyframeId& id, const CameraCloud* cloud,
                     const ViewCloudOptions& options, std::string* out) {
  const std::vector<std::uint32_t> order =
      cloud ? ViewOrder(id, *cloud, options) : std::vector<std::uint32_t>();
  PutLe(id.agent.value(), 2, out);
  PutLe(cloud ? 1 : 0, 1, out);
  PutLe(0, 1, out);
  PutLe(id.keyframe.value(), 4, out);
  PutLe(order.size(), 4, out);
  out->reserve(out->size() + order.size() * 9 + 3);
  for (std::uint32_t i : order) {
    for (int a = 0; a < 3; ++a) {
      const long mm = std::lround(cloud->points[i][a] * 1e3);
      PutLe(static_cast<std::uint16_t>(static_cast<std::int16_t>(mm)), 2, out);
    }
  }
  for (std::uint32_t i : order)
    out->append(reinterpret_cast<const char*>(cloud->colors[i].data()), 3);
  while (out->size() % 4 != 0) out->push_back('\0');
}

std::string EncodeBase64(std::string_view bytes) {
  static constexpr char kDigits[] =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (std::size_t i = 0; i < bytes.size(); i += 3) {
    const std::size_t n = std::min<std::size_t>(3, bytes.size() - i);
    std::uint32_t v = 0;
    for (std::size_t j = 0; j < 3; ++j)
      v = (v << 8) | (j < n ? static_cast<std::uint8_t>(bytes[i + j]) : 0u);
    for (std::size_t j = 0; j < 4; ++j)
      out.push_back(j <= n ? kDigits[(v >> (18 - 6 * j)) & 63] : '=');
  }
  return out;
}

StatusOr<std::vector<ViewCloud>> ParseViewClouds(std::string_view bytes) {
  std::vector<ViewCloud> clouds;
  std::size_t at = 0;
  while (at < bytes.size()) {
    if (bytes.size() - at < kViewCloudHeaderBytes) return Corrupt("view cloud: truncated header");
    ViewCloud c;
    c.id.agent = AgentId(static_cast<std::uint16_t>(GetLe(bytes, at, 2)));
    c.found = GetLe(bytes, at + 2, 1) != 0;
    c.id.keyframe = KeyframeId(static_cast<std::uint32_t>(GetLe(bytes, at + 4, 4)));
    const std::uint64_t n = GetLe(bytes, at + 8, 4);
    at += kViewCloudHeaderBytes;
    const std::uint64_t body = (n * 9 + 3) / 4 * 4;
    if (bytes.size() - at < body) return Corrupt("view cloud: truncated points");
    if (!c.found && n != 0) return Corrupt("view cloud: points in a not-found record");
    c.points_mm.resize(n);
    c.colors.resize(n);
    for (std::uint64_t i = 0; i < n; ++i) {
      for (int a = 0; a < 3; ++a) {
        c.points_mm[i][a] = static_cast<std::int16_t>(
            static_cast<std::uint16_t>(GetLe(bytes, at + 6 * i + 2 * a, 2)));
      }
    }
    std::memcpy(c.colors.data(), bytes.data() + at + 6 * n, 3 * n);
    at += body;
    clouds.push_back(std::move(c));
  }
  return clouds;
}

}  // namespace ccmd
