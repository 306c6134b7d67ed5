// Fuzz target: the PLY reader (reference surfaces and meshes a user gives ccmd_eval and
// ccmd_replay, maps written by the server). An accepted cloud is consistent (one colour, normal
// and label per point where any, every triangle's corners among its points) and finite, and no
// header can make the reader allocate more than the file can hold.

#include <algorithm>
#include <cstring>
#include <string>

#include "libccmd/io/ply.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  std::vector<std::string> files = {
      "ply\nformat ascii 1.0\ncomment a square\nelement vertex 4\nproperty float x\n"
      "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
      "property uchar blue\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
      "0 0 0 255 0 0\n1 0 0 0 255 0\n1 1 0 0 0 255\n0 1 0 9 9 9\n4 0 1 2 3\n",
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty double z\nproperty double x\n"
      "property double y\nproperty float nx\nproperty float ny\nproperty float nz\n"
      "property uint label\nend_header\n1.5 -2 3e-3 0 0 1 7\n-1 2 0.5 1 0 0 4294967295\n",
  };
  // Binary, as the server writes its maps: x y z, colour, label.
  for (const char* endian : {"binary_little_endian", "binary_big_endian"}) {
    std::string ply = std::string("ply\nformat ") + endian +
                      " 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                      "property float z\nproperty uchar red\nproperty uchar green\n"
                      "property uchar blue\nproperty uint label\nend_header\n";
    for (int v = 0; v < 2; ++v) {
      for (const float f : {0.5f * v, -1.0f, 2.25f}) {
        char bytes[4];
        std::memcpy(bytes, &f, 4);
        if (endian[7] == 'b') std::reverse(bytes, bytes + 4);
        ply.append(bytes, 4);
      }
      ply += std::string{static_cast<char>(10 * v), 20, 30};
      ply += std::string("\x01\x00\x00\x00", 4);
    }
    files.push_back(ply);
  }
  std::vector<std::vector<std::uint8_t>> seeds;
  for (const std::string& f : files) seeds.emplace_back(f.begin(), f.end());
  return seeds;
}

std::vector<std::vector<std::uint8_t>> FuzzRegressions() {
  // A text header promising a billion vertices in a few bytes: the points were allocated
  // before the body ran out.
  const std::string huge =
      "ply\nformat ascii 1.0\nelement vertex 190000000\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n0 0 0\n";
  // A vertex that is not a point.
  const std::string not_finite =
      "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
      "property float y\nproperty float z\nend_header\n"
      "\x00\x00\xc0\x7f\x00\x00\x00\x00\x00\x00\x00\x00";
  // Two vertex elements, the second without the first's colours: the points were resized to
  // the second's count and the colours kept the first's.
  const std::string two_vertex_elements =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
      "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
      "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
      "0 0 0 1 2 3\n1 1 1 4 5 6\n2 2 2\n";
  std::vector<std::vector<std::uint8_t>> inputs;
  for (const std::string& s : {huge, not_finite, two_vertex_elements})
    inputs.emplace_back(s.begin(), s.end());
  return inputs;
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  StatusOr<PointCloud> cloud = ParsePly(bytes, "fuzz");
  if (!cloud.ok()) return 0;
  if (!cloud->IsConsistent()) fuzz::FuzzFail("attributes or faces inconsistent");
  if (cloud->size() > size) fuzz::FuzzFail("more vertices than bytes");
  for (std::size_t i = 0; i < cloud->size(); ++i) {
    if (!cloud->points[i].allFinite()) fuzz::FuzzFail("point not finite");
    if (cloud->HasNormals() && !cloud->normals[i].allFinite()) fuzz::FuzzFail("normal not finite");
  }
  return 0;
}
