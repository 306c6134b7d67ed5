#pragma once

// PLY point clouds (and triangle meshes, read only). Written as binary little-endian with
// float x y z, optional float nx ny nz, optional uchar red green blue and optional uint label,
// which CloudCompare, MeshLab and Open3D all read. Reads ASCII and binary (either byte
// order), any property order, the common scalar types, and faces as triangle fans.

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct PointCloud {
  std::vector<Eigen::Vector3f> points;
  std::vector<std::array<std::uint8_t, 3>> colors;      // R, G, B; empty or one per point
  std::vector<Eigen::Vector3f> normals;                 // empty or one per point
  std::vector<std::uint32_t> labels;                    // empty or one per point
  std::vector<std::array<std::uint32_t, 3>> triangles;  // faces (read only)

  std::size_t size() const { return points.size(); }
  bool HasColors() const { return !colors.empty(); }
  bool HasNormals() const { return !normals.empty(); }
  bool HasLabels() const { return !labels.empty(); }
  // True if every optional attribute is empty or has one entry per point and every
  // triangle index is in range.
  bool IsConsistent() const;
};

struct PlyReadOptions {
  std::uint64_t max_vertices = 200'000'000;  // refuse larger files before allocating
  std::uint64_t max_faces = 200'000'000;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

Status WritePly(const PointCloud& cloud, const std::string& path);
StatusOr<PointCloud> ReadPly(const std::string& path, const PlyReadOptions& options = {});

}  // namespace ccmd
