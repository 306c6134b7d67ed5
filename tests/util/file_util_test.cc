#include "libccmd/util/file_util.h"

#include <gtest/gtest.h>

#include <filesystem>

#include "tests/support/test_support.h"

namespace ccmd {
namespace {

TEST(FileUtilTest, AtomicWriteReplacesWholeFileAndLeavesNoTemporary) {
  testing::TempDir dir;
  const std::string path = dir.File("a.txt");
  ASSERT_TRUE(WriteFileAtomic(path, "first version, longer").ok());
  ASSERT_TRUE(WriteFileAtomic(path, "second").ok());
  EXPECT_EQ(*ReadFileToString(path), "second");
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir.path())) {
    (void)entry;
    ++files;
  }
  EXPECT_EQ(files, 1);
}

TEST(FileUtilTest, ReadRefusesFilesOverTheLimit) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteFileAtomic(dir.File("big"), std::string(100, 'x')).ok());
  EXPECT_EQ(ReadFileToString(dir.File("big"), 99).status().code(), StatusCode::kOutOfRange);
  EXPECT_EQ(ReadFileToString(dir.File("missing")).status().code(), StatusCode::kNotFound);
}

TEST(FileUtilTest, WriteIntoMissingFolderFails) {
  EXPECT_FALSE(WriteFileAtomic("/nonexistent-ccmd-folder/x.txt", "data").ok());
}

}  // namespace
}  // namespace ccmd
