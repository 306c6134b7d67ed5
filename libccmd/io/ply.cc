#include "libccmd/io/ply.h"

#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <sstream>

#include "libccmd/util/file_util.h"
#include "libccmd/util/string_util.h"

namespace ccmd {

Status PlyReadOptions::Validate() const {
  if (max_vertices == 0) return InvalidArgument("max_vertices must be positive");
  return Status::Ok();
}

void PlyReadOptions::Describe(OptionsWriter* out) const {
  out->Add("max_vertices", max_vertices);
  out->Add("max_faces", max_faces);
}

bool PointCloud::IsConsistent() const {
  const std::size_t n = points.size();
  if (!colors.empty() && colors.size() != n) return false;
  if (!normals.empty() && normals.size() != n) return false;
  if (!labels.empty() && labels.size() != n) return false;
  for (const auto& t : triangles) {
    if (t[0] >= n || t[1] >= n || t[2] >= n) return false;
  }
  return true;
}

namespace {

// A value that converts to an unsigned integer no larger than `max`.
bool InRange(double v, double max) { return v >= 0 && v <= max; }

template <typename T>
void Append(std::vector<char>* buffer, T value) {
  const char* bytes = reinterpret_cast<const char*>(&value);  // x86/ARM: little-endian hosts
  buffer->insert(buffer->end(), bytes, bytes + sizeof(T));
}

}  // namespace

StatusOr<std::unique_ptr<PlyVertexWriter>> PlyVertexWriter::Open(const std::string& path,
                                                                 std::size_t count, Layout layout) {
  std::unique_ptr<PlyVertexWriter> writer(new PlyVertexWriter());
  writer->path_ = path;
  writer->temp_ = TemporaryPathFor(path);
  writer->layout_ = layout;
  writer->count_ = count;
  writer->file_ = std::fopen(writer->temp_.c_str(), "wb");
  if (writer->file_ == nullptr) {
    return IoError("cannot create " + writer->temp_ + ": " + std::strerror(errno));
  }
  std::ostringstream header;
  header << "ply\nformat binary_little_endian 1.0\ncomment written by ccmd\n"
         << "element vertex " << count << "\n"
         << "property float x\nproperty float y\nproperty float z\n";
  if (layout.normals) header << "property float nx\nproperty float ny\nproperty float nz\n";
  if (layout.colors) header << "property uchar red\nproperty uchar green\nproperty uchar blue\n";
  if (layout.labels) header << "property uint label\n";
  header << "end_header\n";
  const std::string h = header.str();
  writer->buffer_.assign(h.begin(), h.end());
  return writer;
}

PlyVertexWriter::~PlyVertexWriter() {
  if (file_ != nullptr) {
    std::fclose(file_);
    std::remove(temp_.c_str());
  }
}

void PlyVertexWriter::Add(const Eigen::Vector3f& point, const Eigen::Vector3f* normal,
                          const std::array<std::uint8_t, 3>* color, std::uint32_t label) {
  for (int k = 0; k < 3; ++k) Append(&buffer_, point[k]);
  if (layout_.normals) {
    for (int k = 0; k < 3; ++k) Append(&buffer_, (*normal)[k]);
  }
  if (layout_.colors) {
    for (int k = 0; k < 3; ++k) Append(&buffer_, (*color)[k]);
  }
  if (layout_.labels) Append(&buffer_, label);
  ++added_;
  if (buffer_.size() >= (1u << 20)) failed_ |= !Flush().ok();
}

Status PlyVertexWriter::Flush() {
  if (!buffer_.empty() && std::fwrite(buffer_.data(), 1, buffer_.size(), file_) != buffer_.size()) {
    return IoError("write failed for " + temp_);
  }
  buffer_.clear();
  return Status::Ok();
}

Status PlyVertexWriter::Finish() {
  if (file_ == nullptr) return Internal(path_ + ": already finished");
  const bool complete = added_ == count_;
  const bool good = complete && !failed_ && Flush().ok();
  const bool closed = std::fclose(file_) == 0;
  file_ = nullptr;
  if (!good || !closed) {
    std::remove(temp_.c_str());
    if (!complete) {
      return Internal(path_ + ": " + std::to_string(added_) + " vertices written, " +
                      std::to_string(count_) + " announced");
    }
    return IoError("write failed for " + temp_);
  }
  return CommitTemporaryFile(temp_, path_);
}

Status WritePly(const PointCloud& cloud, const std::string& path) {
  if (!cloud.IsConsistent()) return InvalidArgument("point cloud attributes differ in length");
  CCMD_ASSIGN_OR_RETURN(
      std::unique_ptr<PlyVertexWriter> writer,
      PlyVertexWriter::Open(path, cloud.size(),
                            {cloud.HasNormals(), cloud.HasColors(), cloud.HasLabels()}));
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    writer->Add(cloud.points[i], cloud.HasNormals() ? &cloud.normals[i] : nullptr,
                cloud.HasColors() ? &cloud.colors[i] : nullptr,
                cloud.HasLabels() ? cloud.labels[i] : 0);
  }
  return writer->Finish();
}

