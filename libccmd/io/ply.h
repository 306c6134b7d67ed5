#pragma once

// PLY point clouds (and triangle meshes, read only). Written as binary little-endian with
// float x y z, optional float nx ny nz, optional uchar red green blue and optional uint label,
// which CloudCompare, MeshLab and Open3D all read. Reads ASCII and binary (either byte
// order), any property order, the common scalar types, and faces as triangle fans.

#include <array>
#include <cstdint>
#include <cstdio>
#include <memory>
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

// Writes the vertices of a binary PLY, as WritePly does, one at a time: for clouds made on
// the fly and too large to hold twice. The count is stated first; Finish checks it and puts
// the file in place atomically (a writer destroyed unfinished leaves nothing behind).
class PlyVertexWriter {
 public:
  struct Layout {
    bool normals = false;
    bool colors = false;
    bool labels = false;
  };
  static StatusOr<std::unique_ptr<PlyVertexWriter>> Open(const std::string& path, std::size_t count,
                                                         Layout layout);
  ~PlyVertexWriter();
  PlyVertexWriter(const PlyVertexWriter&) = delete;
  PlyVertexWriter& operator=(const PlyVertexWriter&) = delete;

  // The attributes the layout names are read; the others may be null.
  void Add(const Eigen::Vector3f& point, const Eigen::Vector3f* normal,
           const std::array<std::uint8_t, 3>* color, std::uint32_t label);
  Status Finish();

 private:
  PlyVertexWriter() = default;
  Status Flush();

  std::string path_, temp_;
  std::FILE* file_ = nullptr;
  Layout layout_;
  std::size_t count_ = 0, added_ = 0;
  std::vector<char> buffer_;
  bool failed_ = false;
};
StatusOr<PointCloud> ReadPly(const std::string& path, const PlyReadOptions& options = {});
// The same from a PLY file's bytes; `name` prefixes the error messages (the file's path).
StatusOr<PointCloud> ParsePly(const std::string& data, const std::string& name,
                              const PlyReadOptions& options = {});

}  // namespace ccmd
