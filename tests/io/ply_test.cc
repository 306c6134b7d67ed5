#include "libccmd/io/ply.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <limits>
#include <utility>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

PointCloud MakeCloud() {
  PointCloud c;
  for (int i = 0; i < 1000; ++i) {
    c.points.emplace_back(i * 0.001f, -i * 0.5f, 3.25f + i);
    c.normals.emplace_back(0, 0, 1);
    c.colors.push_back({static_cast<std::uint8_t>(i), 7, static_cast<std::uint8_t>(255 - i % 256)});
    c.labels.push_back(0x01000000u + i);
  }
  return c;
}

TEST(PlyTest, BinaryRoundTripIsExact) {
  testing::TempDir dir;
  const PointCloud c = MakeCloud();
  ASSERT_TRUE(WritePly(c, dir.File("c.ply")).ok());
  auto r = ReadPly(dir.File("c.ply"));
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  ASSERT_EQ(r->size(), c.size());
  for (std::size_t i = 0; i < c.size(); ++i) {
    ASSERT_EQ(r->points[i], c.points[i]);
    ASSERT_EQ(r->normals[i], c.normals[i]);
    ASSERT_EQ(r->colors[i], c.colors[i]);
    ASSERT_EQ(r->labels[i], c.labels[i]);
  }
}

TEST(PlyTest, HeaderIsTheStandardOneOtherToolsRead) {
  testing::TempDir dir;
  ASSERT_TRUE(WritePly(MakeCloud(), dir.File("c.ply")).ok());
  const std::string data = *ReadFileToString(dir.File("c.ply"));
  const std::string header = data.substr(0, data.find("end_header"));
  EXPECT_NE(header.find("format binary_little_endian 1.0"), std::string::npos);
  EXPECT_NE(header.find("element vertex 1000"), std::string::npos);
  EXPECT_NE(header.find("property uchar red"), std::string::npos);
  EXPECT_NE(header.find("property uint label"), std::string::npos);
  // 3 floats + 3 floats + 3 bytes + 4 bytes per vertex after the header line.
  EXPECT_EQ(data.size() - (data.find("end_header") + 11), 1000u * (12 + 12 + 3 + 4));
}

// The streaming writer writes what WritePly writes, checks the count it announced, and
// leaves nothing behind when it is not finished (a failed export keeps the previous file).
TEST(PlyTest, AVertexWriterChecksItsCountAndLeavesNothingUnfinished) {
  testing::TempDir dir;
  PointCloud cloud;
  for (int i = 0; i < 70000; ++i) {  // over one write buffer
    cloud.points.emplace_back(0.001f * i, -0.5f * i, 3.25f);
    cloud.colors.push_back({static_cast<std::uint8_t>(i), 7, static_cast<std::uint8_t>(i / 3)});
    cloud.labels.push_back(static_cast<std::uint32_t>(i * 31));
  }
  ASSERT_TRUE(WritePly(cloud, dir.File("whole.ply")).ok());
  auto writer = PlyVertexWriter::Open(dir.File("streamed.ply"), cloud.size(), {false, true, true});
  ASSERT_TRUE(writer.ok());
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    (*writer)->Add(cloud.points[i], nullptr, &cloud.colors[i], cloud.labels[i]);
  }
  ASSERT_TRUE((*writer)->Finish().ok());
  EXPECT_EQ(*ReadFileToString(dir.File("streamed.ply")), *ReadFileToString(dir.File("whole.ply")));

  ASSERT_TRUE(WriteFileAtomic(dir.File("kept.ply"), "previous").ok());
  auto short_one = PlyVertexWriter::Open(dir.File("kept.ply"), 3, {false, true, true});
  ASSERT_TRUE(short_one.ok());
  (*short_one)->Add(cloud.points[0], nullptr, &cloud.colors[0], 1);
  EXPECT_EQ((*short_one)->Finish().code(), StatusCode::kInternal);
  {
    auto abandoned = PlyVertexWriter::Open(dir.File("kept.ply"), 1, {false, true, true});
    ASSERT_TRUE(abandoned.ok());
    (*abandoned)->Add(cloud.points[0], nullptr, &cloud.colors[0], 1);
  }
  EXPECT_EQ(*ReadFileToString(dir.File("kept.ply")), "previous");
  std::size_t files = 0;
  for ([[maybe_unused]] const auto& entry : std::filesystem::directory_iterator(dir.path()))
    ++files;
  EXPECT_EQ(files, 3u);  // whole.ply, streamed.ply, kept.ply: no temporary left
}