namespace {

enum class PlyType { kInt8, kUint8, kInt16, kUint16, kInt32, kUint32, kFloat32, kFloat64 };

bool ParsePlyType(std::string_view name, PlyType* type) {
  if (name == "char" || name == "int8")
    *type = PlyType::kInt8;
  else if (name == "uchar" || name == "uint8")
    *type = PlyType::kUint8;
  else if (name == "short" || name == "int16")
    *type = PlyType::kInt16;
  else if (name == "ushort" || name == "uint16")
    *type = PlyType::kUint16;
  else if (name == "int" || name == "int32")
    *type = PlyType::kInt32;
  else if (name == "uint" || name == "uint32")
    *type = PlyType::kUint32;
  else if (name == "float" || name == "float32")
    *type = PlyType::kFloat32;
  else if (name == "double" || name == "float64")
    *type = PlyType::kFloat64;
  else
    return false;
  return true;
}

int TypeSize(PlyType type) {
  switch (type) {
    case PlyType::kInt8:
    case PlyType::kUint8:
      return 1;
    case PlyType::kInt16:
    case PlyType::kUint16:
      return 2;
    case PlyType::kInt32:
    case PlyType::kUint32:
    case PlyType::kFloat32:
      return 4;
    case PlyType::kFloat64:
      return 8;
  }
  return 0;
}

struct Property {
  std::string name;
  PlyType type = PlyType::kFloat32;
  bool is_list = false;
  PlyType count_type = PlyType::kUint8;
};

struct Element {
  std::string name;
  std::uint64_t count = 0;
  std::vector<Property> properties;
};

enum class Format { kAscii, kBinaryLittle, kBinaryBig };

// Reads values from the body in the file's encoding, failing cleanly at the end of data.
class BodyReader {
 public:
  BodyReader(const std::string& data, std::size_t offset, Format format)
      : data_(data), pos_(offset), format_(format) {}

  bool Read(PlyType type, double* value) {
    if (format_ == Format::kAscii) return ReadAscii(value);
    const int size = TypeSize(type);
    if (pos_ + size > data_.size()) return false;
    unsigned char bytes[8];
    std::memcpy(bytes, data_.data() + pos_, size);
    pos_ += size;
    if (format_ == Format::kBinaryBig) {
      for (int i = 0; i < size / 2; ++i) std::swap(bytes[i], bytes[size - 1 - i]);
    }
    switch (type) {
      case PlyType::kInt8:
        *value = static_cast<std::int8_t>(bytes[0]);
        break;
      case PlyType::kUint8:
        *value = bytes[0];
        break;
      case PlyType::kInt16: {
        std::int16_t v;
        std::memcpy(&v, bytes, 2);
        *value = v;
        break;
      }
      case PlyType::kUint16: {
        std::uint16_t v;
        std::memcpy(&v, bytes, 2);
        *value = v;
        break;
      }
      case PlyType::kInt32: {
        std::int32_t v;
        std::memcpy(&v, bytes, 4);
        *value = v;
        break;
      }
      case PlyType::kUint32: {
        std::uint32_t v;
        std::memcpy(&v, bytes, 4);
        *value = v;
        break;
      }
      case PlyType::kFloat32: {
        float v;
        std::memcpy(&v, bytes, 4);
        *value = v;
        break;
      }
      case PlyType::kFloat64: {
        double v;
        std::memcpy(&v, bytes, 8);
        *value = v;
        break;
      }
    }
    return true;
  }

 private:
  bool ReadAscii(double* value) {
    while (pos_ < data_.size() && std::isspace(static_cast<unsigned char>(data_[pos_]))) ++pos_;
    if (pos_ >= data_.size()) return false;
    std::size_t end = pos_;
    while (end < data_.size() && !std::isspace(static_cast<unsigned char>(data_[end]))) ++end;
    auto parsed = ParseDouble(std::string_view(data_).substr(pos_, end - pos_));
    if (!parsed.ok()) return false;
    *value = *parsed;
    pos_ = end;
    return true;
  }

  const std::string& data_;
  std::size_t pos_;
  Format format_;
};

}  // namespace

StatusOr<PointCloud> ReadPly(const std::string& path, const PlyReadOptions& options) {
  CCMD_ASSIGN_OR_RETURN(const std::string data, ReadFileToString(path, 1ull << 36));
  return ParsePly(data, path, options);
}

StatusOr<PointCloud> ParsePly(const std::string& data, const std::string& path,
                              const PlyReadOptions& options) {
  const std::size_t header_end = data.find("end_header");
  if (data.compare(0, 3, "ply") != 0 || header_end == std::string::npos) {
    return Corrupt(path + " is not a PLY file");
  }
  std::size_t body = data.find('\n', header_end);
  if (body == std::string::npos) return Corrupt(path + ": header not terminated");
  ++body;

  Format format = Format::kAscii;
  std::vector<Element> elements;
  std::istringstream header(data.substr(0, header_end));
  std::string line;
  bool have_format = false;
  while (std::getline(header, line)) {
    const auto f = SplitWhitespace(line);
    if (f.empty() || f[0] == "ply" || f[0] == "comment" || f[0] == "obj_info") continue;
    if (f[0] == "format" && f.size() >= 2) {
      if (f[1] == "ascii")
        format = Format::kAscii;
      else if (f[1] == "binary_little_endian")
        format = Format::kBinaryLittle;
      else if (f[1] == "binary_big_endian")
        format = Format::kBinaryBig;
      else
        return Unsupported(path + ": unknown PLY format " + std::string(f[1]));
      have_format = true;
    } else if (f[0] == "element" && f.size() == 3) {
      auto count = ParseInt(f[2]);
      if (!count.ok() || *count < 0) return Corrupt(path + ": bad element count");
      elements.push_back({std::string(f[1]), static_cast<std::uint64_t>(*count), {}});
    } else if (f[0] == "property" && !elements.empty()) {
      Property p;
      if (f.size() == 5 && f[1] == "list") {
        p.is_list = true;
        if (!ParsePlyType(f[2], &p.count_type) || !ParsePlyType(f[3], &p.type)) {
          return Corrupt(path + ": bad list property type");
        }
        p.name = std::string(f[4]);
      } else if (f.size() == 3) {
        if (!ParsePlyType(f[1], &p.type)) return Corrupt(path + ": bad property type");
        p.name = std::string(f[2]);
      } else {
        return Corrupt(path + ": bad property line '" + line + "'");
      }
      elements.back().properties.push_back(p);
    } else {
      return Corrupt(path + ": unexpected header line '" + line + "'");
    }
  }
  if (!have_format) return Corrupt(path + ": no format line");

  PointCloud cloud;
  BodyReader reader(data, body, format);
  bool vertices_read = false;
  for (const Element& element : elements) {
    const bool is_vertex = element.name == "vertex";
    const bool is_face = element.name == "face";
    if (is_vertex) {
      if (vertices_read) return Corrupt(path + ": a second vertex element");
      if (element.count > options.max_vertices) {
        return OutOfRange(path + ": " + std::to_string(element.count) +
                          " vertices exceed the limit");
      }
      // A binary file must hold at least count * (bytes per vertex): check before allocating.
      if (format != Format::kAscii) {
        std::uint64_t bytes_per_vertex = 0;
        for (const auto& p : element.properties)
          bytes_per_vertex += p.is_list ? 1 : TypeSize(p.type);
        if (element.count * bytes_per_vertex > data.size() - body) {
          return Corrupt(path + ": file shorter than its vertex count says");
        }
      } else if (element.count * 2 * element.properties.size() > data.size() - body + 1) {
        // Text needs a character and a separator for each value at least.
        return Corrupt(path + ": file shorter than its vertex count says");
      }
      int ix = -1, iy = -1, iz = -1, inx = -1, iny = -1, inz = -1, ir = -1, ig = -1, ib = -1,
          il = -1;
      for (int k = 0; k < static_cast<int>(element.properties.size()); ++k) {
        const std::string& n = element.properties[k].name;
        if (n == "x")
          ix = k;
        else if (n == "y")
          iy = k;
        else if (n == "z")
          iz = k;
        else if (n == "nx")
          inx = k;
        else if (n == "ny")
          iny = k;
        else if (n == "nz")
          inz = k;
        else if (n == "red" || n == "r")
          ir = k;
        else if (n == "green" || n == "g")
          ig = k;
        else if (n == "blue" || n == "b")
          ib = k;
        else if (n == "label")
          il = k;
      }
      if (ix < 0 || iy < 0 || iz < 0) return Corrupt(path + ": vertices have no x y z");
      const bool normals = inx >= 0 && iny >= 0 && inz >= 0;
      const bool colors = ir >= 0 && ig >= 0 && ib >= 0;
      cloud.points.resize(element.count);
      if (normals) cloud.normals.resize(element.count);
      if (colors) cloud.colors.resize(element.count);
      if (il >= 0) cloud.labels.resize(element.count);
      std::vector<double> values(element.properties.size());
      for (std::uint64_t i = 0; i < element.count; ++i) {
        for (std::size_t k = 0; k < element.properties.size(); ++k) {
          const Property& p = element.properties[k];
          if (p.is_list) return Unsupported(path + ": list property on vertices");
          if (!reader.Read(p.type, &values[k])) {
            return Corrupt(path + ": truncated at vertex " + std::to_string(i));
          }
        }
        cloud.points[i] = Eigen::Vector3f(values[ix], values[iy], values[iz]);
        if (normals) cloud.normals[i] = Eigen::Vector3f(values[inx], values[iny], values[inz]);
        // Distances and fits over a cloud are meaningless with one NaN or infinite point in
        // it, and a colour or label outside its type does not convert.
        if (!cloud.points[i].allFinite() || (normals && !cloud.normals[i].allFinite())) {
          return Corrupt(path + ": vertex " + std::to_string(i) + " is not finite");
        }
        if ((colors &&
             !(InRange(values[ir], 255) && InRange(values[ig], 255) && InRange(values[ib], 255))) ||
            (il >= 0 && !InRange(values[il], 4294967295.0))) {
          return Corrupt(path + ": vertex " + std::to_string(i) +
                         " has a colour or label out of range");
        }
        if (colors) {
          cloud.colors[i] = {static_cast<std::uint8_t>(values[ir]),
                             static_cast<std::uint8_t>(values[ig]),
                             static_cast<std::uint8_t>(values[ib])};
        }
        if (il >= 0) cloud.labels[i] = static_cast<std::uint32_t>(values[il]);
      }
      vertices_read = true;
    } else if (is_face && vertices_read) {
      if (element.count > options.max_faces) return OutOfRange(path + ": too many faces");
      for (std::uint64_t i = 0; i < element.count; ++i) {
        for (const Property& p : element.properties) {
          double count = 0;
          if (!reader.Read(p.is_list ? p.count_type : p.type, &count)) {
            return Corrupt(path + ": truncated at face " + std::to_string(i));
          }
          if (!p.is_list) continue;
          if (!(count >= 0 && count <= 64)) return Corrupt(path + ": bad face size");
          std::vector<std::uint32_t> indices(static_cast<std::size_t>(count));
          for (auto& index : indices) {
            double v = 0;
            if (!reader.Read(p.type, &v)) return Corrupt(path + ": truncated face");
            if (!(v >= 0 && v < static_cast<double>(cloud.points.size()))) {  // NaN too
              return Corrupt(path + ": face index out of range");
            }
            index = static_cast<std::uint32_t>(v);
          }
          if (p.name != "vertex_indices" && p.name != "vertex_index") continue;
          for (std::size_t k = 2; k < indices.size(); ++k) {
            cloud.triangles.push_back({indices[0], indices[k - 1], indices[k]});
          }
        }
      }
    } else {
      // Elements other than vertex/face (or faces before vertices) are not used; stop here,
      // since skipping them would need their list sizes.
      if (!vertices_read)
        return Unsupported(path + ": element '" + element.name + "' before vertices");
      break;
    }
  }
  if (!vertices_read) return Corrupt(path + ": no vertex element");
  return cloud;
}

}  // namespace ccmd