TEST(PlyTest, ReadsAsciiWithFacesAndOtherPropertyOrder) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("m.ply"),
                              "ply\nformat ascii 1.0\nelement vertex 4\nproperty double z\n"
                              "property double x\nproperty double y\nelement face 1\n"
                              "property list uchar int vertex_indices\nend_header\n"
                              "0 0 0\n0 1 0\n0 1 1\n0 0 1\n4 0 1 2 3\n")
                  .ok());
  auto r = ReadPly(dir.File("m.ply"));
  ASSERT_TRUE(r.ok()) << r.status().ToString();
  ASSERT_EQ(r->size(), 4u);
  EXPECT_EQ(r->points[1], Eigen::Vector3f(1, 0, 0));
  ASSERT_EQ(r->triangles.size(), 2u);  // the quad as a fan
  EXPECT_EQ(r->triangles[1], (std::array<std::uint32_t, 3>{0, 2, 3}));
}

TEST(PlyTest, MalformedFilesAreErrors) {
  testing::TempDir dir;
  const char* header =
      "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
      "property float x\nproperty float y\nproperty float z\nend_header\n";
  ASSERT_TRUE(WriteFileAtomic(dir.File("huge.ply"), std::string(header) + "abc").ok());
  EXPECT_FALSE(ReadPly(dir.File("huge.ply")).ok());  // refused before allocating
  // The same in text, and the shortest text that holds its count.
  const std::string text_header =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n";
  EXPECT_EQ(ParsePly(text_header + "0 0 0\n1 1", "short").status().code(), StatusCode::kCorrupt);
  const auto shortest = ParsePly(text_header + "0 0 0\n1 1 1", "shortest");
  ASSERT_TRUE(shortest.ok()) << shortest.status().ToString();
  EXPECT_EQ(shortest->points[1], Eigen::Vector3f(1, 1, 1));
  ASSERT_TRUE(WriteFileAtomic(dir.File("junk.ply"), "not a ply").ok());
  EXPECT_EQ(ReadPly(dir.File("junk.ply")).status().code(), StatusCode::kCorrupt);
  // Truncated body.
  ASSERT_TRUE(WritePly(MakeCloud(), dir.File("c.ply")).ok());
  std::string data = *ReadFileToString(dir.File("c.ply"));
  data.resize(data.size() - 10);
  ASSERT_TRUE(WriteFileAtomic(dir.File("cut.ply"), data).ok());
  EXPECT_EQ(ReadPly(dir.File("cut.ply")).status().code(), StatusCode::kCorrupt);
  // A vertex that is not a point (NaN, infinite), or whose colour does not fit its byte.
  auto two_vertices = [](float x, float red) {
    std::string ply =
        "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
        "property float y\nproperty float z\nproperty float red\nproperty float green\n"
        "property float blue\nend_header\n";
    for (const float v : {0.f, 0.f, 0.f, 1.f, 2.f, 3.f, x, 1.f, 0.f, red, 5.f, 6.f}) {
      ply.append(reinterpret_cast<const char*>(&v), sizeof v);
    }
    return ply;
  };
  for (const auto& [x, red] : {std::pair<float, float>{std::nanf(""), 4},
                               {std::numeric_limits<float>::infinity(), 4},
                               {0.5f, 300},
                               {0.5f, -1}}) {
    ASSERT_TRUE(WriteFileAtomic(dir.File("bad.ply"), two_vertices(x, red)).ok());
    const auto bad = ReadPly(dir.File("bad.ply"));
    EXPECT_EQ(bad.status().code(), StatusCode::kCorrupt) << x << " " << red;
    EXPECT_NE(bad.status().message().find("vertex 1 "), std::string::npos)
        << bad.status().ToString();
  }
  ASSERT_TRUE(WriteFileAtomic(dir.File("good.ply"), two_vertices(0.5f, 4)).ok());
  const auto good = ReadPly(dir.File("good.ply"));
  ASSERT_TRUE(good.ok()) << good.status().ToString();
  EXPECT_EQ(good->colors[1][0], 4);
}

}  // namespace
}  // namespace ccmd
